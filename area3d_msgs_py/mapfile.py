"""The map file: what the planner and the reconstruction save and load, one versioned format.

A map file is a zip archive of NumPy `.npy` arrays (what `numpy.savez` writes and `numpy.load`
reads, no pickles): `header.npy` holds a JSON object as UTF-8 bytes,

    {"format": "area3d_map", "version": 1, "content": "planner" | "reconstruction",
     "saved_at": ISO 8601 UTC, ...what the content needs to be checked against a running map}

and every other entry is one array the content names (docs/map_format.md lists them). Arrays are
stored uncompressed: a room's planner map is tens of MB and zlib would take seconds to write it;
sparse fields are stored as (ids, values) pairs by their writer.

A save writes a temporary file beside the target and renames it over the target once complete
(`os.replace`, atomic on POSIX), so no reader ever sees a half-written file under the final name
and a failed save leaves the previous file as it was. A load reads and checks everything before
the caller changes its running map.
"""

from __future__ import annotations

import json
import os
import tempfile
import zipfile
from collections.abc import Callable
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from area3d_msgs_py.errors import InputError

FORMAT = "area3d_map"
VERSION = 1
CONTENTS = ("planner", "reconstruction")
HEADER = "header"
SUFFIX = ".a3map"  # what a save writes; a load reads any name


@dataclass(frozen=True)
class MapFile:
    """A map file's header (a dict, checked) and arrays, as read by `read_map`."""

    path: Path
    header: dict
    arrays: dict[str, np.ndarray]
    size_bytes: int

    def array(
        self,
        name: str,
        dtype: Any = None,
        shape: tuple | None = None,
        finite: bool = False,
        bounds: tuple[float | None, float | None] | None = None,
    ) -> np.ndarray:
        """The array `name`, refused with the file's path named when it is missing or has another
        dtype (`dtype`) or shape (`shape`: None for any length on that axis), with `finite` when
        a value is NaN or inf, and with `bounds` (lo, hi; None: open on that side) when a value
        lies outside them: a value its writer cannot have written would become the running map."""
        if name not in self.arrays:
            raise InputError(f"{self.path}: array {name!r}", "missing", "an area3d map file whole")
        value = self.arrays[name]
        if dtype is not None and value.dtype != np.dtype(dtype):
            raise InputError(f"{self.path}: array {name!r}", str(value.dtype), f"dtype {dtype}")
        if shape is not None and (
            value.ndim != len(shape)
            or any(
                want is not None and got != want
                for got, want in zip(value.shape, shape, strict=True)
            )
        ):
            raise InputError(f"{self.path}: array {name!r}", value.shape, f"shape {shape}")
        if finite and not np.isfinite(value).all():
            raise InputError(f"{self.path}: array {name!r}", "NaN or inf", "finite values")
        if bounds is not None and value.size:
            lo, hi = bounds
            below = np.zeros(value.shape, bool) if lo is None else value < lo
            above = np.zeros(value.shape, bool) if hi is None else value > hi
            if (out := int(np.count_nonzero(below | above))) > 0:
                worst = value[below | above]
                found = f"{out} values outside, from {worst.min():g} to {worst.max():g}"
                expected = (
                    f"values >= {lo:g}" if hi is None
                    else f"values <= {hi:g}" if lo is None else f"values in [{lo:g}, {hi:g}]"
                )  # fmt: skip
                raise InputError(f"{self.path}: array {name!r}", found, expected)
        return value

    def require(self, fields: dict[str, str]) -> None:
        """Refuse a header whose entries in `fields` (name -> one of `HEADER_KINDS`) are missing
        or of another kind, the file and the entry named: what a reader turns into its map must
        be there and of the kind it expects, or the file is refused before anything changes."""
        for name, kind in fields.items():
            check, expected = HEADER_KINDS[kind]
            if name not in self.header:
                raise InputError(f"{self.path}: {name}", "missing", f"{expected} in the header")
            if not check(self.header[name]):
                raise InputError(f"{self.path}: {name}", self.header[name], expected)


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _is_count(value: Any) -> bool:
    return _is_int(value) and value >= 0


def _is_number(value: Any) -> bool:
    return (_is_int(value) or isinstance(value, float)) and bool(np.isfinite(value))


#: kind -> (check, what was expected): the kinds of header entries `MapFile.require` checks
HEADER_KINDS: dict[str, tuple[Callable[[Any], bool], str]] = {
    "count": (_is_count, "an integer >= 0"),
    "count or null": (lambda v: v is None or _is_count(v), "an integer >= 0 or null"),
    "integer": (_is_int, "an integer"),
    "number >= 0 or null": (
        lambda v: v is None or (_is_number(v) and v >= 0),
        "a finite number >= 0 or null",
    ),
    "bool": (lambda v: isinstance(v, bool), "true or false"),
    "integers or null": (
        lambda v: v is None or (isinstance(v, list) and all(_is_int(x) for x in v)),
        "a list of integers or null",
    ),
    "camera": (
        lambda v: (
            isinstance(v, dict)
            and _is_number(v.get("hfov_deg"))
            and 0 < v["hfov_deg"] < 180
            and _is_count(v.get("width"))
            and _is_count(v.get("height"))
            and v["width"] > 0
            and v["height"] > 0
        ),
        "{hfov_deg: (0, 180), width: integer > 0, height: integer > 0}",
    ),
}


def resolve(path: str | os.PathLike) -> Path:
    """`path` as an absolute path (relative to the working directory); an empty one refused, and
    one ending in a separator (a directory's name: "mesh.ply/" would write mesh.ply)."""
    if not str(path).strip():
        raise InputError("path", str(path), "a file path")
    if str(path).endswith(("/", os.sep)):
        raise InputError("path", str(path), "a file path, not a directory (no trailing '/')")
    return Path(os.path.abspath(os.path.expanduser(str(path))))


def write_file(
    path: str | os.PathLike, write: Callable[[Path], None], suffix: str = ".tmp"
) -> tuple[Path, int]:
    """Write the file `path` atomically: `write(tmp)` fills a temporary file (ending in `suffix`)
    beside it, which is flushed to the disk and renamed over `path`. (The absolute path, its size
    in bytes.) A directory as `path`, or one that does not exist or cannot be written, is refused
    by name before anything is written; a failure while writing removes the temporary file and
    leaves any previous file untouched."""
    target = resolve(path)
    if target.is_dir():
        raise InputError("path", str(target), "a file path, not a directory")
    folder = target.parent
    if not folder.is_dir():
        why = "is not a directory" if folder.exists() else "does not exist"
        raise InputError("path", str(target), f"a path in an existing directory ({folder} {why})")
    if not os.access(folder, os.W_OK):
        raise InputError(
            "path", str(target), f"a path in a directory this node may write ({folder})"
        )
    replace_atomically(target, write, suffix)
    return target, target.stat().st_size


def replace_atomically(
    target: Path, write: Callable[[Path], None], suffix: str = ".tmp", sync: bool = True
) -> None:
    """`write(tmp)` on a temporary file beside `target` (hidden, a name of its own, ending in
    `suffix`: `np.savez` appends ".npz" to a name without it), flushed to the disk with `sync`,
    then renamed over `target` (atomic on POSIX): a reader sees the old complete file or the new
    one, never a torn one. A failure removes the temporary file and leaves `target` untouched."""
    try:
        # the name cut short: a legal name of 255 bytes plus these would be too long
        prefix = f".{target.name[:64]}."
        fd, name = tempfile.mkstemp(prefix=prefix, suffix=suffix, dir=target.parent)
    except OSError as exc:  # e.g. a directory that says it is writable and is not (/proc)
        raise OSError(
            exc.errno, f"no file can be created in {target.parent} for {target} ({exc.strerror})"
        ) from exc
    os.close(fd)
    tmp = Path(name)
    try:
        write(tmp)
        if sync:
            with tmp.open("rb") as written:
                os.fsync(written.fileno())
        # the mode of the file replaced, or the one a new file gets (mkstemp's: the owner's
        # only); set once written, so that a read-only mode does not stop the write
        os.chmod(tmp, target.stat().st_mode & 0o777 if target.exists() else 0o666 & ~UMASK)
        os.replace(tmp, target)
    except BaseException as exc:
        tmp.unlink(missing_ok=True)
        if not isinstance(exc, OSError) or exc.filename is not None or str(target) in str(exc):
            raise
        # a full disk says only "No space left on device": the answer names the file
        message = f"{target} not written: {exc.strerror or exc}"
        raise (OSError(exc.errno, message) if exc.errno else OSError(message)) from exc


def _umask() -> int:
    """The process's umask, read once at import (POSIX reads it only by setting it, which is
    process-wide: not done again while node threads may be creating files)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


UMASK = _umask()


def write_map(
    path: str | os.PathLike,
    content: str,
    header: dict,
    arrays: dict,
    world_frame: str | None = None,
) -> tuple[Path, int]:
    """Write a map file of `content` atomically (`write_file`): (the absolute path, its size in
    bytes). `header` is the content's part of the header (JSON-serialisable); `arrays` maps names
    to NumPy arrays; `world_frame` the frame the map is expressed in (None: not recorded)."""
    if content not in CONTENTS:
        raise InputError("content", content, f"one of {', '.join(CONTENTS)}")
    target = resolve(path)
    if not target.is_dir() and target.suffix.lower() != SUFFIX:  # a folder: `write_file` says so
        # a map written as mesh.ply would be taken for a mesh and fail in every mesh viewer
        raise InputError(
            "path", str(target), f"a file name ending in {SUFFIX} (export_mesh writes .ply)"
        )
    if HEADER in arrays:
        raise InputError("arrays", HEADER, "names other than 'header'")
    meta = {
        "format": FORMAT,
        "version": VERSION,
        "content": content,
        "saved_at": datetime.now(UTC).isoformat(timespec="seconds"),
        **({} if world_frame is None else {"world_frame": world_frame}),
        **header,
    }
    encoded = np.frombuffer(json.dumps(meta, sort_keys=True).encode(), np.uint8)

    def write(tmp: Path) -> None:
        with tmp.open("wb") as out:
            np.savez(out, **{HEADER: encoded}, **{k: np.asarray(v) for k, v in arrays.items()})

    return write_file(path, write)


def read_map(path: str | os.PathLike, content: str, world_frame: str | None = None) -> MapFile:
    """Read a map file of `content` whole. Refused by name, with nothing returned: a missing
    file, one that is not a complete map file (truncated, another program's), another content,
    a format version this code does not know, or a map recorded in a frame other than
    `world_frame` (when given; a file that records none is taken)."""
    source = resolve(path)
    if not source.is_file():
        raise InputError("path", str(source), "an existing map file")
    try:
        with np.load(source, allow_pickle=False) as archive:
            arrays = {name: archive[name] for name in archive.files}
    except (zipfile.BadZipFile, ValueError, OSError, EOFError, KeyError) as exc:
        # numpy takes a file that is no zip archive for a pickle and advises loading it unsafely
        why = (
            "not a zip archive, or one cut short" if not zipfile.is_zipfile(source)
            else f"read failed: {exc}"
        )  # fmt: skip
        raise InputError("path", str(source), f"a complete area3d map file ({why})") from exc
    if HEADER not in arrays:
        raise InputError("path", str(source), f"an area3d map file (no {HEADER!r} entry)")
    try:
        header = json.loads(arrays.pop(HEADER).tobytes().decode())
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError("path", str(source), f"an area3d map file (header: {exc})") from exc
    if not isinstance(header, dict) or header.get("format") != FORMAT:
        found = header.get("format") if isinstance(header, dict) else header
        raise InputError(f"{source}: format", found, repr(FORMAT))
    if header.get("version") != VERSION:
        raise InputError(f"{source}: version", header.get("version"), f"{VERSION}")
    if header.get("content") != content:
        raise InputError(f"{source}: content", header.get("content"), f"{content!r}")
    saved_frame = header.get("world_frame", world_frame)
    if world_frame is not None and saved_frame != world_frame:
        raise InputError(
            f"{source}: world_frame", saved_frame, f"{world_frame!r} (the running node's)"
        )
    return MapFile(source, header, arrays, source.stat().st_size)


def check_same(source: Path, field: str, saved: Any, running: Any, tol: float = 1e-9) -> None:
    """Refuse a map whose `field` (a number or a sequence of numbers, or a string) differs from
    the running map's: the file and both values named."""
    if isinstance(running, str) or isinstance(saved, str):
        same = saved == running
    else:
        b = np.asarray(running, dtype=np.float64)
        try:  # a header entry of another kind (a string, an object) is refused by name too
            a = np.asarray(saved, dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise InputError(
                f"{source}: {field}", saved, f"{running} (the running map's; numbers)"
            ) from exc
        same = a.shape == b.shape and bool(np.all(np.abs(a - b) <= tol))
    if not same:
        raise InputError(f"{source}: {field}", saved, f"{running} (the running map's)")
