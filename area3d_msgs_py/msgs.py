"""ROS 2 Jazzy message types: the generated Python classes of the ROS 2 wheels, in one namespace.

    >>> from area3d_msgs_py import msgs
    >>> t = msgs.Time(sec=1, nanosec=5)
    >>> msgs.deserialize(msgs.serialize(t), "builtin_interfaces/msg/Time") == t
    True

``tf2_msgs`` (TFMessage only; it is not on PyPI) and ``area3d_interfaces`` (NextBestView, MapFile,
HardRegion, HardRegionArray) are generated and built into the environment by ``make install``
(``tools/build_interfaces.py``); with a sourced ROS 2 install, colcon builds ``area3d_interfaces`` and
ROS 2 has ``tf2_msgs``.
"""

from __future__ import annotations

import importlib
from typing import Any

from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import (
    Point,
    Pose,
    PoseArray,
    PoseStamped,
    Quaternion,
    Transform,
    TransformStamped,
    Vector3,
)
from nav_msgs.msg import Odometry, Path
from nav_msgs.srv import GetPlan
from rclpy.serialization import deserialize_message, serialize_message
from sensor_msgs.msg import CameraInfo, Image, PointCloud2, PointField, RegionOfInterest
from std_msgs.msg import Header, String
from std_srvs.srv import Trigger
from visualization_msgs.msg import Marker, MarkerArray

from area3d_msgs_py.errors import InputError

try:
    from area3d_interfaces.msg import HardRegion, HardRegionArray
    from area3d_interfaces.srv import MapFile, NextBestView
    from tf2_msgs.msg import TFMessage
except ImportError as exc:  # built by `make install`, not installed by pip
    raise ImportError(
        f"{exc.name or exc}: the ROS 2 interfaces tf2_msgs and area3d_interfaces are not built "
        "into this environment: run `make install` (or `python tools/build_interfaces.py` with "
        "this environment's python)"
    ) from exc

GetPlan_Request = GetPlan.Request
GetPlan_Response = GetPlan.Response

__all__ = [
    "CameraInfo", "DiagnosticArray", "DiagnosticStatus", "KeyValue", "Marker", "MarkerArray",
    "GetPlan", "GetPlan_Request", "GetPlan_Response", "HardRegion",
    "HardRegionArray", "Header", "Image", "MapFile", "NextBestView", "Odometry", "Path", "Point",
    "PointCloud2", "PointField", "Pose", "PoseArray", "PoseStamped", "Quaternion",
    "RegionOfInterest", "String", "TFMessage", "Time", "Transform", "TransformStamped", "Trigger",
    "Vector3",
    "deserialize", "get", "serialize", "type_name_of",
]  # fmt: skip


def get(type_name: str) -> type:
    """The generated class of a type name such as ``"sensor_msgs/msg/Image"`` or ``"nav_msgs/srv/GetPlan"``."""
    package, sep, rest = type_name.partition("/")
    kind, sep2, name = rest.partition("/")
    if not (sep and sep2 and package and name and kind in ("msg", "srv")):
        raise InputError("type_name", type_name, "'pkg/msg/Name' such as 'std_msgs/msg/String'")
    try:
        return getattr(importlib.import_module(f"{package}.{kind}"), name)
    except (ImportError, AttributeError):
        raise InputError(
            "type_name",
            type_name,
            "a ROS 2 interface installed here, such as 'std_msgs/msg/String'",
        ) from None


def type_name_of(msg: Any) -> str:
    """ROS type name of a message instance, e.g. ``'sensor_msgs/msg/Image'``."""
    cls = type(msg)
    module = cls.__module__.split(".")
    if len(module) < 2 or module[1] not in ("msg", "srv") or not hasattr(cls, "_TYPE_SUPPORT"):
        raise InputError(
            "msg", cls.__name__, "a generated ROS 2 message such as std_msgs.msg.String"
        )
    return f"{module[0]}/{module[1]}/{cls.__name__}"


def serialize(msg: Any) -> bytes:
    """CDR bytes (with the 4-byte encapsulation header), exactly what a ROS 2 publisher sends."""
    return serialize_message(msg)


def deserialize(data: bytes, type_name: str) -> Any:
    """Message of ``type_name`` from CDR bytes."""
    return deserialize_message(bytes(data), get(type_name))
