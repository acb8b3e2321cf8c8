"""Depth images of planes for the depth-model tests (`area3d_msgs_py`, `sim_bridge`,
`area3d_perception`): a small camera with the paper's 90 degree field of view, a plane seen by it,
and the axial noise curve the sensor model is checked against."""

from __future__ import annotations

import numpy as np

H, W = 120, 160
# 90 degree horizontal field of view, the paper's camera.
K = np.array([[W / 2, 0, W / 2], [0, W / 2, H / 2], [0, 0, 1.0]])


def plane_depth(distance: float, tilt_deg: float = 0.0, h: int = H, w: int = W) -> np.ndarray:
    """Depth of a plane through (0, 0, distance) whose normal is tilted by `tilt_deg` about x."""
    a = np.deg2rad(tilt_deg)
    n = np.array([0.0, np.sin(a), -np.cos(a)])
    u = (np.arange(w) + 0.5 - w / 2) / (w / 2)
    v = (np.arange(h) + 0.5 - h / 2) / (w / 2)
    uu, vv = np.meshgrid(u, v)
    rays = np.stack([uu, vv, np.ones_like(uu)], axis=-1)
    t = (n @ np.array([0, 0, distance])) / (rays @ n)
    t[t <= 0] = np.nan
    return t.astype(np.float32)


def nguyen_sigma(z: float) -> float:
    """Axial noise at normal incidence as published (Nguyen et al. 2012)."""
    return 0.0012 + 0.0019 * (z - 0.4) ** 2


def centre(a: np.ndarray, r: int = 5) -> np.ndarray:
    """The (2 r, 2 r) patch at the middle of an (H, W) image."""
    return a[H // 2 - r : H // 2 + r, W // 2 - r : W // 2 + r]
