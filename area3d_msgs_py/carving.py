"""Free space carved by camera rays into a voxel grid: each ray walked voxel by voxel (3D DDA,
Amanatides and Woo) from the camera centre to its end, the voxels before a surface hit counted or
marked as crossed (`carve_free_space`); a whole depth frame's rays at once (`carve_depth_frame`).
Shared by perception's geometric field and the planner's fusion, as the grid (`grid.py`) and
back-projection (`backproject.py`) are.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from area3d_msgs_py.backproject import pixel_to_world
from area3d_msgs_py.camera import PAPER_MAX_RANGE
from area3d_msgs_py.errors import InputError
from area3d_msgs_py.grid import GridSpec

# Pixels are subsampled by 2 in u and v for carving: 76,800 rays per 640x480 frame (our choice).
CARVE_STRIDE = 2


def check_grid_array(name: str, array: np.ndarray, spec: GridSpec) -> np.ndarray:
    if not isinstance(array, np.ndarray) or array.shape != tuple(spec.shape):
        shape = getattr(array, "shape", type(array).__name__)
        raise InputError(name, shape, f"a numpy array of the grid shape {tuple(spec.shape)}")
    if not array.flags.c_contiguous:
        raise InputError(
            name, "non-contiguous array", "a C-contiguous array (it is updated in place)"
        )
    return array


def _check_marks(free_count: np.ndarray) -> np.ndarray:
    """`free_count` when it can take marks (count=False): uint8."""
    if free_count.dtype != np.uint8:
        raise InputError("free_count", free_count.dtype, "a uint8 array to mark (count=False)")
    return free_count


def check_points(name: str, points: np.ndarray) -> np.ndarray:
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise InputError(name, f"shape {points.shape}", "an (N, 3) array of world points in metres")
    return points


@njit(cache=True, inline="always")
def _axis_start(o, d, i):  # pragma: no cover - compiled
    """Step sign, ray parameter of the first voxel boundary and parameter per voxel along one
    axis, for a ray at `o` with direction component `d` starting in voxel `i`."""
    if d > 0:
        return 1, (i + 1 - o) / d, 1.0 / d
    if d < 0:
        return -1, (i - o) / d, -1.0 / d
    return 0, np.inf, np.inf


@njit(cache=True, inline="always")
def _walk_ray(o0, o1, o2, e0, e1, e2, nx, ny, nz, free, count):  # pragma: no cover - compiled
    """Amanatides-Woo traversal of one ray in voxel units; marks every voxel before its end voxel.

    free: flat array of length nx*ny*nz; `count`: add 1 per carved voxel, else set it to 1.
    The walk from the first voxel to the end voxel takes exactly their Manhattan distance in
    steps, so the loop runs that many steps (marking, then stepping) and needs no end test.
    """
    d0, d1, d2 = e0 - o0, e1 - o1, e2 - o2
    # Clip the segment [0, 1] to the grid box [0, n] on every axis (slab method).
    t0 = 0.0
    t1 = 1.0
    if d0 != 0.0:
        ta, tb = -o0 / d0, (nx - o0) / d0
        t0, t1 = max(t0, min(ta, tb)), min(t1, max(ta, tb))
    elif o0 < 0.0 or o0 >= nx:
        return
    if d1 != 0.0:
        ta, tb = -o1 / d1, (ny - o1) / d1
        t0, t1 = max(t0, min(ta, tb)), min(t1, max(ta, tb))
    elif o1 < 0.0 or o1 >= ny:
        return
    if d2 != 0.0:
        ta, tb = -o2 / d2, (nz - o2) / d2
        t0, t1 = max(t0, min(ta, tb)), min(t1, max(ta, tb))
    elif o2 < 0.0 or o2 >= nz:
        return
    if t0 >= t1:
        return
    ts = t0 + 1e-9
    i = min(max(int(np.floor(o0 + ts * d0)), 0), nx - 1)
    j = min(max(int(np.floor(o1 + ts * d1)), 0), ny - 1)
    k = min(max(int(np.floor(o2 + ts * d2)), 0), nz - 1)
    steps = abs(int(np.floor(e0)) - i) + abs(int(np.floor(e1)) - j) + abs(int(np.floor(e2)) - k)
    si, tmi, tdi = _axis_start(o0, d0, i)
    sj, tmj, tdj = _axis_start(o1, d1, j)
    sk, tmk, tdk = _axis_start(o2, d2, k)
    flat = (i * ny + j) * nz + k
    fi, fj = si * ny * nz, sj * nz
    for _ in range(steps):
        if count:
            free[flat] += 1
        else:
            free[flat] = 1
        if tmi <= tmj and tmi <= tmk:
            i += si
            if i < 0 or i >= nx:
                break
            tmi += tdi
            flat += fi
        elif tmj <= tmk:
            j += sj
            if j < 0 or j >= ny:
                break
            tmj += tdj
            flat += fj
        else:
            k += sk
            if k < 0 or k >= nz:
                break
            tmk += tdk
            flat += sk


@njit(cache=True)
def _carve_rays(origin, ends, shape, free):  # pragma: no cover - compiled
    """Count, per voxel of the flat `free`, the rays from `origin` (3,) to `ends` (N, 3) (voxel
    coordinates, (p - lower) / voxel_size) that crossed it before their end voxel."""
    for r in range(ends.shape[0]):
        _walk_ray(
            origin[0], origin[1], origin[2], ends[r, 0], ends[r, 1], ends[r, 2],
            shape[0], shape[1], shape[2], free, True,
        )  # fmt: skip


@njit(cache=True, nogil=True, parallel=True)
def _mark_rays(origin, ends, shape, crossed):  # pragma: no cover - compiled
    """Set to 1 every voxel of the flat uint8 `crossed` that a ray crossed before its end voxel.
    Rays run in parallel: concurrent writes to a voxel all write the same 1, so the result is the
    set `_carve_rays` counts > 0 in, whatever the order. Runs without the GIL (it writes only its
    own output), so a node's other threads (a plan request) go on meanwhile."""
    for r in prange(ends.shape[0]):
        _walk_ray(
            origin[0], origin[1], origin[2], ends[r, 0], ends[r, 1], ends[r, 2],
            shape[0], shape[1], shape[2], crossed, False,
        )  # fmt: skip


def carve_free_space(
    spec: GridSpec,
    origin: np.ndarray,
    points: np.ndarray,
    free_count: np.ndarray,
    hit_mask: np.ndarray | None = None,
    surface_margin: float = 0.0,
    count: bool = True,
) -> np.ndarray:
    """Count, per voxel, the camera rays that crossed it before ending (observed free space).

    spec: the grid. origin: (3,) camera centre in world metres. points: (N, 3) world ray ends.
    free_count: (nx, ny, nz) counter (any numeric dtype), incremented in place, once per ray per
    voxel. hit_mask: (N,) bool, True where the end is a surface hit (default: all True); a non-hit
    ray (no return, passed as its point at max range) carves to its end. No ray ever marks the voxel
    that holds its end, and a voxel is carved only if the ray leaves it before the end.
    surface_margin: metres; hit rays stop this far short of the hit (depth noise band, default 0).
    count=False: only mark, in a uint8 `free_count`, the voxels any ray crossed (set to 1); the
    rays then run in parallel.
    Returns free_count.
    """
    origin = np.asarray(origin, dtype=np.float64).reshape(-1)
    if origin.shape != (3,) or not np.all(np.isfinite(origin)):
        raise InputError("origin", origin.tolist(), "a finite (3,) camera centre in metres")
    points = check_points("points", points)
    free_count = check_grid_array("free_count", free_count, spec)
    if hit_mask is None:
        hit_mask = np.ones(points.shape[0], dtype=bool)
    hit_mask = np.asarray(hit_mask, dtype=bool).reshape(-1)
    if hit_mask.shape[0] != points.shape[0]:
        raise InputError(
            "hit_mask", f"length {hit_mask.shape[0]}", f"one flag per point ({points.shape[0]})"
        )
    if not (np.isfinite(surface_margin) and surface_margin >= 0):
        raise InputError("surface_margin", surface_margin, "a finite value >= 0 metres")
    finite = np.all(np.isfinite(points), axis=1)
    points, hit_mask = points[finite], hit_mask[finite]
    if surface_margin > 0:
        # A hit ray ends `surface_margin` short of its hit; the voxel holding that point is kept.
        offset = points - origin
        length = np.linalg.norm(offset, axis=1)
        with np.errstate(divide="ignore", invalid="ignore"):
            keep = np.where(hit_mask, np.clip(1.0 - surface_margin / length, 0.0, 1.0), 1.0)
        points = origin + offset * keep[:, None]
    scale = 1.0 / spec.voxel_size
    origin_v = (origin - spec.lower) * scale
    ends_v = (points - spec.lower) * scale
    shape = np.asarray(spec.shape, dtype=np.int64)
    if count:
        _carve_rays(origin_v, ends_v, shape, free_count.reshape(-1))
    else:
        _mark_rays(origin_v, ends_v, shape, _check_marks(free_count).reshape(-1))
    return free_count


def _frame_arrays(depth, K, T_world_cam, stride, max_range):
    """(depth float32, K float64, T float64) of a frame whose rays are built, with `stride` and
    `max_range` checked."""
    if int(stride) != stride or stride < 1:
        raise InputError("stride", stride, "an integer >= 1")
    if not (np.isfinite(max_range) and max_range > 0):
        raise InputError("max_range", max_range, "a finite range > 0 metres")
    if np.ndim(depth) != 2:
        raise InputError("depth", f"shape {np.shape(depth)}", "an (H, W) image in metres")
    K = np.asarray(K, dtype=np.float64)
    depth = np.ascontiguousarray(depth, dtype=np.float32)
    return depth, K, np.ascontiguousarray(T_world_cam, dtype=np.float64)


def frame_rays(
    depth: np.ndarray,
    K: np.ndarray,
    T_world_cam: np.ndarray,
    stride: int = CARVE_STRIDE,
    max_range: float = PAPER_MAX_RANGE,
) -> tuple[np.ndarray, np.ndarray]:
    """Ray ends of a depth frame subsampled by `stride`, for `carve_free_space`.

    depth: (H, W) metres along optical z, NaN = no return. K: (3, 3). T_world_cam: (4, 4).
    Pixels with a return at most `max_range` from the camera end at their surface point (hit); the
    others end `max_range` metres along their ray (no hit).
    Returns (points (N, 3) world metres, hit_mask (N,) bool).
    """
    depth, K, T = _frame_arrays(depth, K, T_world_cam, stride, max_range)
    return _frame_ray_ends(
        depth, K[0, 0], K[1, 1], K[0, 2], K[1, 2], T, int(stride), float(max_range)
    )


@njit(cache=True, nogil=True, inline="always")
def _ray_end(depth, u, v, fx, fy, cx, cy, T, max_range, out):  # pragma: no cover - compiled
    """out[:3] = the world end of pixel (u, v)'s ray; True if it is a surface hit (a return at
    most `max_range` from the camera), False if it ends `max_range` metres along the ray."""
    x = (u + 0.5 - cx) / fx
    y = (v + 0.5 - cy) / fy
    norm = np.sqrt(x * x + y * y + 1.0)
    d = np.float64(depth[v, u])
    hit = np.isfinite(d) and d > 0 and d * norm <= max_range
    if not hit:
        d = max_range / norm
    pixel_to_world(u, v, d, fx, fy, cx, cy, T, out)
    return hit


@njit(cache=True, nogil=True)
def _frame_ray_ends(depth, fx, fy, cx, cy, T, stride, max_range):  # pragma: no cover - compiled
    h, w = depth.shape
    rows = (h + stride - 1) // stride
    cols = (w + stride - 1) // stride
    points = np.empty((rows * cols, 3), dtype=np.float64)
    hit = np.empty(rows * cols, dtype=np.bool_)
    n = 0
    for v in range(0, h, stride):
        for u in range(0, w, stride):
            hit[n] = _ray_end(depth, u, v, fx, fy, cx, cy, T, max_range, points[n])
            n += 1
    return points, hit


@njit(cache=True, nogil=True, parallel=True)
def _mark_frame_rays(
    depth, fx, fy, cx, cy, T, stride, max_range, no_return, carve_mask, lower, scale, shape, crossed
):  # pragma: no cover - compiled
    """`frame_rays` and `carve_free_space(count=False)` in one pass, rows of rays in parallel:
    each ray's end is computed and walked at once (no arrays of every ray). no_return: 0 = rays
    without a return carve nothing, 1 = all of them carve, 2 = those where `carve_mask` is True."""
    h, w = depth.shape
    o0 = (T[0, 3] - lower[0]) * scale
    o1 = (T[1, 3] - lower[1]) * scale
    o2 = (T[2, 3] - lower[2]) * scale
    for r in prange((h + stride - 1) // stride):
        v = r * stride
        end = np.empty(3)
        for u in range(0, w, stride):
            hit = _ray_end(depth, u, v, fx, fy, cx, cy, T, max_range, end)
            if not hit and (no_return == 0 or (no_return == 2 and not carve_mask[v, u])):
                continue
            _walk_ray(
                o0, o1, o2,
                (end[0] - lower[0]) * scale, (end[1] - lower[1]) * scale,
                (end[2] - lower[2]) * scale,
                shape[0], shape[1], shape[2], crossed, False,
            )  # fmt: skip


def carve_depth_frame(
    spec: GridSpec,
    depth: np.ndarray,
    K: np.ndarray,
    T_world_cam: np.ndarray,
    free_count: np.ndarray,
    stride: int = CARVE_STRIDE,
    max_range: float = PAPER_MAX_RANGE,
    surface_margin: float = 0.0,
    carve_no_return: bool | np.ndarray = True,
    count: bool = True,
) -> np.ndarray:
    """Carve the free space seen by one depth frame into `free_count` (see `carve_free_space`).

    carve_no_return: also carve along pixels with no return, up to `max_range`: True for all of
    them, False for none (a dropout of a dark or specular surface looks like empty space), or an
    (H, W) bool mask of the no-return pixels that may carve. count=False: mark (see
    `carve_free_space`).
    """
    if isinstance(carve_no_return, np.ndarray):
        carve_no_return = np.ascontiguousarray(carve_no_return, dtype=bool)
        if carve_no_return.shape != np.shape(depth):
            raise InputError(
                "carve_no_return", carve_no_return.shape, f"the depth shape {np.shape(depth)}"
            )
    if not count and surface_margin == 0:
        return _mark_depth_frame(spec, depth, K, T_world_cam, free_count, stride, max_range,
                                 carve_no_return)  # fmt: skip
    points, hit = frame_rays(depth, K, T_world_cam, stride, max_range)
    if isinstance(carve_no_return, np.ndarray):
        keep = hit | carve_no_return[::stride, ::stride].reshape(-1)
        points, hit = points[keep], hit[keep]
    elif not carve_no_return:
        points, hit = points[hit], hit[hit]
    return carve_free_space(
        spec, T_world_cam[:3, 3], points, free_count, hit, surface_margin, count
    )


def _mark_depth_frame(spec, depth, K, T_world_cam, crossed, stride, max_range, carve_no_return):
    """`carve_depth_frame(count=False)` without a surface margin: every ray's end computed and
    walked in one compiled pass (`_mark_frame_rays`); marks the same voxels as the general path
    (test). `carve_no_return`: as checked by `carve_depth_frame`."""
    depth, K, T = _frame_arrays(depth, K, T_world_cam, stride, max_range)
    if not np.all(np.isfinite(K)):
        raise InputError("K", K.tolist(), "finite (3, 3) intrinsics")
    if not np.all(np.isfinite(T)):
        raise InputError("T_world_cam", T.tolist(), "a finite (4, 4) pose")
    crossed = _check_marks(check_grid_array("free_count", crossed, spec))
    mask = np.zeros((1, 1), dtype=bool)
    if isinstance(carve_no_return, np.ndarray):
        mask = carve_no_return
        no_return = 2
    else:
        no_return = 1 if carve_no_return else 0
    _mark_frame_rays(
        depth,
        K[0, 0], K[1, 1], K[0, 2], K[1, 2],
        T, int(stride), float(max_range), no_return, mask,
        np.asarray(spec.lower, dtype=np.float64), 1.0 / spec.voxel_size,
        np.asarray(spec.shape, dtype=np.int64), crossed.reshape(-1),
    )  # fmt: skip
    return crossed
