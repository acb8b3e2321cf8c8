"""Building the visibility masks (`VisibilityCache.build` / `update`, `visibility.py`): the map's
geometry checked and prepared (`Geometry`), and every candidate position's masks, built in full
(`zbuffer.seed_view_masks`) or brought up to date from the previous cache (`incremental.py`),
on worker threads, assembled into a cache (`assemble`).
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from area3d_msgs_py.errors import InputError
from area3d_msgs_py.grid import GridSpec
from area3d_planner import incremental
from area3d_planner.candidates import VisibilityParams
from area3d_planner.fusion import RANGE_BIN
from area3d_planner.incremental_geometry import STAT_NAMES
from area3d_planner.observation import DIRECTION_BINS
from area3d_planner.zbuffer import new_zbuffer, seed_view_masks

if TYPE_CHECKING:
    from area3d_planner.visibility import VisibilityCache

CHUNKS_PER_THREAD = 8  # seed chunks per worker thread when building masks (load balance)


def range_bin_dtype(max_range: float) -> type:
    """The integer type of the masks' range bins (`fusion.RANGE_BIN` metres each) up to
    max_range: uint8 up to 25.5 m, else uint16."""
    return np.uint8 if max_range / RANGE_BIN < np.iinfo(np.uint8).max else np.uint16


def free_side_normals(spec: GridSpec, occupancy: np.ndarray, ids: np.ndarray) -> np.ndarray:
    """(K, 3) unit normals of voxels `ids`: the mean direction to their known-free face neighbours
    (where a surface they hold faces), zero for voxels with none."""
    free = np.asarray(occupancy).reshape(spec.shape) == 0
    ijk = np.stack(np.unravel_index(np.asarray(ids, np.int64), spec.shape), axis=1)
    shape = np.asarray(spec.shape)
    n = np.zeros((ijk.shape[0], 3))
    for axis in range(3):
        for step in (-1, 1):
            nb = ijk.copy()
            nb[:, axis] += step
            ok = (nb[:, axis] >= 0) & (nb[:, axis] < shape[axis])
            hit = np.zeros(ijk.shape[0], bool)
            hit[ok] = free[tuple(nb[ok].T)]
            n[hit, axis] += step
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    return np.divide(n, norm, out=np.zeros_like(n), where=norm > 0)


@dataclass
class Geometry:
    """What a build reads of the map, checked and prepared."""

    spec: GridSpec
    params: VisibilityParams
    occupancy: np.ndarray  # (N,) int8
    seeds: np.ndarray  # (S, 3)
    rotations: np.ndarray  # (S, B, 3, 3)
    record_ids: np.ndarray  # (K,) int32 ascending
    centres: np.ndarray  # (K, 3)
    normals: np.ndarray  # (K, 3)
    occluders: np.ndarray  # (N,) bool

    @classmethod
    def of(
        cls,
        spec: GridSpec,
        params: VisibilityParams,
        occupancy: np.ndarray,
        seeds: np.ndarray,
        rotations: np.ndarray,
        relevant: np.ndarray | None,
        occluders: np.ndarray | None,
    ) -> Geometry:
        occupancy = np.ascontiguousarray(occupancy, dtype=np.int8)
        if occupancy.shape != (spec.num_voxels,):
            raise InputError(
                "occupancy", occupancy.shape, f"({spec.num_voxels},) int8 flat occupancy"
            )
        seeds = np.ascontiguousarray(np.asarray(seeds, dtype=np.float64).reshape(-1, 3))
        rotations = np.asarray(rotations, np.float64)
        if rotations.ndim == 3:
            rotations = np.broadcast_to(rotations, (seeds.shape[0], *rotations.shape))
        # a copy where it is a broadcast: one seed's broadcast is contiguous but read-only, and
        # a read-only array is another type to numba (the lazy greedy compiled twice)
        rotations = np.require(rotations, requirements=("C", "W"))
        if rotations.shape[:1] != seeds.shape[:1] or rotations.shape[2:] != (3, 3):
            raise InputError(
                "rotations", rotations.shape, f"({seeds.shape[0]}, B, 3, 3) view rotations"
            )
        if relevant is None:
            relevant = occupancy != 0
        record_ids = np.flatnonzero(relevant).astype(np.int32)
        if params.incidence:
            normals = free_side_normals(spec, occupancy, record_ids)
        else:
            normals = np.zeros((record_ids.size, 3))
        if occluders is None:
            occluders = occupancy == 1
        return cls(
            spec,
            params,
            occupancy,
            seeds,
            rotations,
            record_ids,
            spec.centers_of(record_ids),
            normals,
            np.asarray(occluders, bool),
        )

    @property
    def tol(self) -> float:
        return 0.7 * self.spec.voxel_size  # the surface layer counts, one behind it does not

    @property
    def bin_template(self) -> np.ndarray:
        return np.zeros(0, range_bin_dtype(self.params.max_range))


def _match(g: Geometry, previous: tuple | None) -> np.ndarray:
    """(S,) int64: the position of each candidate of `g` in the previous cache (same centre and
    view rotations, bit for bit), -1 for a new one (or without a compatible previous cache)."""
    match = np.full(g.seeds.shape[0], -1, np.int64)
    if previous is None:
        return match
    old = previous[0]
    if old.params != g.params or old.spec != g.spec or old.num_bins != g.rotations.shape[1]:
        return match
    where = {
        seed.tobytes() + rot.tobytes(): i
        for i, (seed, rot) in enumerate(zip(old.seeds, old.rotations, strict=True))
    }
    for s, (seed, rot) in enumerate(zip(g.seeds, g.rotations, strict=True)):
        match[s] = where.get(seed.tobytes() + rot.tobytes(), -1)
    return match


def _chunks(positions: np.ndarray, count: int) -> list[np.ndarray]:
    return [c for c in np.array_split(positions, max(1, min(count, positions.size))) if c.size]


def assemble(
    cls: type, g: Geometry, previous: tuple | None, threads: int | None, keep: bool
) -> VisibilityCache:
    """Masks of every candidate view of `g`: built in full, or updated from `previous` (a cache
    and its `incremental.State`) for the positions it holds too; with `keep`, the new cache
    keeps its z-buffers for the next update."""
    params, spec = g.params, g.spec
    n_seeds, n_views = g.seeds.shape[0], g.rotations.shape[1]
    match = _match(g, previous)
    fresh, kept = np.flatnonzero(match < 0), np.flatnonzero(match >= 0)
    change = incremental.Change(g, *previous, match) if kept.size else None
    threads = max(1, min(threads or os.cpu_count() or 1, max(1, n_seeds)))
    per_share = (threads * CHUNKS_PER_THREAD if threads > 1 else 1) / max(1, n_seeds)
    tasks = [("full", c) for c in _chunks(fresh, round(per_share * fresh.size))]
    if change is not None and not change.nothing:
        tasks += [("update", c) for c in _chunks(kept, round(per_share * kept.size))]
    occ_centres = spec.centers_of(np.flatnonzero(g.occluders)) if fresh.size else None
    scratch = threading.local()

    def run(task: tuple) -> tuple:
        kind, idx = task
        if kind == "update":
            if not hasattr(scratch, "update"):
                scratch.update = incremental.new_scratch(params.face_res, spec.num_voxels)
            return kind, idx, change.run(idx, scratch.update)
        if not hasattr(scratch, "zbuf"):
            scratch.zbuf, scratch.dirty = new_zbuffer(params.face_res)
        return (
            kind,
            idx,
            seed_view_masks(
                np.ascontiguousarray(g.seeds[idx]),
                np.ascontiguousarray(g.rotations[idx]),
                occ_centres,
                g.centres,
                g.record_ids,
                g.normals,
                spec.voxel_size,
                params.max_range,
                params.near,
                params.tan_x,
                params.tan_y,
                params.focal,
                params.pixels_per_voxel,
                g.tol,
                scratch.zbuf,
                scratch.dirty,
                RANGE_BIN,
                DIRECTION_BINS,
                g.bin_template,
                keep,
            ),
        )

    if threads == 1 or len(tasks) <= 1:
        results = [run(t) for t in tasks]
    else:
        with ThreadPoolExecutor(max_workers=threads) as pool:
            results = list(pool.map(run, tasks))
    # each position's masks, and its buffer
    pieces: list = [None] * n_seeds
    buffers = incremental.Buffers.empty(n_seeds, params.face_res)
    if change is not None:
        change.finish()
        buffers.take(kept, change.buffers, match[kept])
    if keep:  # the new positions' buffers go into the pool: room for all of them at once
        buffers.reserve(sum(out[5][0].size for kind, _, out in results if kind == "full"))
    for kind, idx, out in results:
        if kind == "update":
            for s, piece in zip(idx, out, strict=True):
                pieces[s] = piece
            continue
        nnz, ids, w, rb, db, (data, rects, offsets) = out
        if keep:
            buffers.add(idx, data, rects, offsets, g.rotations[idx], params)
        counts = nnz.reshape(idx.size, n_views)
        ends = np.cumsum(counts.sum(axis=1))
        for q, s in enumerate(idx):
            a, e = ends[q] - counts[q].sum(), ends[q]
            pieces[s] = (counts[q], ids[a:e], w[a:e], rb[a:e], db[a:e])
    for s in kept:
        if pieces[s] is None:  # nothing it sees changed: its masks as they were
            pieces[s] = change.old_piece(match[s])
    columns = [
        np.concatenate([p[i] for p in pieces]) if pieces else np.zeros(0, dtype)
        for i, dtype in enumerate((np.int64, np.int32, np.float64, g.bin_template.dtype, np.uint8))
    ]
    indptr = np.zeros(columns[0].size + 1, np.int64)
    np.cumsum(columns[0], out=indptr[1:])
    cache = cls(
        spec,
        g.seeds,
        g.rotations,
        indptr,
        columns[1],
        columns[2],
        g.record_ids,
        params,
        columns[3],
        columns[4],
    )
    if keep:
        cache._state = incremental.State(buffers.compacted(), g.occluders, g.normals)
    cache.report = {"positions": n_seeds, "built": int(fresh.size), "updated": int(kept.size)}
    if change is not None:
        cache.report |= change.counts | dict(zip(STAT_NAMES, change.stats.tolist(), strict=True))
    return cache
