"""Rotations in the graph's conventions: quaternions are (x, y, z, w) as in ROS (scipy's
scalar-last order), rotations (3, 3) float64, rigid transforms 4x4 float64.

Written on numpy rather than scipy's `Rotation` / `Slerp`, for two measured reasons (scipy 1.17.1;
the tests check every function here against scipy):

- Speed on the paths that run per frame (`timeit`, one call, idle 2-core machine): quaternion to
  matrix 3 us against 11 us (`Rotation.from_quat(q).as_matrix()`), matrix to quaternion 13 us
  against 52 us (`Rotation.from_matrix(R).as_quat(canonical=True)`), `slerp` 5 us against 145 us
  (`Slerp`), `rotation_angle` 1 us against 41 us (`Rotation.magnitude`). With scipy's quaternion to
  matrix alone, `area3d bench tf` measured the per-frame TF lookup at p50 90 us against 57 us.
- The same views bit for bit: `Rotation.from_matrix` maps a rotation matrix that is orthonormal
  only to its stored precision (the bundled scenes keep 7 decimals) to a quaternion up to 2.2e-8
  away from Shepperd's, and the poses on the wire move with it: a 12-view single_object episode
  captured every frame up to 6.6e-8 (rotation) and 3e-6 (position of a planned view) off, its depth
  images and maps no longer the same.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from area3d_msgs_py.errors import InputError

# How far a quaternion's squared norm may be off 1, as tf2 and RViz accept it (their
# QUATERNION_NORMALIZATION_TOLERANCE): a driver's float32 quaternions that ROS tools take are taken.
QUATERNION_NORM2_TOLERANCE = 1e-2
# Below this angle slerp is replaced by a normalised linear blend (sin(theta) ~ 0).
_SLERP_LINEAR_BELOW_RAD = 1e-6


def rotation_to_quaternion(R: np.ndarray) -> np.ndarray:
    """(3, 3) rotation -> (4,) unit quaternion (x, y, z, w) with w >= 0 (Shepperd's method)."""
    trace = np.trace(R)
    diag = np.diag(R)
    i = int(np.argmax(np.r_[trace, diag]))
    if i == 0:
        w = np.sqrt(1.0 + trace) / 2.0
        q = np.array(
            [
                (R[2, 1] - R[1, 2]) / (4 * w),
                (R[0, 2] - R[2, 0]) / (4 * w),
                (R[1, 0] - R[0, 1]) / (4 * w),
                w,
            ]
        )
    else:
        a = i - 1
        b, c = (a + 1) % 3, (a + 2) % 3
        s = np.sqrt(1.0 + R[a, a] - R[b, b] - R[c, c]) * 2.0
        q = np.empty(4)
        q[a] = s / 4.0
        q[b] = (R[b, a] + R[a, b]) / s
        q[c] = (R[c, a] + R[a, c]) / s
        q[3] = (R[c, b] - R[b, c]) / s
    q /= np.linalg.norm(q)
    return -q if q[3] < 0 else q


def quaternion_to_rotation(q: np.ndarray) -> np.ndarray:
    """(4,) unit quaternion (x, y, z, w) -> (3, 3) rotation.

    numpy, not `Rotation.from_quat`: it runs for every dynamic edge of every TF lookup (see the
    module docstring)."""
    x, y, z, w = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def check_quaternion(values: Any, field: str) -> np.ndarray:
    """(4,) float64 unit quaternion (x, y, z, w) from `values`, normalised; a quaternion that is
    not finite or whose squared norm is off 1 by more than QUATERNION_NORM2_TOLERANCE is
    refused."""
    q = np.asarray(values, dtype=np.float64).reshape(-1)
    norm = np.linalg.norm(q) if q.shape == (4,) else np.nan
    if not np.isfinite(norm) or abs(norm * norm - 1.0) > QUATERNION_NORM2_TOLERANCE:
        raise InputError(
            field,
            q.tolist(),
            f"a unit quaternion (|norm^2 - 1| <= {QUATERNION_NORM2_TOLERANCE:g}, as tf2)",
        )
    return q / norm


def check_translation(values: Any, field: str) -> np.ndarray:
    """(3,) float64 finite translation in metres from `values`."""
    t = np.asarray(values, dtype=np.float64).reshape(-1)
    if t.shape != (3,) or not np.isfinite(t).all():
        raise InputError(field, t.tolist(), "finite (x, y, z) in metres")
    return t


def rotation_angle(q0: np.ndarray, q1: np.ndarray) -> float:
    """Angle in radians (in [0, pi]) of the rotation between two unit quaternions.

    numpy, not `Rotation.magnitude`: it runs for every TF sample of an edge whose angular speed is
    checked (see the module docstring)."""
    return float(2.0 * np.arccos(min(1.0, abs(float(np.dot(q0, q1))))))


def slerp(q0: np.ndarray, q1: np.ndarray, u: float) -> np.ndarray:
    """Unit quaternion at fraction `u` in [0, 1] of the shortest rotation from q0 to q1.

    numpy, not scipy's `Slerp`: it runs for every dynamic edge of every TF lookup (see the module
    docstring)."""
    dot = float(np.dot(q0, q1))
    if dot < 0.0:  # q and -q are one rotation: take the shorter arc
        q1, dot = -q1, -dot
    theta = np.arccos(min(1.0, dot))
    if theta < _SLERP_LINEAR_BELOW_RAD:
        q = q0 + u * (q1 - q0)
    else:
        q = (np.sin((1.0 - u) * theta) * q0 + np.sin(u * theta) * q1) / np.sin(theta)
    return q / np.linalg.norm(q)


def matrix(translation: np.ndarray, rotation: np.ndarray) -> np.ndarray:
    """4x4 homogeneous transform from a translation (3,) and a unit quaternion (x, y, z, w)."""
    T = np.eye(4)
    T[:3, :3] = quaternion_to_rotation(rotation)
    T[:3, 3] = translation
    return T


def invert(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid 4x4 transform."""
    inv = np.eye(4)
    R_t = T[:3, :3].T
    inv[:3, :3] = R_t
    inv[:3, 3] = -R_t @ T[:3, 3]
    return inv
