"""Dataclass fields that describe the ROS 2 parameter they become.

A core's configuration (`PlannerConfig`, `StereoParams`, ...) is a dataclass; each field made
with `described` carries what it does, its unit and its range beside its default, and
`area3d_msgs_py.parameters.params_of` turns the fields into the node's declared parameters. One
source: no table of descriptions beside the dataclass. No ROS here (cores import it).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any


def described(
    default: Any,
    description: str,
    unit: str = "",
    range: tuple[float, float] | None = None,  # noqa: A002 - the parameter's own word
    choices: tuple[str, ...] | None = None,
    check: Callable[[Any], str | None] | None = None,
) -> Any:
    """A dataclass field with `default`, documented for its parameter: `description` says what
    it does (and where the value comes from), `unit` its unit ("" for a plain number or a
    name), `range` the inclusive bounds of a number, `choices` the allowed names, `check` a
    function returning what was expected when a value is refused (or None)."""
    meta = {"description": description, "unit": unit, "range": range, "choices": choices}
    meta["check"] = check
    if isinstance(default, list | dict | set):
        return dataclasses.field(default_factory=lambda: type(default)(default), metadata=meta)
    return dataclasses.field(default=default, metadata=meta)


def description_of(field: dataclasses.Field) -> str:
    """The field's description with its unit, e.g. "voxel edge, metres"."""
    meta = field.metadata
    unit = meta.get("unit", "")
    return f"{meta['description']}, {unit}" if unit else meta["description"]


def is_described(field: dataclasses.Field) -> bool:
    return "description" in field.metadata
