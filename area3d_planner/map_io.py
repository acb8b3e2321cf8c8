"""The planner's whole map in a map file (`area3d_msgs_py/mapfile.py`, content "planner").

Everything the next view depends on is saved: the fused evidence of every voxel, the frames the
budget counts and the views handed out, the decay of the committed views, the fused camera poses,
the camera the candidates are planned for, the recent frames a late semantic map is fused with
(and the semantic maps fused or waiting), a sequential policy's remaining views, and the map at
the last closed-loop request's frame, whose masks the next request plans from
(`pipeline_masks`). Visibility masks are not saved: they depend on the occupancy alone and are
rebuilt after a load (an update equals a full build, `VisibilityCache.update`), so a mission
resumed from a saved map chooses the same views as the one never stopped.

Per-voxel fields are stored sparse: the ids of the voxels with any evidence and their values.
docs/map_format.md lists every entry.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import replace
from pathlib import Path

import numpy as np

from area3d_msgs_py import mapfile
from area3d_msgs_py.errors import InputError
from area3d_planner.context import SelectedViews
from area3d_planner.server import CachedFrame

CONTENT = "planner"
# the grid's per-voxel evidence (FusedGrid), stored for the voxels where any is non-zero
VOXEL_FIELDS = (
    "conf_sum", "hit_count", "log_residual", "free_count", "sem_sum", "sem_count",
    "best_confidence", "directions",
)  # fmt: skip
# what the evidence can hold (`FusedGrid.apply_depth`, `integrate_semantic`): counts and sums of
# confidences are >= 0, a sum of log(1 - confidence) <= 0, a frame's mean confidence at most 1
# (and a float's rounding); `sem_sum` is left out: a retracted mask can leave it a rounding below 0
VOXEL_BOUNDS = {
    "conf_sum": (0.0, None), "hit_count": (0.0, None), "log_residual": (None, 0.0),
    "free_count": (0.0, None), "sem_count": (0.0, None), "best_confidence": (0.0, 1.0001),
}  # fmt: skip
RANGE_FIELDS = ("range_confidence", "range_hits")
# the header's entries `restore` reads, and their kinds (`mapfile.HEADER_KINDS`)
HEADER_FIELDS = {
    "frames": "count",
    "semantic_frames": "count",
    "committed": "count",
    "initial_frames": "count or null",
    "initial_counted": "count",
    "initial_views": "count or null",
    "last_fused_stamp": "integer",
    "handed_out": "integers or null",
    "has_sequence": "bool",
    "map_version": "count",
    "pipeline_base": "count",
    "base": "integers or null",
    "camera": "camera",
}
# ... and those older files lack (`restore` then takes what a new map starts with)
OPTIONAL_HEADER_FIELDS = {"first_gain": "number >= 0 or null"}


def _poses(poses: list) -> np.ndarray:
    return np.asarray(poses, np.float64).reshape(-1, 4, 4)


def _ragged(pieces: list[np.ndarray], dtype) -> tuple[np.ndarray, np.ndarray]:
    """Concatenated pieces and their (len + 1,) offsets."""
    offsets = np.cumsum([0] + [len(p) for p in pieces]).astype(np.int64)
    values = np.concatenate(pieces).astype(dtype) if pieces else np.zeros(0, dtype)
    return values, offsets


def _pieces(values: np.ndarray, offsets: np.ndarray) -> list[np.ndarray]:
    return [values[a:b] for a, b in zip(offsets[:-1], offsets[1:], strict=True)]


def grid_header(server) -> dict:
    """What a map must match to be loaded into `server`'s: its grid and region."""
    spec = server.grid.spec
    return {
        "voxel_size": spec.voxel_size,
        "origin": list(spec.origin),
        "shape": list(spec.shape),
        "roi_min": [float(v) for v in server.grid.roi_lo],
        "roi_max": [float(v) for v in server.grid.roi_hi],
        "level": server.context.visibility.level,
    }


def snapshot(server) -> tuple[dict, dict]:
    """(header, arrays) of `server`'s map, taken under its lock (a frame being fused waits)."""
    with server._lock:
        grid, context = server.grid, server.context
        n = grid.spec.num_voxels
        evidence = np.zeros(n, bool)
        for name in VOXEL_FIELDS:
            evidence |= getattr(grid, name) != 0
        ids = np.flatnonzero(evidence).astype(np.int64)
        arrays = {"voxel_ids": ids}
        arrays |= {f"voxel_{name}": getattr(grid, name)[ids] for name in VOXEL_FIELDS}
        arrays |= {name: getattr(grid, name).copy() for name in RANGE_FIELDS}
        decay = context.committed_decay
        decayed = np.zeros(0, np.int64) if decay is None else np.flatnonzero(decay != 1.0)
        arrays["decay_ids"] = decayed
        arrays["decay_values"] = np.zeros(0) if decay is None else decay[decayed]
        arrays["camera_poses"] = _poses(context.camera_poses)
        arrays["fused_stamps"] = np.asarray(server._fused_order, np.int64)
        versions = server._stamp_version
        arrays["stamp_versions"] = np.asarray([versions[s] for s in server._fused_order], np.int64)
        arrays["answered_poses"] = _poses([T for T, _ in server._answered])
        arrays["answered_stamps"] = np.asarray([s for _, s in server._answered], np.int64)
        frames = server._frames
        arrays["frame_stamps"] = np.asarray(list(frames), np.int64)
        arrays["frame_depths"] = (
            np.stack([f.depth for f in frames.values()]) if frames else np.zeros((0, 1, 1))
        ).astype(np.float32)
        arrays["frame_K"] = np.asarray([f.K for f in frames.values()], np.float64).reshape(-1, 3, 3)
        arrays["frame_T"] = _poses([f.T for f in frames.values()])
        semantic = server._semantic_of
        arrays["semantic_stamps"] = np.asarray(list(semantic), np.int64)
        arrays["semantic_ids"], arrays["semantic_offsets"] = _ragged(
            [ids for ids, _ in semantic.values()], np.int64
        )
        arrays["semantic_values"], _ = _ragged([v for _, v in semantic.values()], np.float32)
        pending = server._pending_semantic
        arrays["pending_stamps"] = np.asarray(list(pending), np.int64)
        arrays["pending_maps"] = (
            np.stack(list(pending.values())) if pending else np.zeros((0, 1, 1))
        ).astype(np.float32)
        sequence = server._sequence
        arrays["sequence_poses"] = _poses([] if sequence is None else sequence.poses)
        arrays["sequence_gains"] = np.asarray([] if sequence is None else sequence.gains, float)
        base = _base_map(server)
        arrays["base_occupancy"] = np.zeros(0, np.int8) if base is None else base[2]
        hfov_deg, width, height = server.camera()
        header = {
            **grid_header(server),
            "config": {k: v for k, v in vars(server.config).items()},
            "frames": grid.frames,
            "semantic_frames": grid.semantic_frames,
            "committed": server.committed,
            "initial_frames": server.initial_frames,
            "initial_counted": server.initial_counted,
            "initial_views": context.initial_views,
            "first_gain": context.first_gain,
            "last_fused_stamp": server.last_fused_stamp,
            "handed_out": server._handed_out,
            "has_sequence": sequence is not None,
            "map_version": server._map_version,
            "pipeline_base": server._pipeline_base,
            "base": None if base is None else [base[0], base[1]],
            "camera": {"hfov_deg": hfov_deg, "width": width, "height": height},
        }
        return header, arrays


def _base_map(server) -> tuple | None:
    """(map version, stamp, occupancy) of the map the next closed-loop request plans its masks
    from (`pipeline_masks`), when that is not the current map; None when there is none."""
    base = server._pipeline_base
    if base == 0 or base == server._map_version:
        return None
    kept = server._base_map
    if kept is None or kept[0] != base:
        return None
    return kept


def save(server, path, world_frame: str | None = None) -> tuple[Path, int, dict]:
    """Write `server`'s map, expressed in `world_frame`, to `path` atomically: (the absolute
    path, its size, the header)."""
    header, arrays = snapshot(server)
    written, size = mapfile.write_map(path, CONTENT, header, arrays, world_frame)
    return written, size, header


def read(server, path, world_frame: str | None = None) -> mapfile.MapFile:
    """Read a planner map for `server` and check it whole: its grid, region and frame must be
    the running map's, every array present with the dtype and length the header says."""
    loaded = mapfile.read_map(path, CONTENT, world_frame)
    h, source = loaded.header, loaded.path
    for key, running in grid_header(server).items():
        if key not in h:
            raise InputError(f"{source}: {key}", "missing", "a planner map's header whole")
        mapfile.check_same(source, key, h[key], running)
    loaded.require(HEADER_FIELDS)
    loaded.require({k: v for k, v in OPTIONAL_HEADER_FIELDS.items() if k in h})
    n = server.grid.spec.num_voxels
    ids = loaded.array("voxel_ids", np.int64, (None,))
    if ids.size and (ids.min() < 0 or ids.max() >= n):
        raise InputError(
            f"{source}: voxel_ids", [int(ids.min()), int(ids.max())], f"ids in [0, {n})"
        )
    for name in VOXEL_FIELDS:
        dtype = getattr(server.grid, name).dtype
        loaded.array(
            f"voxel_{name}", dtype, (ids.size,), finite=dtype.kind == "f",
            bounds=VOXEL_BOUNDS.get(name),
        )  # fmt: skip
    for name in RANGE_FIELDS:
        loaded.array(name, np.float64, getattr(server.grid, name).shape, bounds=(0.0, None))
    decay_ids = loaded.array("decay_ids", np.int64, (None,))
    loaded.array("decay_values", np.float64, (decay_ids.size,))
    if decay_ids.size and (decay_ids.min() < 0 or decay_ids.max() >= n):
        raise InputError(f"{source}: decay_ids", int(decay_ids.max()), f"ids in [0, {n})")
    stamps = loaded.array("fused_stamps", np.int64, (None,))
    if stamps.size != h["frames"]:
        raise InputError(f"{source}: fused_stamps", stamps.size, f"{h.get('frames')} (frames)")
    loaded.array("camera_poses", np.float64, (stamps.size, 4, 4))
    loaded.array("stamp_versions", np.int64, (stamps.size,))
    answered = loaded.array("answered_stamps", np.int64, (None,))
    loaded.array("answered_poses", np.float64, (answered.size, 4, 4))
    frames = loaded.array("frame_stamps", np.int64, (None,))
    loaded.array("frame_depths", np.float32, (frames.size if frames.size else 0, None, None))
    loaded.array("frame_K", np.float64, (frames.size, 3, 3))
    loaded.array("frame_T", np.float64, (frames.size, 4, 4))
    semantic = loaded.array("semantic_stamps", np.int64, (None,))
    offsets = loaded.array("semantic_offsets", np.int64, (semantic.size + 1,))
    total = int(offsets[-1])
    loaded.array("semantic_ids", np.int64, (total,))
    loaded.array("semantic_values", np.float32, (total,))
    pending = loaded.array("pending_stamps", np.int64, (None,))
    loaded.array("pending_maps", np.float32, (pending.size if pending.size else 0, None, None))
    sequence = loaded.array("sequence_gains", np.float64, (None,))
    loaded.array("sequence_poses", np.float64, (sequence.size, 4, 4))
    base = loaded.array("base_occupancy", np.int8, (None,))
    if h["base"] is not None and len(h["base"]) != 2:
        raise InputError(f"{source}: base", h["base"], "[map version, stamp] or null")
    if h["handed_out"] is not None and len(h["handed_out"]) != 3:
        raise InputError(f"{source}: handed_out", h["handed_out"], "3 integers or null")
    if h["base"] is not None and base.size != n:
        raise InputError(f"{source}: base_occupancy", base.size, f"{n} voxels")
    return loaded


def restore(server, loaded: mapfile.MapFile) -> None:
    """Make `server` (a new one, no frame fused, `read` checked `loaded` against it) hold the
    saved map; its masks are rebuilt from the saved occupancies (the background worker, or now)."""
    h, a = loaded.header, loaded.arrays
    with server._lock:
        grid, context = server.grid, server.context
        ids = a["voxel_ids"]
        for name in VOXEL_FIELDS:
            getattr(grid, name)[ids] = a[f"voxel_{name}"]
        for name in RANGE_FIELDS:
            getattr(grid, name)[:] = a[name]
        grid.frames = int(h["frames"])
        grid.semantic_frames = int(h["semantic_frames"])
        if a["decay_ids"].size or h["committed"]:
            context.committed_decay = np.ones(grid.spec.num_voxels)
            context.committed_decay[a["decay_ids"]] = a["decay_values"]
        camera = h["camera"]
        visibility = replace(
            context.visibility,
            hfov_deg=float(camera["hfov_deg"]),
            width=int(camera["width"]),
            height=int(camera["height"]),
        )
        visibility.validate()
        context.visibility = visibility
        context.camera_poses = [T.copy() for T in a["camera_poses"]]
        context.camera_positions = [T[:3, 3].copy() for T in a["camera_poses"]]
        context.initial_views = h["initial_views"]
        context.first_gain = h.get("first_gain")  # absent from older files: set by the next plan
        stamps = [int(s) for s in a["fused_stamps"]]
        server._fused_order = stamps
        server._fused_stamps = set(stamps)
        server._stamp_version = dict(
            zip(stamps, (int(v) for v in a["stamp_versions"]), strict=True)
        )
        server._map_version = int(h["map_version"])
        server.last_fused_stamp = int(h["last_fused_stamp"])
        server.committed = int(h["committed"])
        server.initial_frames = h["initial_frames"]
        server.initial_counted = int(h["initial_counted"])
        handed = h["handed_out"]
        server._handed_out = None if handed is None else tuple(int(v) for v in handed)
        server._answered = [
            (T.copy(), int(s))
            for T, s in zip(a["answered_poses"], a["answered_stamps"], strict=True)
        ]
        server._frames = OrderedDict(
            (int(s), CachedFrame(d.copy(), K.copy(), T.copy()))
            for s, d, K, T in zip(
                a["frame_stamps"], a["frame_depths"], a["frame_K"], a["frame_T"], strict=True
            )
        )
        server._semantic_of = {
            int(s): (i.copy(), v.copy())
            for s, i, v in zip(
                a["semantic_stamps"],
                _pieces(a["semantic_ids"], a["semantic_offsets"]),
                _pieces(a["semantic_values"], a["semantic_offsets"]),
                strict=True,
            )
        }
        server._pending_semantic = OrderedDict(
            (int(s), m.copy()) for s, m in zip(a["pending_stamps"], a["pending_maps"], strict=True)
        )
        server._sequence = (
            SelectedViews([T.copy() for T in a["sequence_poses"]], list(a["sequence_gains"]))
            if h["has_sequence"]
            else None
        )
        server._pipeline_base = int(h["pipeline_base"])
        if h["base"] is not None:
            version, stamp = (int(v) for v in h["base"])
            server._base_map = (version, stamp, a["base_occupancy"].copy())
        server.rebuild_after_load()
