"""A saved map file rewritten with one thing changed: how the tests make the damaged files a
map loader must refuse (a header entry missing or of another kind, an array replaced)."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import numpy as np

MISSING = object()  # as a header value: the entry taken out


def rewrite_map(
    source: Path,
    target: Path,
    header: dict | None = None,
    arrays: dict | None = None,
    change: Callable[[dict], None] | None = None,
) -> Path:
    """`source` written again as `target` with the header entries of `header` set (`MISSING`
    removes one), those of `arrays` replaced and `change(header)` applied."""
    with np.load(source, allow_pickle=False) as archive:
        entries = {name: archive[name] for name in archive.files}
    meta = json.loads(entries.pop("header").tobytes().decode())
    for name, value in (header or {}).items():
        if value is MISSING:
            del meta[name]
        else:
            meta[name] = value
    if change is not None:
        change(meta)
    entries |= arrays or {}
    entries["header"] = np.frombuffer(json.dumps(meta).encode(), np.uint8)
    with target.open("wb") as out:
        np.savez(out, **entries)
    return target
