"""Pixels to world points: X = T (D K^-1 x), the paper's back-projection."""

from __future__ import annotations

import numpy as np


def pixel_rays(K: np.ndarray, height: int, width: int) -> np.ndarray:
    """(H, W, 3) float32 rays K^-1 [u+0.5, v+0.5, 1] in the optical frame (z = 1)."""
    u = np.arange(width, dtype=np.float64) + 0.5
    v = np.arange(height, dtype=np.float64) + 0.5
    uu, vv = np.meshgrid(u, v)
    x = (uu - K[0, 2]) / K[0, 0]
    y = (vv - K[1, 2]) / K[1, 1]
    return np.stack([x, y, np.ones_like(x)], axis=-1).astype(np.float32)


def backproject(depth: np.ndarray, K: np.ndarray, T_world_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World points of every pixel with a finite, positive depth.

    depth: (H, W) float32 metres along the optical z axis, NaN = no return.
    K: (3, 3) intrinsics. T_world_cam: (4, 4) pose of the camera optical frame in `world`.
    Returns (points (N, 3) float64 world metres, pixel (N,) int64 flat pixel index).
    """
    h, w = depth.shape
    rays = pixel_rays(K, h, w).reshape(-1, 3)
    d = depth.reshape(-1)
    pixel = np.flatnonzero(np.isfinite(d) & (d > 0))
    cam = rays[pixel].astype(np.float64) * d[pixel, None]
    points = cam @ T_world_cam[:3, :3].T + T_world_cam[:3, 3]
    return points, pixel
