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
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np
from numba import njit

from area3d_planner.fusion import DIRECTION_BINS, RANGE_BIN
from area3d_planner.zbuffer import (
    MAX_SPLAT_HALF_ANGLE,
    SPLAT_HALF_EXTENT,
    _cube_coords,
    _pixel,
    direction_bin,
    grown,
    splat_alpha,
    splat_rect,
    view_entry,
)

BRICK = 8  # voxels per brick edge
TILE = 16  # pixels per tile edge of the culling masks
ADDED, REWEIGHED = 1, 2  # record status bits: joined the recorded set; its normal changed
UNCHANGED, CHANGED, GROW = 0, 1, 2  # outcome of one position's update
# what an update did, summed over positions (`Change.stats`)
STAT_NAMES = (
    "positions_changed",
    "pixels_reset",
    "occluders_resplatted",
    "voxels_retested",
    "voxels_changed",
)
STATS = len(STAT_NAMES)
# Buffers are gathered into a new pool when the pool holds more than twice the data in use (plus
# this many values): a position whose crops grow gets its buffer anew at the pool's end, its
# old one left unused, a few dozen positions a frame at object level with the camera's noise.
SPARE_VALUES = 1 << 20


def brick_index(ids: np.ndarray, shape: tuple, centres: np.ndarray) -> tuple:
    """Voxels `ids` (K,) (centres (K, 3)) grouped by BRICK^3 bricks: (order (K,) int64, the
    positions of the voxels brick by brick; ptr (nb + 1,) int64, brick b holding
    order[ptr[b]:ptr[b+1]]; lo, hi (nb, 3) float64, the box of its voxel centres)."""
    if ids.size == 0:
        return np.zeros(0, np.int64), np.zeros(1, np.int64), np.zeros((0, 3)), np.zeros((0, 3))
    ijk = np.stack(np.unravel_index(np.asarray(ids, np.int64), shape), axis=1) // BRICK
    dims = np.asarray(shape) // BRICK + 1
    key = (ijk[:, 0] * dims[1] + ijk[:, 1]) * dims[2] + ijk[:, 2]
    order = np.argsort(key, kind="stable")
    keys, starts = np.unique(key[order], return_index=True)
    ptr = np.append(starts, order.size).astype(np.int64)
    ordered = centres[order]
    lo = np.minimum.reduceat(ordered, starts, axis=0)
    hi = np.maximum.reduceat(ordered, starts, axis=0)
    return order.astype(np.int64), ptr, lo, hi


@njit(cache=True, inline="always")
def _at(rect, offset, f, i, j):
    """Index into a position's buffer data of pixel (f, i, j), -1 outside its crop (inf)."""
    if i < rect[f, 0] or i > rect[f, 1] or j < rect[f, 2] or j > rect[f, 3]:
        return -1
    return offset[f] + (i - rect[f, 0]) * (rect[f, 3] - rect[f, 2] + 1) + (j - rect[f, 2])


@njit(cache=True, nogil=True)
def box_face_rect(o, lo, hi, a, sign, t_min, alpha_max, n):
    """(i0, i1, j0, j1): pixels of the face of axis a on side sign (+1/-1) that can hold a point
    of the box [lo, hi] (3,) seen from o (3,), for points whose coordinate along the face's axis
    is at least t_min > 0 (none below), widened by a splat of half angle up to alpha_max (the
    linearised footprint of `zbuffer.splat_rect`, bounded at the ends of the box's range: its
    lower edge u - alpha (1 + u^2) is concave in u, its upper edge convex). i1 < i0: none."""
    b = 1 if a == 0 else 0
    c = 1 if a == 2 else 2
    if sign > 0:
        a0, a1 = lo[a] - o[a], hi[a] - o[a]
    else:
        a0, a1 = o[a] - hi[a], o[a] - lo[a]
    a0 = max(a0, t_min)
    if a1 < a0:
        return 0, -1, 0, -1
    half = 0.5 * n
    rect = np.empty(4, np.int64)
    for q in range(2):
        e = b if q == 0 else c
        m0, m1 = lo[e] - o[e], hi[e] - o[e]
        u_lo = min(m0 / a0, m0 / a1)
        u_hi = max(m1 / a0, m1 / a1)
        low = min(u_lo - alpha_max * (1.0 + u_lo * u_lo), u_hi - alpha_max * (1.0 + u_hi * u_hi))
        high = max(u_lo + alpha_max * (1.0 + u_lo * u_lo), u_hi + alpha_max * (1.0 + u_hi * u_hi))
        if high < -1.0 or low > 1.0:
            return 0, -1, 0, -1
        low = max(low, -1.0)
        high = min(high, 1.0)
        rect[2 * q] = max(int(np.floor((low + 1.0) * half)) - 1, 0)
        rect[2 * q + 1] = min(int(np.floor((high + 1.0) * half)) + 1, n - 1)
    return rect[0], rect[1], rect[2], rect[3]


@njit(cache=True, inline="always")
def _box_distance(o, lo, hi):
    d2 = 0.0
    for a in range(3):
        g = max(lo[a] - o[a], 0.0, o[a] - hi[a])
        d2 += g * g
    return np.sqrt(d2)


@njit(cache=True, nogil=True)
def _brick_meets(o, lo, hi, splat, voxel_size, max_range, window_lo, window_hi, tol, n):
    """Whether a voxel of the brick [lo, hi] seen from o can matter to a flagged tile: land in
    one of its pixels (its splat with `splat`, else the pixel of its centre) at a range within
    the tile's window [window_lo - tol, window_hi + tol] ((6, nt, nt) float64 each; a tile is
    flagged where window_lo <= window_hi)."""
    r_min = _box_distance(o, lo, hi)
    if r_min > max_range:
        return False
    r_max = 0.0
    for a in range(3):
        g = max(abs(lo[a] - o[a]), abs(hi[a] - o[a]))
        r_max += g * g
    r_max = np.sqrt(r_max)
    near = r_min < 2.0 * voxel_size  # at or next to the camera: any direction
    if splat:
        alpha_max = min(SPLAT_HALF_EXTENT * voxel_size / max(r_min, 1e-9), MAX_SPLAT_HALF_ANGLE)
        t_min = min(SPLAT_HALF_EXTENT * voxel_size, MAX_SPLAT_HALF_ANGLE * r_min)
    else:
        alpha_max = 0.0
        t_min = r_min / np.sqrt(3.0)  # the face of a direction is that of its largest coordinate
    t_min *= 1.0 - 1e-9
    slack = 1e-6 * (1.0 + r_max)
    nt = window_lo.shape[1]
    for f in range(6):
        if near:
            i0, i1, j0, j1 = 0, n - 1, 0, n - 1
        else:
            i0, i1, j0, j1 = box_face_rect(o, lo, hi, f // 2, 1 - 2 * (f % 2), t_min, alpha_max, n)
            if i1 < i0 or j1 < j0:
                continue
        for ti in range(i0 // TILE, min(i1 // TILE, nt - 1) + 1):
            for tj in range(j0 // TILE, min(j1 // TILE, nt - 1) + 1):
                w_lo, w_hi = window_lo[f, ti, tj], window_hi[f, ti, tj]
                if w_lo <= w_hi and r_max >= w_lo - tol - slack and r_min <= w_hi + tol + slack:
                    return True
    return False


@njit(cache=True, nogil=True, inline="always")
def _in_window(window_lo, window_hi, f, i0, i1, j0, j1, r):
    """Whether range r lies in the window of a flagged tile holding a pixel of the rectangle
    (i0..i1, j0..j1) of face f (see `_brick_meets`)."""
    for ti in range(i0 // TILE, i1 // TILE + 1):
        for tj in range(j0 // TILE, j1 // TILE + 1):
            if window_lo[f, ti, tj] <= r * (1.0 + 1e-6) and r <= window_hi[f, ti, tj] * (
                1.0 + 1e-6
            ):
                return True
    return False


@njit(cache=True, nogil=True)
def _push(d_q, d_id, d_vis, nd, q, voxel, vis):
    """Append (q, voxel, vis) to the dirty voxels (grown when full)."""
    if nd == d_q.shape[0]:
        d_q, d_id, d_vis = grown(d_q, nd, 2 * nd), grown(d_id, nd, 2 * nd), grown(d_vis, nd, 2 * nd)
    d_q[nd], d_id[nd], d_vis[nd] = q, voxel, vis
    return d_q, d_id, d_vis, nd + 1


@njit(cache=True, nogil=True)
def _pixel_of(o, c, n):
    """(face, i, j) of the pixel holding the direction from o to c (as `zbuffer.visible_from`)."""
    face, u, v = _cube_coords(c[0] - o[0], c[1] - o[1], c[2] - o[2])
    return face, _pixel(u, n), _pixel(v, n)


@njit(cache=True, nogil=True)
def grow_buffer(data, rect, offset, new_rect):
    """The buffer (data, rect (6, 4), offset (6,)) copied into crops new_rect (6, 4) (each
    holding the old one; inf elsewhere): (new data, new offset)."""
    new_offset = np.zeros(6, np.int64)
    size = 0
    for f in range(6):
        new_offset[f] = size
        if new_rect[f, 1] >= new_rect[f, 0]:
            size += (new_rect[f, 1] - new_rect[f, 0] + 1) * (new_rect[f, 3] - new_rect[f, 2] + 1)
    out = np.full(size, np.inf, np.float32)
    for f in range(6):
        for i in range(rect[f, 0], rect[f, 1] + 1):
            for j in range(rect[f, 2], rect[f, 3] + 1):
                out[_at(new_rect, new_offset, f, i, j)] = data[_at(rect, offset, f, i, j)]
    return out, new_offset


@njit(cache=True, nogil=True)
def view_cells(rotations, n, tan_x, tan_y):
    """(S, 6, nt, nt) uint64: for each position's views (rotations (S, B, 3, 3), B <= 64), bit b
    of a cell (its TILE x TILE pixels of the cube map) set where view b's frustum may hold a
    direction of the cell: the frustum lies in the cone of its corner rays around the optical
    axis, the cell in the cone of its corners around its centre; bits of views whose cones are
    apart stay clear. All bits for B > 64."""
    n_seeds, n_views = rotations.shape[0], rotations.shape[1]
    nt = -(-n // TILE)
    out = np.zeros((n_seeds, 6, nt, nt), np.uint64)
    if n_views > 64:
        out[:] = np.uint64(0xFFFFFFFFFFFFFFFF)
        return out
    frustum = np.arctan(np.sqrt(tan_x * tan_x + tan_y * tan_y))
    centre = np.empty(3)
    corner = np.empty(3)
    for f in range(6):
        a = f // 2
        sign = 1.0 - 2.0 * (f % 2)
        b = 1 if a == 0 else 0
        c = 1 if a == 2 else 2
        for ti in range(nt):
            u0, u1 = 2.0 * ti * TILE / n - 1.0, 2.0 * min(n, ti * TILE + TILE) / n - 1.0
            for tj in range(nt):
                v0, v1 = 2.0 * tj * TILE / n - 1.0, 2.0 * min(n, tj * TILE + TILE) / n - 1.0
                centre[a], centre[b], centre[c] = sign, 0.5 * (u0 + u1), 0.5 * (v0 + v1)
                centre /= np.sqrt(centre[0] ** 2 + centre[1] ** 2 + centre[2] ** 2)
                radius = 0.0
                for q in range(4):
                    corner[a] = sign
                    corner[b] = u0 if q < 2 else u1
                    corner[c] = v0 if q % 2 == 0 else v1
                    corner /= np.sqrt(corner[0] ** 2 + corner[1] ** 2 + corner[2] ** 2)
                    dot = centre[0] * corner[0] + centre[1] * corner[1] + centre[2] * corner[2]
                    radius = max(radius, np.arccos(min(1.0, dot)))
                reach = np.cos(min(np.pi, frustum + radius + 1e-6))
                for s in range(n_seeds):
                    bits = np.uint64(0)
                    for v in range(n_views):
                        R = rotations[s, v]
                        dot = R[0, 2] * centre[0] + R[1, 2] * centre[1] + R[2, 2] * centre[2]
                        if dot >= reach:
                            bits |= np.uint64(1) << np.uint64(v)
                    out[s, f, ti, tj] = bits
    return out


@njit(cache=True, nogil=True)
def _one_tile_max(data, rect, offset, f, ti, tj, n):
    """The largest value of tile (f, ti, tj) of a position's buffer (inf unless wholly inside
    its crop: the buffer is inf outside)."""
    i0, i1 = ti * TILE, min(n, ti * TILE + TILE) - 1
    j0, j1 = tj * TILE, min(n, tj * TILE + TILE) - 1
    if rect[f, 1] < rect[f, 0] or i0 < rect[f, 0] or i1 > rect[f, 1]:
        return np.inf
    if j0 < rect[f, 2] or j1 > rect[f, 3]:
        return np.inf
    m = -np.inf
    for i in range(i0, i1 + 1):
        row = _at(rect, offset, f, i, j0)
        for q in range(j1 - j0 + 1):
            m = max(m, data[row + q])
    return m


@njit(cache=True, nogil=True)
def tile_maxima(data, rects, offsets, n):
    """(S, 6, nt, nt) float32: the largest value of each TILE x TILE tile of each position's
    buffer (in data, crops rects (S, 6, 4), offsets (S, 6)), inf for a tile not wholly inside
    its crops."""
    nt = -(-n // TILE)
    out = np.empty((rects.shape[0], 6, nt, nt), np.float32)
    for s in range(rects.shape[0]):
        for f in range(6):
            for ti in range(nt):
                for tj in range(nt):
                    out[s, f, ti, tj] = _one_tile_max(data, rects[s], offsets[s], f, ti, tj, n)
    return out


@njit(cache=True, nogil=True)
def update_seeds(
    seeds,
    rotations,
    pool,
    zrect,
    zoff,
    theirs,
    cells,
    maxima,
    old_start,
    old_counts,
    old_masks,
    added,
    removed,
    occluders,
    record,
    changed_record,
    removed_record,
    geometry,
    direction_bins,
    bin_template,
    scratch,
    out,
):
    """Update the buffers and masks of positions that stay candidates after the map changed.

    seeds (S, 3), rotations (S, B, 3, 3): the positions and their views; their buffers: in
    pool (float32), crops zrect[s] (6, 4), offsets zoff[s] (6,) into it (see
    `zbuffer.seed_view_masks`), updated in place. Position s was theirs[s] in the cache
    updated, whose arrays by position are: the largest value of each tile, maxima (S', 6, nt,
    nt) float32 (`tile_maxima`, updated in place); the views a direction in each tile may be in,
    cells (S', 6, nt, nt) uint64 (`view_cells`); its masks, old_masks = (ids, weights, range
    bins, direction bins), view b of position t at old_start[t] + sum(old_counts[t, :b]),
    old_counts[t, b] entries.

    Voxel sets come brick by brick (`brick_index`: centres in brick order, ptr, lo, hi, ...):
    added / removed: the occluders that joined / left the map; occluders: those of the map now;
    record = (centres (K, 3), ids (K,) int32 ascending, normals (K, 3), status (K,) uint8
    ADDED / REWEIGHED bits, order, ptr, lo, hi): the voxels recorded now; changed_record =
    (positions in record, ptr, lo, hi): those with a status; removed_record = (centres, ids,
    ptr, lo, hi): those recorded before and not now. geometry = (voxel_size, max_range, near,
    tan_x, tan_y, fs2, pixels_per_voxel, tol, range_bin). scratch (`new_scratch`): left as
    found. out: (ids, weights, range bins, direction bins) arrays to write the new masks into
    (grown when they are too small).

    Returns (outcome (S,) int8 UNCHANGED / CHANGED / GROW, grow (S, 6, 4) int64 the crops a GROW
    position needs (its buffer untouched: grow it with `grow_buffer`, then run it again), stats
    (STAT_NAMES), counts (S, B) int64 and the entries (ids, weights, range bins, direction bins)
    of the CHANGED positions' new masks, position after position)."""
    voxel_size, max_range, near, tan_x, tan_y, fs2, ppv, tol, range_bin = geometry
    add_c, add_ptr, add_lo, add_hi = added
    rm_c, rm_ptr, rm_lo, rm_hi = removed
    occ_c, occ_ptr, occ_lo, occ_hi = occluders
    rec_c, rec_ids, rec_n, rec_status, rec_order, rec_ptr, rec_lo, rec_hi = record
    chg_q, chg_ptr, chg_lo, chg_hi = changed_record
    gone_c, gone_ids, gone_ptr, gone_lo, gone_hi = removed_record
    old_ids, old_w, old_r, old_d = old_masks
    mark, touched, old_z, reset_lo, reset_hi, changed_lo, changed_hi = scratch[:7]
    tile_before, tile_max, tile_now, no_floor, dirty_flag = scratch[7:]
    out_ids, out_w, out_r, out_d = out
    cap = out_ids.shape[0]
    n = mark.shape[1]
    nt = reset_lo.shape[1]
    n_seeds, n_views = rotations.shape[0], rotations.shape[1]
    max_bin = np.iinfo(bin_template.dtype).max
    outcome = np.zeros(n_seeds, np.int8)
    stats = np.zeros(STATS, np.int64)
    grow = np.zeros((n_seeds, 6, 4), np.int64)
    counts = np.zeros((n_seeds, n_views), np.int64)
    total = 0
    ins_e = np.empty((n_views, 1024), np.int64)  # per view, the dirty voxels it gets ...
    ins_w = np.empty((n_views, 1024), np.float64)  # ... their weights ...
    ins_r = np.empty((n_views, 1024), np.int64)  # ... and range bins
    ins_count = np.zeros(n_views, np.int64)
    d_q = np.empty(16, np.int64)  # dirty voxels: record position (-1: left the record) ...
    d_id = np.empty(16, np.int64)  # ... voxel id ...
    d_vis = np.empty(16, np.bool_)  # ... visible now
    for s in range(n_seeds):
        o = seeds[s]
        data = pool
        rect = zrect[s]
        offset = zoff[s]
        # 0. the crops must hold every pixel a new occluder covers (full faces always do)
        need = False
        full = True
        for f in range(6):
            full = full and rect[f, 0] == 0 and rect[f, 1] == n - 1
            full = full and rect[f, 2] == 0 and rect[f, 3] == n - 1
            for q in range(4):
                grow[s, f, q] = rect[f, q]
        for k in range(0 if full else add_c.shape[0]):
            dx, dy, dz = add_c[k, 0] - o[0], add_c[k, 1] - o[1], add_c[k, 2] - o[2]
            r = np.sqrt(dx * dx + dy * dy + dz * dz)
            if r < 1e-9 or r > max_range:
                continue
            alpha = splat_alpha(r, voxel_size)
            for a in range(3):
                f, i0, i1, j0, j1 = splat_rect(dx, dy, dz, r, alpha, a, n)
                if f < 0:
                    continue
                if rect[f, 1] >= rect[f, 0]:
                    if i0 >= rect[f, 0] and i1 <= rect[f, 1]:
                        if j0 >= rect[f, 2] and j1 <= rect[f, 3]:
                            continue
                need = True
                g = grow[s, f]
                if g[1] < g[0]:
                    g[0], g[1], g[2], g[3] = i0, i1, j0, j1
                else:
                    g[0], g[1] = min(g[0], i0), max(g[1], i1)
                    g[2], g[3] = min(g[2], j0), max(g[3], j1)
        if need:
            outcome[s] = GROW
            continue
        # the farthest value of each tile: a voxel farther than that cannot change it
        tile_before[:] = maxima[theirs[s]]
        tile_max[:] = tile_before
        # A. an occluder that left resets the pixels where it was the nearest
        n_touched = 0
        for bi in range(rm_ptr.shape[0] - 1):
            if not _brick_meets(
                o, rm_lo[bi], rm_hi[bi], True, voxel_size, max_range, no_floor, tile_max, 0.0, n
            ):
                continue
            for k in range(rm_ptr[bi], rm_ptr[bi + 1]):
                dx, dy, dz = rm_c[k, 0] - o[0], rm_c[k, 1] - o[1], rm_c[k, 2] - o[2]
                r = np.sqrt(dx * dx + dy * dy + dz * dz)
                if r < 1e-9 or r > max_range:
                    continue
                rf = np.float32(r)
                alpha = splat_alpha(r, voxel_size)
                for a in range(3):
                    f, i0, i1, j0, j1 = splat_rect(dx, dy, dz, r, alpha, a, n)
                    if f < 0:
                        continue
                    for i in range(i0, i1 + 1):
                        for j in range(j0, j1 + 1):
                            idx = _at(rect, offset, f, i, j)
                            if idx < 0 or data[idx] < rf or mark[f, i, j] >= 0:
                                continue
                            mark[f, i, j] = n_touched
                            touched[n_touched] = (f * n + i) * n + j
                            old_z[n_touched] = data[idx]
                            n_touched += 1
                            data[idx] = np.inf
                            tile_max[f, i // TILE, j // TILE] = np.inf
        n_reset = n_touched  # the pixels touched first are the reset ones
        stats[1] += n_reset
        # C. an occluder that joined is splatted (nearest wins)
        for bi in range(add_ptr.shape[0] - 1):
            if not _brick_meets(
                o, add_lo[bi], add_hi[bi], True, voxel_size, max_range, no_floor, tile_max, 0.0, n
            ):
                continue
            for k in range(add_ptr[bi], add_ptr[bi + 1]):
                dx, dy, dz = add_c[k, 0] - o[0], add_c[k, 1] - o[1], add_c[k, 2] - o[2]
                r = np.sqrt(dx * dx + dy * dy + dz * dz)
                if r < 1e-9 or r > max_range:
                    continue
                alpha = splat_alpha(r, voxel_size)
                for a in range(3):
                    f, i0, i1, j0, j1 = splat_rect(dx, dy, dz, r, alpha, a, n)
                    if f < 0:
                        continue
                    for i in range(i0, i1 + 1):
                        for j in range(j0, j1 + 1):
                            idx = _at(rect, offset, f, i, j)
                            if r < data[idx]:
                                if mark[f, i, j] < 0:
                                    mark[f, i, j] = n_touched
                                    touched[n_touched] = (f * n + i) * n + j
                                    old_z[n_touched] = data[idx]
                                    n_touched += 1
                                data[idx] = np.float32(r)
        # B. a reset pixel gets the nearest occluder (now) that covers it: one that stayed is at
        # least as far as the one that left (that was the nearest), and counts only if nearer
        # than what the new ones gave it, so each tile of reset pixels has a window of ranges
        for t in range(n_reset):
            f, i, j = touched[t] // (n * n), (touched[t] // n) % n, touched[t] % n
            ti, tj = i // TILE, j // TILE
            reset_lo[f, ti, tj] = min(reset_lo[f, ti, tj], old_z[t])
            reset_hi[f, ti, tj] = max(reset_hi[f, ti, tj], data[_at(rect, offset, f, i, j)])
        for bi in range(occ_ptr.shape[0] - 1 if n_reset > 0 else 0):
            if not _brick_meets(
                o, occ_lo[bi], occ_hi[bi], True, voxel_size, max_range, reset_lo, reset_hi, 0.0, n
            ):
                continue
            stats[2] += occ_ptr[bi + 1] - occ_ptr[bi]
            for k in range(occ_ptr[bi], occ_ptr[bi + 1]):
                dx, dy, dz = occ_c[k, 0] - o[0], occ_c[k, 1] - o[1], occ_c[k, 2] - o[2]
                r = np.sqrt(dx * dx + dy * dy + dz * dz)
                if r < 1e-9 or r > max_range:
                    continue
                alpha = splat_alpha(r, voxel_size)
                for a in range(3):
                    f, i0, i1, j0, j1 = splat_rect(dx, dy, dz, r, alpha, a, n)
                    if f < 0 or not _in_window(reset_lo, reset_hi, f, i0, i1, j0, j1, r):
                        continue
                    for i in range(i0, i1 + 1):
                        for j in range(j0, j1 + 1):
                            m = mark[f, i, j]
                            if m < 0 or m >= n_reset:  # not reset: its value stands
                                continue
                            idx = _at(rect, offset, f, i, j)
                            if r < data[idx]:
                                data[idx] = np.float32(r)
        # D. the pixels whose value changed: each tile's window of ranges whose visibility did
        any_changed = False
        for t in range(n_touched):
            f, i, j = touched[t] // (n * n), (touched[t] // n) % n, touched[t] % n
            z_now = data[_at(rect, offset, f, i, j)]
            if z_now != old_z[t]:
                ti, tj = i // TILE, j // TILE
                changed_lo[f, ti, tj] = min(changed_lo[f, ti, tj], min(z_now, old_z[t]))
                changed_hi[f, ti, tj] = max(changed_hi[f, ti, tj], max(z_now, old_z[t]))
                any_changed = True
        for f in range(6):  # the farthest value of each tile before or now
            for ti in range(nt):
                for tj in range(nt):
                    tile_now[f, ti, tj] = max(tile_before[f, ti, tj], changed_hi[f, ti, tj])
        # E. the recorded voxels whose visibility or entries change
        nd = 0
        for bi in range(chg_ptr.shape[0] - 1):  # joined the record, or a new normal
            if not _brick_meets(
                o, chg_lo[bi], chg_hi[bi], False, voxel_size, max_range, no_floor, tile_now, tol, n
            ):
                continue
            for e in range(chg_ptr[bi], chg_ptr[bi + 1]):
                q = chg_q[e]
                c = rec_c[q]
                dx, dy, dz = c[0] - o[0], c[1] - o[1], c[2] - o[2]
                r = np.sqrt(dx * dx + dy * dy + dz * dz)
                if r < 1e-9 or r > max_range:
                    continue
                f, i, j = _pixel_of(o, c, n)
                idx = _at(rect, offset, f, i, j)
                z_now = data[idx] if idx >= 0 else np.inf
                vis = r <= z_now + tol
                if rec_status[q] & ADDED:
                    if not vis:
                        continue
                else:
                    z_before = old_z[mark[f, i, j]] if mark[f, i, j] >= 0 else z_now
                    if not (vis or r <= z_before + tol):
                        continue
                d_q, d_id, d_vis, nd = _push(d_q, d_id, d_vis, nd, q, rec_ids[q], vis)
        for bi in range(rec_ptr.shape[0] - 1 if any_changed else 0):
            # the voxels behind a changed pixel, at a range whose visibility changed
            if not _brick_meets(
                o,
                rec_lo[bi],
                rec_hi[bi],
                False,
                voxel_size,
                max_range,
                changed_lo,
                changed_hi,
                tol,
                n,
            ):
                continue
            stats[3] += rec_ptr[bi + 1] - rec_ptr[bi]
            for e in range(rec_ptr[bi], rec_ptr[bi + 1]):
                q = rec_order[e]
                if rec_status[q] != 0:
                    continue
                c = rec_c[q]
                dx, dy, dz = c[0] - o[0], c[1] - o[1], c[2] - o[2]
                r = np.sqrt(dx * dx + dy * dy + dz * dz)
                if r < 1e-9 or r > max_range:
                    continue
                f, i, j = _pixel_of(o, c, n)
                m = mark[f, i, j]
                if m < 0:
                    continue
                vis = r <= data[_at(rect, offset, f, i, j)] + tol
                if vis != (r <= old_z[m] + tol):
                    d_q, d_id, d_vis, nd = _push(d_q, d_id, d_vis, nd, q, rec_ids[q], vis)
        for bi in range(gone_ptr.shape[0] - 1):  # left the record: out of the masks it was in
            if not _brick_meets(
                o,
                gone_lo[bi],
                gone_hi[bi],
                False,
                voxel_size,
                max_range,
                no_floor,
                tile_before,
                tol,
                n,
            ):
                continue
            for e in range(gone_ptr[bi], gone_ptr[bi + 1]):
                c = gone_c[e]
                dx, dy, dz = c[0] - o[0], c[1] - o[1], c[2] - o[2]
                r = np.sqrt(dx * dx + dy * dy + dz * dz)
                if r < 1e-9 or r > max_range:
                    continue
                f, i, j = _pixel_of(o, c, n)
                if mark[f, i, j] >= 0:
                    z_before = old_z[mark[f, i, j]]
                else:
                    idx = _at(rect, offset, f, i, j)
                    z_before = data[idx] if idx >= 0 else np.inf
                if r <= z_before + tol:
                    d_q, d_id, d_vis, nd = _push(d_q, d_id, d_vis, nd, -1, gone_ids[e], False)
        # the scratch back to clean
        for t in range(n_touched):
            p = touched[t]
            mark[p // (n * n), (p // n) % n, p % n] = -1
        if n_reset > 0:
            reset_lo[:] = np.inf
            reset_hi[:] = -np.inf
        if any_changed:
            for f in range(6):
                for ti in range(nt):
                    for tj in range(nt):
                        if changed_lo[f, ti, tj] <= changed_hi[f, ti, tj]:
                            maxima[theirs[s], f, ti, tj] = _one_tile_max(
                                data, rect, offset, f, ti, tj, n
                            )
            changed_lo[:] = np.inf
            changed_hi[:] = -np.inf
        if nd == 0:
            outcome[s] = UNCHANGED
            continue
        # F. each view's mask: its entries of the dirty voxels out, theirs now in, in voxel order
        outcome[s] = CHANGED
        stats[0] += 1
        stats[4] += nd
        by_id = np.argsort(d_id[:nd])
        dq, did, dvis = d_q[:nd][by_id], d_id[:nd][by_id], d_vis[:nd][by_id]
        if nd > ins_e.shape[1]:
            size = 2 * nd
            ins_e = np.empty((n_views, size), np.int64)
            ins_w = np.empty((n_views, size), np.float64)
            ins_r = np.empty((n_views, size), np.int64)
        ins_count[:] = 0
        to_seed = np.zeros(nd, np.uint8)
        for e in range(nd):
            dirty_flag[did[e]] = 1
            if not dvis[e]:
                continue
            c = rec_c[dq[e]]
            dx, dy, dz = c[0] - o[0], c[1] - o[1], c[2] - o[2]
            to_seed[e] = direction_bin(direction_bins, -dx, -dy, -dz)
            f, i, j = _pixel_of(o, c, n)
            bits = cells[theirs[s], f, i // TILE, j // TILE]
            for b in range(n_views):
                if b < 64 and not (bits >> np.uint64(b)) & np.uint64(1):
                    continue
                w, rb = view_entry(
                    rotations[s, b], dx, dy, dz, rec_n[dq[e]],
                    near, max_range, tan_x, tan_y, fs2, ppv, range_bin, max_bin,
                )  # fmt: skip
                if w >= 0.0:
                    m = ins_count[b]
                    ins_e[b, m], ins_w[b, m], ins_r[b, m] = e, w, rb
                    ins_count[b] = m + 1
        start = old_start[theirs[s]]
        for b in range(n_views):
            n_old, n_in = old_counts[theirs[s], b], ins_count[b]
            if total + n_old + n_in > cap:
                while total + n_old + n_in > cap:
                    cap *= 2
                out_ids = grown(out_ids, total, cap)
                out_w = grown(out_w, total, cap)
                out_r = grown(out_r, total, cap)
                out_d = grown(out_d, total, cap)
            at = total
            m = 0
            for k in range(start, start + n_old):
                voxel = old_ids[k]
                while m < n_in and did[ins_e[b, m]] < voxel:  # the voxels that come first
                    e = ins_e[b, m]
                    out_ids[at], out_w[at], out_r[at], out_d[at] = (
                        did[e],
                        ins_w[b, m],
                        ins_r[b, m],
                        to_seed[e],
                    )
                    at += 1
                    m += 1
                if dirty_flag[voxel]:
                    continue
                out_ids[at], out_w[at], out_r[at], out_d[at] = voxel, old_w[k], old_r[k], old_d[k]
                at += 1
            while m < n_in:
                e = ins_e[b, m]
                out_ids[at], out_w[at], out_r[at], out_d[at] = (
                    did[e],
                    ins_w[b, m],
                    ins_r[b, m],
                    to_seed[e],
                )
                at += 1
                m += 1
            counts[s, b] = at - total
            total = at
            start += n_old
        for e in range(nd):
            dirty_flag[did[e]] = 0
    return (
        outcome,
        grow,
        stats,
        counts,
        out_ids[:total],
        out_w[:total],
        out_r[:total],
        out_d[:total],
    )


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

    g: the new geometry (`visibility._Geometry`); old: the cache; state: its `State`; match:
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
