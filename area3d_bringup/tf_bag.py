"""TF for the episode's bag where `tf2_msgs` does not import (it is not on PyPI).

The bag always carries `/tf` (world -> camera_link at every captured frame) and `/tf_static`
(camera_link -> camera_optical_frame), exactly what sim_bridge publishes with a sourced ROS 2;
the messages are built and serialised with the rosbags Jazzy type store.
"""

from __future__ import annotations

import numpy as np
from rosbags.typesys import Stores, get_typestore

from area3d_msgs_py.codecs import NS_PER_S, rotation_to_quaternion
from sim_bridge.camera import R_LINK_OPTICAL, link_from_optical
from sim_bridge.node import LINK_FRAME, OPTICAL_FRAME, WORLD_FRAME

_STORE = get_typestore(Stores.ROS2_JAZZY)
_T = _STORE.types


def _transform_stamped(T: np.ndarray, stamp_ns: int, parent: str, child: str):
    sec, nanosec = divmod(int(stamp_ns), NS_PER_S)
    x, y, z, w = rotation_to_quaternion(T[:3, :3])
    return _T["geometry_msgs/msg/TransformStamped"](
        header=_T["std_msgs/msg/Header"](
            stamp=_T["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec), frame_id=parent
        ),
        child_frame_id=child,
        transform=_T["geometry_msgs/msg/Transform"](
            translation=_T["geometry_msgs/msg/Vector3"](x=T[0, 3], y=T[1, 3], z=T[2, 3]),
            rotation=_T["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w),
        ),
    )


def _tf_message(transforms: list) -> bytes:
    msg = _T["tf2_msgs/msg/TFMessage"](transforms=transforms)
    return bytes(_STORE.serialize_cdr(msg, "tf2_msgs/msg/TFMessage"))


def tf_cdr(stamp_ns: int, T_world_optical: np.ndarray) -> bytes:
    """CDR of tf2_msgs/TFMessage world -> camera_link for an optical-frame pose."""
    T = link_from_optical(np.asarray(T_world_optical, float))
    return _tf_message([_transform_stamped(T, stamp_ns, WORLD_FRAME, LINK_FRAME)])


def static_tf_cdr(stamp_ns: int) -> bytes:
    """CDR of tf2_msgs/TFMessage camera_link -> camera_optical_frame."""
    T = np.eye(4)
    T[:3, :3] = R_LINK_OPTICAL
    return _tf_message([_transform_stamped(T, stamp_ns, LINK_FRAME, OPTICAL_FRAME)])
