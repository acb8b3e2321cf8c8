"""What a depth image says about the surface it sees: the incidence angle of each pixel's viewing
ray, the depth discontinuities, and each pixel's distance to the nearest one.

Both halves of the sensor model stand on these: the simulated camera's noise (`sim_bridge.noise`:
lateral jitter and dropouts near edges, axial noise and dropouts growing with incidence) and
perception's `rgbd` confidence (`area3d_perception.sensor_model`: the incidence and edge factors).
"""

from __future__ import annotations

from functools import lru_cache

import cv2
import numpy as np
from numba import njit

from area3d_msgs_py.depth_sensor import RgbdSensorParams

_UNIT_K = np.eye(3)


# The kernels below run on one thread: the graph already runs its nodes as processes on a few
# cores, and numba's thread pool on a busy 2-core machine waits on descheduled workers (measured:
# noise + confidence per 640x480 frame 41-44 ms on one thread, 81-106 ms on two, same load).
# They walk the image a row at a time with branch-free inner loops over the columns, which LLVM
# turns into SIMD code; error_model="numpy" lets it (a float division by zero gives inf or NaN,
# never a Python exception, so the division needs no branch). The per-pixel arithmetic is that
# of the straightforward per-pixel loops (test_msgs_depth_surface checks them against one).
@njit(cache=True, error_model="numpy")
def _accumulate_same_surface(row, near, total, count, jump_rel, max_range):  # pragma: no cover
    for u in range(row.size):
        d = row[u]
        dn = near[u]
        same = (dn > 0) & (dn <= max_range) & (abs(dn - d) <= jump_rel * d)
        total[u] += dn if same else 0.0
        count[u] += 1.0 if same else 0.0


@njit(cache=True, error_model="numpy")
def _smooth_depth(depth, radius, jump_rel, max_range):  # pragma: no cover - compiled
    """Edge-preserving box mean: each valid pixel averages the valid pixels of its
    (2 radius + 1)^2 window that lie within `jump_rel` of its own depth (same surface), summed in
    row-major window order. NaN where the pixel itself is missing."""
    h, w = depth.shape
    out = np.empty((h, w), dtype=np.float32)
    total = np.empty(w, dtype=np.float64)
    count = np.empty(w, dtype=np.float64)
    for v in range(h):
        row = depth[v]
        total[:] = 0.0
        count[:] = 0.0
        for vv in range(max(v - radius, 0), min(v + radius + 1, h)):
            for du in range(-radius, radius + 1):
                lo = max(-du, 0)
                hi = min(w - du, w)
                _accumulate_same_surface(
                    row[lo:hi],
                    depth[vv, lo + du : hi + du],
                    total[lo:hi],
                    count[lo:hi],
                    jump_rel,
                    max_range,
                )
        for u in range(w):
            d = row[u]
            out[v, u] = total[u] / count[u] if (d > 0) & (d <= max_range) else np.nan
    return out


@njit(cache=True, inline="always")
def _is_jump(d, dn, jump_rel, max_range):  # pragma: no cover - compiled
    """A neighbour depth `dn` that is missing or off the surface of `d` (see `_surface_terms`)."""
    present = (dn > 0) & (dn <= max_range)
    return (not present) | (abs(dn - d) > jump_rel * min(d, dn))


@njit(cache=True, inline="always")
def _pick_tangent(back, fwd, ds):  # pragma: no cover - compiled
    """(forward, any): the tangent of a pixel at smoothed depth `ds` comes from the backward
    neighbour unless the forward one has a strictly smaller depth step; a neighbour that is NaN,
    <= 0 or infinitely far is never picked (a missing or out-of-image one is NaN here)."""
    use_back = (back > 0) & (abs(back - ds) < np.inf)
    best = abs(back - ds) if use_back else np.inf
    use_fwd = (fwd > 0) & (abs(fwd - ds) < best)
    return use_fwd, use_back | use_fwd


@njit(cache=True, error_model="numpy")
def _surface_row(
    d_row,
    d_left,
    d_right,
    d_up,
    d_down,
    s_row,
    s_back,
    s_fwd,
    s_up,
    s_down,
    xs,
    xs_back,
    xs_fwd,
    y,
    y_up,
    y_down,
    jump_rel,
    max_range,
    cos,
    edge,
):  # pragma: no cover - compiled
    """One image row of `_surface_terms`: d_* the depth row and its 4-neighbour rows (an
    out-of-image neighbour is the pixel itself), s_* the smoothed row and its neighbours `step`
    pixels away (NaN out of the image), xs/xs_* and y/y_* their normalised image coordinates."""
    for u in range(d_row.size):
        d = d_row[u]
        valid = (d > 0) & (d <= max_range)
        jump = (
            _is_jump(d, d_left[u], jump_rel, max_range)
            | _is_jump(d, d_right[u], jump_rel, max_range)
            | _is_jump(d, d_up[u], jump_rel, max_range)
            | _is_jump(d, d_down[u], jump_rel, max_range)
        )
        edge[u] = valid & jump
        ds = np.float64(s_row[u])
        x = xs[u]
        back = np.float64(s_back[u])
        fwd = np.float64(s_fwd[u])
        fwd_u, any_u = _pick_tangent(back, fwd, ds)
        dn = fwd if fwd_u else back
        xn = xs_fwd[u] if fwd_u else xs_back[u]
        sign = 1.0 if fwd_u else -1.0
        tux = sign * (xn * dn - x * ds)
        tuy = sign * (y * dn - y * ds)
        tuz = sign * (dn - ds)
        back = np.float64(s_up[u])
        fwd = np.float64(s_down[u])
        fwd_v, any_v = _pick_tangent(back, fwd, ds)
        dn = fwd if fwd_v else back
        yn = y_down if fwd_v else y_up
        sign = 1.0 if fwd_v else -1.0
        tvx = sign * (x * dn - x * ds)
        tvy = sign * (yn * dn - y * ds)
        tvz = sign * (dn - ds)
        nx = tuy * tvz - tuz * tvy
        ny = tuz * tvx - tux * tvz
        nz = tux * tvy - tuy * tvx
        px = x * ds
        py = y * ds
        nn = np.sqrt((nx * nx + ny * ny + nz * nz) * (px * px + py * py + ds * ds))
        c = min(abs(nx * px + ny * py + nz * ds) / nn, 1.0)
        cos[u] = c if valid & any_u & any_v & (nn > 0) else 0.0


@njit(cache=True)
def _surface_terms(depth, smooth, fx, fy, cx, cy, jump_rel, max_range, step):  # pragma: no cover
    """Per pixel |cos| of the incidence angle and a depth-discontinuity flag.

    The normal is the cross product of the two image-axis tangents of the back-projected smoothed
    depth, taken `step` pixels apart; each tangent comes from the forward or backward neighbour,
    whichever has the smaller depth step, so a pixel next to a discontinuity takes its tangent from
    its own surface. A valid pixel whose 4-neighbour is missing or differs by more than `jump_rel`
    x the nearer depth is a discontinuity.
    """
    h, w = depth.shape
    cos = np.empty((h, w), dtype=np.float32)
    edge = np.empty((h, w), dtype=np.bool_)
    xs = np.empty(w + 2 * step)  # columns -step .. w + step - 1
    for i in range(w + 2 * step):
        xs[i] = (i - step + 0.5 - cx) / fx
    depth_padded = np.empty(w + 2, dtype=np.float32)  # the row with its end pixels repeated
    smooth_padded = np.full(w + 2 * step, np.nan, dtype=np.float32)
    missing = np.full(w, np.nan, dtype=np.float32)
    for v in range(h):
        depth_padded[1 : w + 1] = depth[v]
        depth_padded[0] = depth[v, 0]
        depth_padded[w + 1] = depth[v, w - 1]
        smooth_padded[step : step + w] = smooth[v]
        _surface_row(
            depth[v],
            depth_padded[0:w],
            depth_padded[2 : w + 2],
            depth[v - 1] if v > 0 else depth[v],
            depth[v + 1] if v < h - 1 else depth[v],
            smooth[v],
            smooth_padded[0:w],
            smooth_padded[2 * step : 2 * step + w],
            smooth[v - step] if v >= step else missing,
            smooth[v + step] if v + step < h else missing,
            xs[step : step + w],
            xs[0:w],
            xs[2 * step : 2 * step + w],
            (v + 0.5 - cy) / fy,
            (v - step + 0.5 - cy) / fy,
            (v + step + 0.5 - cy) / fy,
            jump_rel,
            max_range,
            cos[v],
            edge[v],
        )
    return cos, edge


def surface_terms(
    depth: np.ndarray,
    K: np.ndarray,
    jump_rel: float,
    max_range: float = np.inf,
    smoothing_px: int = 1,
    normal_step_px: int = 2,
) -> tuple[np.ndarray, np.ndarray]:
    """Incidence cosine and discontinuity mask of a depth image.

    depth: (H, W) float metres (NaN, <= 0 or beyond `max_range` = missing). K: (3, 3).
    Normals are estimated on the depth smoothed by an edge-preserving box mean of radius
    `smoothing_px`, from neighbours `normal_step_px` apart, so sensor noise does not tilt them.
    Returns (cos (H, W) float32 |cos| of the angle between normal and viewing ray, 0 where missing
    or without neighbours; edges (H, W) bool, valid pixels on either side of a depth jump larger
    than `jump_rel` x the nearer depth, or next to a missing pixel).
    """
    depth = np.ascontiguousarray(depth, dtype=np.float32)
    max_range = float(min(max_range, np.finfo(np.float32).max))
    smooth = (
        _smooth_depth(depth, int(smoothing_px), float(jump_rel), max_range)
        if smoothing_px > 0
        else depth
    )
    cos, edge = _surface_terms(
        depth,
        smooth,
        K[0, 0],
        K[1, 1],
        K[0, 2],
        K[1, 2],
        float(jump_rel),
        max_range,
        int(normal_step_px),
    )
    return cos, edge


def incidence_cosine(depth: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(H, W) float32 |cos| of the angle between the surface normal and the viewing ray."""
    return surface_terms(depth, K, RgbdSensorParams.edge_jump_rel)[0]


def discontinuity_mask(depth: np.ndarray, jump_rel: float) -> np.ndarray:
    """(H, W) bool: valid pixels on either side of a depth jump (see `surface_terms`)."""
    return surface_terms(depth, K=_UNIT_K, jump_rel=jump_rel)[1]


# A bounded distance writes each edge pixel's window (`_edge_distance_within`) while that is at
# most this many writes; past it one full OpenCV pass is cheaper (measured on 640x480 frames,
# max_px 3, 29 offsets: 0.4-0.8 ms at the 1% edges of a rendered frame, even with OpenCV's
# 1.4-1.8 ms at 5%, 5 ms against 2 ms at 20%).
_WINDOW_WRITES = 400_000


def _chamfer(edges: np.ndarray) -> np.ndarray:
    return cv2.distanceTransform((~edges).view(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_5)


@lru_cache(maxsize=8)
def _chamfer_window(max_px: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(dy, dx, distance) of every pixel offset whose chamfer distance is at most `max_px`.

    The distances are read off OpenCV's own transform of a single edge pixel, so that a minimum
    over them reproduces its values exactly (a chamfer distance is a shortest path of mask steps,
    and the 5x5 mask's steps never make it shorter than the Chebyshev distance)."""
    n = int(np.floor(max_px))
    c = 2 * n + 2
    single = np.zeros((2 * c + 1, 2 * c + 1), dtype=bool)
    single[c, c] = True
    window = _chamfer(single)[c - n : c + n + 1, c - n : c + n + 1]
    dy, dx = np.nonzero(window <= max_px)
    return dy - n, dx - n, window[dy, dx]


@njit(cache=True)
def _edge_distance_within(edges, dy, dx, values):  # pragma: no cover - compiled
    """min over offsets k of values[k] where edges[v + dy[k], u + dx[k]], inf where none: each
    edge pixel writes its window into the pixels around it, so the cost follows the edges (about
    1% of a frame's pixels), not the image."""
    h, w = edges.shape
    out = np.full((h, w), np.inf, dtype=np.float32)
    for y in range(h):
        for x in range(w):
            if edges[y, x]:
                for k in range(dy.size):
                    v = y - dy[k]
                    u = x - dx[k]
                    if 0 <= v < h and 0 <= u < w and values[k] < out[v, u]:
                        out[v, u] = values[k]
    return out


def edge_distance(edges: np.ndarray, max_px: float = np.inf) -> np.ndarray:
    """(H, W) float32 pixel distance to the nearest True pixel of `edges` (0 on it); inf where no
    True pixel lies within `max_px`.

    The distance is OpenCV's 5x5 chamfer approximation of the Euclidean one (steps 1, 1.4 and
    2.1969 px). A finite `max_px` is what the sensor model needs (its ramps end there): with few
    edges it is computed in a window of that radius around each edge pixel instead of over the
    whole image.
    """
    edges = np.asarray(edges, dtype=bool)
    count = np.count_nonzero(edges)
    if count == 0:
        return np.full(edges.shape, np.inf, dtype=np.float32)
    if np.isfinite(max_px):
        dy, dx, values = _chamfer_window(float(max_px))
        if count * dy.size <= _WINDOW_WRITES:
            return _edge_distance_within(np.ascontiguousarray(edges), dy, dx, values)
    dist = _chamfer(edges)
    if np.isfinite(max_px):
        dist[dist > max_px] = np.inf
    return dist
