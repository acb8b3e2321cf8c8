"""The one error type for bad input at a package boundary."""

from __future__ import annotations

from typing import Any

# Long reprs (a whole image buffer, a 1M-point cloud) would drown the message.
MAX_REPR_CHARS = 120


def _short_repr(value: Any) -> str:
    text = repr(value)
    if len(text) > MAX_REPR_CHARS:
        text = text[: MAX_REPR_CHARS - 3] + "..."
    return text


class InputError(ValueError):
    """Bad input rejected at a boundary; the message names the field, the value and what was expected.

    >>> str(InputError("encoding", "yuv422", "one of rgb8, bgr8"))
    "encoding: got 'yuv422', expected one of rgb8, bgr8"
    """

    def __init__(self, field: str, value: Any, expected: str) -> None:
        self.field = field
        self.value = value
        self.expected = expected
        super().__init__(f"{field}: got {_short_repr(value)}, expected {expected}")

    def __reduce__(self):
        return (type(self), (self.field, self.value, self.expected))
