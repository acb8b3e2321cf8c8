"""Camera poses that look at a point, in the graph's conventions (REP 103/105).

`world` is z-up; a camera pose is the pose of `camera_optical_frame` (z forward, x right, y
down) in `world`, as a (4, 4) float64 T_world_cam. One definition for the simulator's scenes,
the planner's candidate views and the evaluation's synthetic views.
"""

from __future__ import annotations

import numpy as np

WORLD_UP = np.array([0.0, 0.0, 1.0])  # REP 103: `world` is z-up


def look_rotation(forward: np.ndarray) -> np.ndarray:
    """(..., 3, 3) R_world_cam of optical frames with z along `forward` (..., 3), x horizontal
    (zero roll), y down. `forward` need not be unit; looking straight up or down falls back to
    x = world +x.
    """
    z = np.asarray(forward, dtype=np.float64)
    z = z / np.linalg.norm(z, axis=-1, keepdims=True)
    x = np.cross(z, WORLD_UP)
    nx = np.linalg.norm(x, axis=-1, keepdims=True)
    x = np.where(nx < 1e-9, np.array([1.0, 0.0, 0.0]), x / np.maximum(nx, 1e-12))
    y = np.cross(z, x)
    return np.stack([x, y, z], axis=-1)


def look_at(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """(4, 4) float64 T_world_cam of an optical frame at `eye` (3,) whose z axis points at
    `target` (3,), metres; zero roll (see `look_rotation`)."""
    eye = np.asarray(eye, dtype=np.float64)
    T = np.eye(4)
    T[:3, :3] = look_rotation(np.asarray(target, dtype=np.float64) - eye)
    T[:3, 3] = eye
    return T
