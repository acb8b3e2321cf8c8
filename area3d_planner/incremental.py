"""Incremental update of the visibility masks after the map changed (`VisibilityCache.update`).

A frame changes the occupancy only inside its frustum, up to its range, yet almost every
candidate position of a room sees part of what it changed: a position has to be re-examined,
but only where the change shows. Each position keeps its cube-map z-buffer (cropped to what its
splats wrote). After a frame:

- an occluder that left the map resets the pixels where it was the nearest (the buffer holds its
  range there); those pixels are splatted again from the occluders that cover them;
- an occluder that joined the map is splatted like in a full build (nearest wins);
- a recorded voxel changes visibility only where its pixel changed, or when it joined or left
  the recorded set (or its normal changed, with `incidence`); only those voxels' entries are
  taken out of, or put into, each view's mask, which keeps its entries in voxel order.

So a position whose cube map cannot see any change (out of range, or behind unchanged
occluders) keeps its masks as they are, and the masks equal a full rebuild's exactly: the same
splat footprint (`zbuffer.splat_rect`), the same nearest-wins buffer (the minimum of float32
ranges, whatever the order), the same visibility test and entries (`zbuffer.view_entry`).

Which occluders can cover a reset pixel, and which recorded voxels can lie in a changed pixel,
is found by bricks of BRICK^3 voxels: a brick whose pixels on a face (a conservative rectangle,
`box_face_rect`) meet no flagged TILE x TILE tile is skipped whole.

This module holds the update's Python side (`Buffers`, `State`, `Change`); its kernel,
`update_seeds`, is in `incremental_kernel.py`, the helpers and constants it shares with this
module in `incremental_geometry.py`.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np

from area3d_planner.fusion import RANGE_BIN
from area3d_planner.incremental_geometry import (
    ADDED,
    CHANGED,
    GROW,
    REWEIGHED,
    STATS,
    TILE,
    brick_index,
    grow_buffer,
    tile_maxima,
    view_cells,
)
from area3d_planner.incremental_kernel import update_seeds
from area3d_planner.observation import DIRECTION_BINS

# Buffers are gathered into a new pool when the pool holds more than twice the data in use (plus
# this many values): a position whose crops grow gets its buffer anew at the pool's end, its
# old one left unused, a few dozen positions a frame at object level with the camera's noise.
SPARE_VALUES = 1 << 20


@dataclass
class Buffers:
    """Each position's cube-map z-buffer, cropped to what its splats wrote (see
    `zbuffer.seed_view_masks`): position s's in pool from offsets[s], crops rects[s] (6, 4),
    its faces one after the other; the largest value of each of its tiles (maxima,
    `tile_maxima`) and the views each tile's directions may be in (cells, `view_cells`).

    The pool holds buffers in pool[:used] and has room to spare after: a buffer added (a new
    position, or one whose crops grew) is copied to the end, and the pool is made twice as
    large when it is full. One array, so that the update's kernel takes it as it is (a numba
    list of arrays is compiled afresh in every process: 1.2 s the first time)."""

    pool: np.ndarray  # (capacity,) float32
    used: int
    rects: np.ndarray  # (S, 6, 4) int64
    offsets: np.ndarray  # (S, 6) int64
    maxima: np.ndarray  # (S, 6, nt, nt) float32
    cells: np.ndarray  # (S, 6, nt, nt) uint64

    @classmethod
    def empty(cls, count: int, face_res: int) -> Buffers:
        nt = -(-int(face_res) // TILE)
        return cls(
            np.zeros(0, np.float32),
            0,
            np.zeros((count, 6, 4), np.int64),
            np.zeros((count, 6), np.int64),
            np.zeros((count, 6, nt, nt), np.float32),
            np.zeros((count, 6, nt, nt), np.uint64),
        )

    def reserve(self, values: int) -> None:
        """Make room in the pool for this many more values (one copy of what it holds, if any)."""
        if self.used + values > self.pool.size:
            pool = np.empty(max(self.used + values, 2 * self.pool.size), np.float32)
            pool[: self.used] = self.pool[: self.used]
            self.pool = pool

    def append(self, data: np.ndarray) -> int:
        """Copy data to the end of the pool (made larger when it is full); where it starts."""
        self.reserve(data.size)
        start = self.used
        self.pool[start : start + data.size] = data
        self.used += data.size
        return start

    def take(self, positions: np.ndarray, other: Buffers, theirs: np.ndarray) -> None:
        """Positions `positions` hold `other`'s buffers of its positions `theirs` (its pool is
        shared: call on empty buffers, before `add`)."""
        if self.used:
            raise ValueError("Buffers.take: these buffers already hold data")
        self.pool, self.used = other.pool, other.used
        same = positions.size == self.offsets.shape[0] == other.offsets.shape[0]
        same = same and np.array_equal(positions, theirs)
        for name in ("rects", "offsets", "maxima", "cells"):
            if same:  # the same positions in the same order: their arrays as they are
                setattr(self, name, getattr(other, name))
            else:
                getattr(self, name)[positions] = getattr(other, name)[theirs]

    def add(self, positions, data, rects, offsets, rotations, params) -> None:
        """Positions `positions` hold the buffers in data (their crops rects, offsets into
        data), of views of rotations (len(positions), B, 3, 3) (params: `VisibilityParams`)."""
        self.offsets[positions] = offsets + self.append(data)
        self.rects[positions] = rects
        self.maxima[positions] = tile_maxima(data, rects, offsets, params.face_res)
        self.cells[positions] = view_cells(rotations, params.face_res, params.tan_x, params.tan_y)

    def spans(self) -> tuple[np.ndarray, np.ndarray]:
        """(first, end) (S,) int64: where each position's data lies in the pool."""
        r = self.rects
        rows, cols = r[:, :, 1] - r[:, :, 0] + 1, r[:, :, 3] - r[:, :, 2] + 1
        sizes = np.where(r[:, :, 1] >= r[:, :, 0], rows * cols, 0).sum(axis=1)
        first = self.offsets[:, 0].copy()
        return first, first + sizes

    def compacted(self) -> Buffers:
        """These buffers gathered into a new pool where the pool holds more than twice what is
        in use (positions dropped, buffers grown) plus SPARE_VALUES, else themselves. The new
        pool has room for as much again plus SPARE_VALUES (memory the system gives when it is
        written), so that it needs no copy before it is gathered again."""
        first, end = self.spans()
        live = int((end - first).sum())
        if self.used <= 2 * live + SPARE_VALUES:
            return self
        pool = np.empty(2 * live + SPARE_VALUES, np.float32)
        offsets = np.empty_like(self.offsets)
        at = 0
        for s in range(self.offsets.shape[0]):
            size = int(end[s] - first[s])
            pool[at : at + size] = self.pool[first[s] : end[s]]
            offsets[s] = self.offsets[s] - first[s] + at
            at += size
        return Buffers(pool, live, self.rects, offsets, self.maxima, self.cells)

    @property
    def nbytes(self) -> int:
        return self.pool.nbytes + self.maxima.nbytes + self.cells.nbytes


@dataclass
class State:
    """What an incremental update starts from: the positions' buffers, the occluders they hold,
    the normals of the cache's recorded voxels."""

    buffers: Buffers
    occluders: np.ndarray  # (N,) bool
    normals: np.ndarray  # (K, 3)


def new_scratch(face_res: int, num_voxels: int) -> tuple:
    """Clean scratch of one thread for `update_seeds`: marks of the touched pixels (6, n, n)
    int32 -1, their list and old values; per tile (6, nt, nt) float64, the range windows of
    reset and of changed pixels (inf, -inf), the largest values before, while and after the
    update, a floor of -inf; dirty flags (N,) uint8 of the voxels whose entries change."""
    n, nt = int(face_res), -(-int(face_res) // TILE)
    tiles = (6, nt, nt)
    return (
        np.full((6, n, n), -1, np.int32),
        np.empty(6 * n * n, np.int64),
        np.empty(6 * n * n, np.float32),
        np.full(tiles, np.inf),
        np.full(tiles, -np.inf),
        np.full(tiles, np.inf),
        np.full(tiles, -np.inf),
        np.zeros(tiles),
        np.zeros(tiles),
        np.zeros(tiles),
        np.full(tiles, -np.inf),
        np.zeros(num_voxels, np.uint8),
    )


class Change:
    """How the map changed since a cache was built, and the update of the positions it keeps.

    g: the new geometry (`visibility_build.Geometry`); old: the cache; state: its `State`; match:
    (S,) the old position of each new one (-1: new)."""

    def __init__(self, g, old, state: State, match: np.ndarray) -> None:
        self.g, self.old, self.match = g, old, match
        self.buffers = state.buffers
        spec, n = g.spec, g.spec.num_voxels
        added = np.flatnonzero(g.occluders & ~state.occluders)
        removed = np.flatnonzero(state.occluders & ~g.occluders)
        in_old = np.zeros(n, bool)
        in_old[old.record_ids] = True
        in_new = np.zeros(n, bool)
        in_new[g.record_ids] = True
        status = np.where(in_old[g.record_ids], 0, ADDED).astype(np.uint8)
        if g.params.incidence:
            both = np.flatnonzero(status == 0)
            before = state.normals[np.searchsorted(old.record_ids, g.record_ids[both])]
            moved = np.any(before != g.normals[both], axis=1)
            status[both[moved]] = REWEIGHED
        gone = old.record_ids[~in_new[old.record_ids]]
        changed = np.flatnonzero(status)
        self.nothing = not (added.size or removed.size or changed.size or gone.size)
        self.counts = {"occluders_added": added.size, "occluders_removed": removed.size}
        self.counts |= {"record_changed": changed.size, "record_removed": gone.size}
        self._lock = threading.Lock()
        self.stats = np.zeros(STATS, np.int64)  # STAT_NAMES
        # grown buffers, put into the pool by `finish` once every `run` is over: (position,
        # its crops, its data, its offsets into the data)
        self._grown: list[tuple] = []
        if self.nothing:
            return
        self.occluders = _bricked(spec, np.flatnonzero(g.occluders))
        self.added = _bricked(spec, added)
        self.removed = _bricked(spec, removed)
        order, ptr, lo, hi = brick_index(g.record_ids, spec.shape, g.centres)
        self.record = (g.centres, g.record_ids, g.normals, status, order, ptr, lo, hi)
        order, ptr, lo, hi = brick_index(g.record_ids[changed], spec.shape, g.centres[changed])
        self.changed_record = (changed[order], ptr, lo, hi)
        centres, ptr, lo, hi = _bricked(spec, gone)
        order, _, _, _ = brick_index(gone, spec.shape, spec.centers_of(gone))
        self.removed_record = (centres, gone[order].astype(np.int32), ptr, lo, hi)
        b = g.rotations.shape[1]
        self.old_start = old.indptr[:-1:b][: old.num_seeds].copy()
        self.old_counts = np.diff(old.indptr).reshape(old.num_seeds, b)
        self.old_masks = (old.voxel_ids, old.weights, old.range_bins, old.direction_bins)
        p = g.params
        self.geometry = (
            float(spec.voxel_size),
            float(p.max_range),
            float(p.near),
            float(p.tan_x),
            float(p.tan_y),
            float((p.focal * spec.voxel_size) ** 2),
            float(p.pixels_per_voxel),
            float(g.tol),
            float(RANGE_BIN),
        )

    def _kernel(self, idx, pool, rects, offsets, scratch) -> tuple:
        theirs = self.match[idx]
        old_entries = int(self.old_counts[theirs].sum())
        cap = old_entries + old_entries // 4 + (1 << 16)
        return update_seeds(
            np.ascontiguousarray(self.g.seeds[idx]),
            np.ascontiguousarray(self.g.rotations[idx]),
            pool,
            rects,
            offsets,
            theirs,
            self.buffers.cells,
            self.buffers.maxima,
            self.old_start,
            self.old_counts,
            self.old_masks,
            self.added,
            self.removed,
            self.occluders,
            self.record,
            self.changed_record,
            self.removed_record,
            self.geometry,
            DIRECTION_BINS,
            self.g.bin_template,
            scratch,
            (
                np.empty(cap, np.int32),
                np.empty(cap, np.float64),
                np.empty(cap, self.g.bin_template.dtype),
                np.empty(cap, np.uint8),
            ),
        )

    def run(self, idx: np.ndarray, scratch: tuple) -> list:
        """The new masks of positions idx (new indices, all kept), each (counts (B,), ids,
        weights, range bins, direction bins), or None where they stay as they were; their
        buffers are brought up to date in the pool, or grown (where new occluders splat
        outside their crops) into arrays of their own that `finish` puts into the pool. Runs
        of disjoint positions may run at once."""
        theirs = self.match[idx]
        b = self.buffers
        out = self._kernel(idx, b.pool, b.rects[theirs], b.offsets[theirs], scratch)
        outcome, grow = out[0], out[1]
        with self._lock:
            self.stats += out[2]
        pieces = _pieces(outcome, *out[3:])
        regrow = np.flatnonzero(outcome == GROW)
        if regrow.size:
            grown_data, grown_offsets = [], []
            for q in regrow:
                s = theirs[q]
                data, offset = grow_buffer(b.pool, b.rects[s], b.offsets[s], grow[q])
                grown_data.append(data)
                grown_offsets.append(offset)
            starts = np.cumsum([0] + [d.size for d in grown_data])
            grown = np.concatenate(grown_data)
            offsets = np.array(grown_offsets, np.int64).reshape(-1, 6) + starts[:-1, None]
            again = self._kernel(
                idx[regrow], grown, np.ascontiguousarray(grow[regrow]), offsets, scratch
            )
            for q, piece in zip(regrow, _pieces(*again[:1], *again[3:]), strict=True):
                pieces[q] = piece
            with self._lock:
                for k, q in enumerate(regrow):
                    data = grown[starts[k] : starts[k + 1]]
                    self._grown.append((theirs[q], grow[q], data, grown_offsets[k]))
        return pieces

    def finish(self) -> None:
        """Put the buffers grown by `run` into the pool (after every run is over: the pool may
        be made larger, which the runs' kernels must not see)."""
        b = self.buffers
        for s, rect, data, offset in self._grown:
            b.offsets[s] = offset + b.append(data)
            b.rects[s] = rect
        self._grown = []

    def old_piece(self, s: int) -> tuple:
        """Old position s's masks as they were: (counts (B,), ids, weights, range bins,
        direction bins)."""
        old, b = self.old, self.g.rotations.shape[1]
        lo, hi = old.indptr[s * b], old.indptr[s * b + b]
        return (
            np.diff(old.indptr[s * b : s * b + b + 1]),
            old.voxel_ids[lo:hi],
            old.weights[lo:hi],
            old.range_bins[lo:hi],
            old.direction_bins[lo:hi],
        )


def _bricked(spec, ids: np.ndarray) -> tuple:
    """(centres brick by brick, ptr, lo, hi) of voxels `ids` (see `brick_index`)."""
    centres = spec.centers_of(ids)
    order, ptr, lo, hi = brick_index(ids, spec.shape, centres)
    return np.ascontiguousarray(centres[order]), ptr, lo, hi


def _pieces(outcome, counts, ids, weights, range_bins, direction_bins) -> list:
    """Per position of one `update_seeds` call: its new masks (CHANGED) or None."""
    pieces: list = [None] * outcome.size
    at = 0
    for q in np.flatnonzero(outcome == CHANGED):
        end = at + int(counts[q].sum())
        pieces[q] = (
            counts[q],
            ids[at:end],
            weights[at:end],
            range_bins[at:end],
            direction_bins[at:end],
        )
        at = end
    return pieces
