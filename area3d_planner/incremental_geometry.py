"""Geometry of the incremental visibility update (`incremental.py`): its constants, and the
small numba helpers of its kernel (`incremental_kernel.py`).

Which occluders can cover a reset pixel, and which recorded voxels can lie in a changed pixel,
is found by bricks of BRICK^3 voxels (`brick_index`): a brick whose pixels on a face (a
conservative rectangle, `box_face_rect`) meet no flagged TILE x TILE tile is skipped whole
(`_brick_meets`). Per position: the largest value of each tile of its buffer (`tile_maxima`),
the views each tile's directions may be in (`view_cells`); a buffer whose crops must grow is
copied into larger ones (`grow_buffer`).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from area3d_planner.zbuffer import (
    MAX_SPLAT_HALF_ANGLE,
    SPLAT_HALF_EXTENT,
    _cube_coords,
    _pixel,
    grown,
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
