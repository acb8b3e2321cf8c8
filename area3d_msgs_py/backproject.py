"""Pixels to world points: X = T (D K^-1 x), the paper's back-projection."""

from __future__ import annotations

import functools

import numpy as np
from numba import njit


@functools.lru_cache(maxsize=8)
def _cached_rays(k: tuple[float, float, float, float], height: int, width: int) -> np.ndarray:
    fx, fy, cx, cy = k
    x = ((np.arange(width, dtype=np.float64) + 0.5 - cx) / fx).astype(np.float32)
    y = ((np.arange(height, dtype=np.float64) + 0.5 - cy) / fy).astype(np.float32)
    rays = np.empty((height, width, 3), dtype=np.float32)
    rays[..., 0] = x[None, :]
    rays[..., 1] = y[:, None]
    rays[..., 2] = 1.0
    rays.flags.writeable = False
    return rays


def pixel_rays(K: np.ndarray, height: int, width: int) -> np.ndarray:
    """(H, W, 3) float32 rays K^-1 [u+0.5, v+0.5, 1] in the optical frame (z = 1).

    The array is cached per (K, H, W) and read-only; copy it before writing to it.
    """
    K = np.asarray(K, dtype=np.float64)
    key = (float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]))
    return _cached_rays(key, int(height), int(width))


@njit(cache=True, nogil=True)
def pixel_to_world(u, v, d, fx, fy, cx, cy, T, out):  # pragma: no cover - compiled
    """out[:3] = T (d K^-1 [u + 0.5, v + 0.5, 1]): the world point of pixel (u, v) at depth d
    along the optical z axis. The one back-projection of the compiled kernels."""
    px = (u + 0.5 - cx) / fx * d
    py = (v + 0.5 - cy) / fy * d
    for a in range(3):
        out[a] = T[a, 0] * px + T[a, 1] * py + T[a, 2] * d + T[a, 3]


@njit(cache=True, nogil=True)
def _backproject(depth, fx, fy, cx, cy, T):  # pragma: no cover - compiled
    h, w = depth.shape
    n = 0
    for v in range(h):
        for u in range(w):
            d = depth[v, u]
            if np.isfinite(d) and d > 0:
                n += 1
    points = np.empty((n, 3), dtype=np.float64)
    pixel = np.empty(n, dtype=np.int64)
    m = 0
    for v in range(h):
        for u in range(w):
            d = np.float64(depth[v, u])
            if not (np.isfinite(d) and d > 0):
                continue
            pixel_to_world(u, v, d, fx, fy, cx, cy, T, points[m])
            pixel[m] = v * w + u
            m += 1
    return points, pixel


def backproject(
    depth: np.ndarray, K: np.ndarray, T_world_cam: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """World points of every pixel with a finite, positive depth.

    depth: (H, W) float32 metres along the optical z axis, NaN = no return.
    K: (3, 3) intrinsics. T_world_cam: (4, 4) pose of the camera optical frame in `world`.
    Returns (points (N, 3) float64 world metres, pixel (N,) int64 flat pixel index, row-major).
    """
    K = np.asarray(K, dtype=np.float64)
    T = np.ascontiguousarray(T_world_cam, dtype=np.float64)
    depth = np.ascontiguousarray(depth, dtype=np.float32)
    return _backproject(depth, K[0, 0], K[1, 1], K[0, 2], K[1, 2], T)


def depth_to_world(depth: np.ndarray, K: np.ndarray, T_world_cam: np.ndarray) -> np.ndarray:
    """(H, W, 3) float64 world point of every pixel, NaN where the depth is NaN.

    The dense form of `backproject` (same rays, `pixel_rays`), for image-shaped masks and samples.
    depth: (H, W) metres along the optical z axis. T_world_cam: (4, 4) optical-frame pose.
    """
    depth = np.asarray(depth, dtype=np.float64)
    T = np.asarray(T_world_cam, dtype=np.float64)
    cam = pixel_rays(K, *depth.shape) * depth[..., None]
    return cam @ T[:3, :3].T + T[:3, 3]


def roi_pixels(
    depth: np.ndarray,
    K: np.ndarray,
    T_world_cam: np.ndarray,
    roi_min: np.ndarray,
    roi_max: np.ndarray,
) -> np.ndarray:
    """(H, W) bool: the pixels with a finite, positive depth whose world point lies in the box
    [roi_min, roi_max] (world metres, both ends included)."""
    lo, hi = np.asarray(roi_min, np.float64), np.asarray(roi_max, np.float64)
    with np.errstate(invalid="ignore"):  # NaN and inf depths give NaN points: outside
        world = depth_to_world(depth, K, T_world_cam)
        inside = np.all((world >= lo) & (world <= hi), axis=-1)
        return np.isfinite(depth) & (np.asarray(depth) > 0) & inside
