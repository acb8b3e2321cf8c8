"""Poses and transforms <-> 4x4 float64 homogeneous matrices: geometry_msgs Pose, Transform,
PoseArray, TransformStamped and tf2_msgs/TFMessage. A rejection names the message field
(`poses[3].orientation`, `transforms[1].transform.rotation`)."""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import numpy as np

from area3d_msgs_py import msgs
from area3d_msgs_py.codecs.header import header, stamp_to_ns
from area3d_msgs_py.errors import InputError
from area3d_msgs_py.rotations import (
    check_quaternion,
    quaternion_to_rotation,
    rotation_to_quaternion,
)
from area3d_msgs_py.transforms import StampedTransform

# Rotation orthonormality tolerance on max |R^T R - I| (float64 poses composed a few times).
ROTATION_TOLERANCE = 1e-5


def _check_matrix(T: Any, field: str) -> np.ndarray:
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4):
        raise InputError(field, T.shape, "a 4x4 homogeneous matrix")
    if not np.isfinite(T).all():
        raise InputError(field, "non-finite entries", "a finite 4x4 matrix")
    if not np.allclose(T[3], (0.0, 0.0, 0.0, 1.0)):
        raise InputError(f"{field}[3]", T[3].tolist(), "[0, 0, 0, 1]")
    R = T[:3, :3]
    error = np.abs(R.T @ R - np.eye(3)).max()
    if error > ROTATION_TOLERANCE or np.linalg.det(R) < 0:
        raise InputError(
            f"{field} rotation", np.round(R, 6).tolist(), "an orthonormal right-handed rotation"
        )
    return T


def _check_quaternion(orientation: Any, field: str) -> np.ndarray:
    return check_quaternion((orientation.x, orientation.y, orientation.z, orientation.w), field)


def _prefixed(prefix: str, field: str) -> str:
    return f"{prefix}.{field}" if prefix else field


def matrix_to_pose(T: np.ndarray, field: str = "T") -> Any:
    """(4, 4) homogeneous transform -> geometry_msgs/Pose (quaternion with w >= 0)."""
    T = _check_matrix(T, field)
    x, y, z, w = rotation_to_quaternion(T[:3, :3])
    px, py, pz = (float(v) for v in T[:3, 3])
    return msgs.Pose(
        position=msgs.Point(x=px, y=py, z=pz),
        orientation=msgs.Quaternion(x=float(x), y=float(y), z=float(z), w=float(w)),
    )


def pose_to_matrix(pose: Any, field: str = "") -> np.ndarray:
    """geometry_msgs/Pose -> (4, 4) float64; rejects quaternions off unit length by > 1e-3.
    field: the pose's own field in its message, prefixed to the names in a rejection."""
    q = _check_quaternion(pose.orientation, _prefixed(field, "orientation"))
    p = np.array([pose.position.x, pose.position.y, pose.position.z], dtype=np.float64)
    if not np.isfinite(p).all():
        raise InputError(_prefixed(field, "position"), p.tolist(), "finite coordinates")
    T = np.eye(4)
    T[:3, :3] = quaternion_to_rotation(q)
    T[:3, 3] = p
    return T


def matrix_to_transform(T: np.ndarray, field: str = "T") -> Any:
    """(4, 4) homogeneous transform -> geometry_msgs/Transform."""
    pose = matrix_to_pose(T, field)
    p = pose.position
    return msgs.Transform(translation=msgs.Vector3(x=p.x, y=p.y, z=p.z), rotation=pose.orientation)


def transform_to_matrix(transform: Any, field: str = "") -> np.ndarray:
    """geometry_msgs/Transform -> (4, 4) float64; rejects non-unit quaternions and non-finite
    translations. field: as for pose_to_matrix."""
    q = _check_quaternion(transform.rotation, _prefixed(field, "rotation"))
    t = transform.translation
    p = np.array([t.x, t.y, t.z], dtype=np.float64)
    if not np.isfinite(p).all():
        raise InputError(_prefixed(field, "translation"), p.tolist(), "finite coordinates")
    T = np.eye(4)
    T[:3, :3] = quaternion_to_rotation(q)
    T[:3, 3] = p
    return T


def matrices_to_pose_array(Ts: np.ndarray, stamp_ns: int, frame_id: str) -> Any:
    """(N, 4, 4) homogeneous transforms -> geometry_msgs/PoseArray (N may be 0)."""
    Ts = np.asarray(Ts, dtype=np.float64)
    if Ts.ndim != 3 or Ts.shape[1:] != (4, 4):
        raise InputError("poses", Ts.shape, "(N, 4, 4) homogeneous transforms")
    return msgs.PoseArray(
        header=header(stamp_ns, frame_id),
        poses=[matrix_to_pose(T, f"poses[{i}]") for i, T in enumerate(Ts)],
    )


def pose_array_to_matrices(msg: Any, field: str = "poses") -> np.ndarray:
    """geometry_msgs/PoseArray -> (N, 4, 4) float64; a bad pose is named by its index."""
    Ts = np.empty((len(msg.poses), 4, 4))
    for i, pose in enumerate(msg.poses):
        Ts[i] = pose_to_matrix(pose, f"{field}[{i}]")
    return Ts


def stamped_transform_to_msg(transform: StampedTransform) -> Any:
    """(parent, child, stamp_ns, 4x4) -> geometry_msgs/TransformStamped."""
    parent, child, stamp_ns, T = transform
    for field, frame in (("parent", parent), ("child", child)):
        if not isinstance(frame, str) or not frame:
            raise InputError(field, frame, "a frame's name")
    return msgs.TransformStamped(
        header=header(stamp_ns, parent),
        child_frame_id=child,
        transform=matrix_to_transform(T, "T"),
    )


def msg_to_stamped_transform(msg: Any, field: str = "") -> StampedTransform:
    """geometry_msgs/TransformStamped -> (parent, child, stamp_ns, 4x4); field: as pose_to_matrix."""
    return StampedTransform(
        msg.header.frame_id,
        msg.child_frame_id,
        stamp_to_ns(msg.header.stamp),
        transform_to_matrix(msg.transform, _prefixed(field, "transform")),
    )


def transforms_to_tf_message(transforms: Iterable[StampedTransform]) -> Any:
    """[(parent, child, stamp_ns, 4x4), ...] -> tf2_msgs/TFMessage (for /tf or /tf_static)."""
    return msgs.TFMessage(transforms=[stamped_transform_to_msg(t) for t in transforms])


def tf_message_to_transforms(msg: Any) -> list[StampedTransform]:
    """tf2_msgs/TFMessage -> [(parent, child, stamp_ns, 4x4), ...]; a bad transform is named by
    its index (`transforms[3].transform.rotation`). A node that must keep the good transforms of a
    message with a bad one decodes each with msg_to_stamped_transform (transforms.TransformBuffer
    checks them one by one)."""
    return [msg_to_stamped_transform(t, f"transforms[{i}]") for i, t in enumerate(msg.transforms)]
