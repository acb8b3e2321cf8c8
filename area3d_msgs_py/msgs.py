"""ROS 2 Jazzy message types (from the rosbags type store) and their CDR (de)serialisation.

The message classes are the rosbags dataclasses; the same CDR bytes travel over Cyclone DDS,
rclpy and rosbag2 files.

    >>> from area3d_msgs_py import msgs
    >>> t = msgs.Time(sec=1, nanosec=5)
    >>> msgs.deserialize(msgs.serialize(t), "builtin_interfaces/msg/Time") == t
    True
"""

from __future__ import annotations

from typing import Any

from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from area3d_msgs_py.errors import InputError

# nav_msgs/srv/GetPlan.srv as shipped in ROS 2 common_interfaces, split at "---" into the two
# message halves that rmw implementations transport (the type store holds messages only).
GETPLAN_REQUEST_MSG = """\
# Get a plan from the current position to the goal Pose
geometry_msgs/PoseStamped start
geometry_msgs/PoseStamped goal
float32 tolerance
"""
GETPLAN_RESPONSE_MSG = """\
nav_msgs/Path plan
"""

SERVICE_HALVES: dict[str, tuple[str, str]] = {
    "nav_msgs/srv/GetPlan": ("nav_msgs/srv/GetPlan_Request", "nav_msgs/srv/GetPlan_Response"),
}


def _build_typestore():
    store = get_typestore(Stores.ROS2_JAZZY)
    extra = {}
    for text, name in (
        (GETPLAN_REQUEST_MSG, "nav_msgs/srv/GetPlan_Request"),
        (GETPLAN_RESPONSE_MSG, "nav_msgs/srv/GetPlan_Response"),
    ):
        # The parser files every type under "<pkg>/msg/"; the service halves live under "srv".
        (definition,) = get_types_from_msg(text, name).values()
        extra[name] = definition
    store.register(extra)
    return store


typestore = _build_typestore()


def get(type_name: str) -> type:
    """Return the dataclass of a message type, e.g. ``get("sensor_msgs/msg/Image")``."""
    try:
        return typestore.types[type_name]
    except KeyError:
        raise InputError(
            "type_name", type_name, "a ROS 2 Jazzy message type such as 'std_msgs/msg/String'"
        ) from None


def type_name_of(msg: Any) -> str:
    """ROS type name of a message instance, e.g. ``'sensor_msgs/msg/Image'``."""
    name = getattr(type(msg), "__msgtype__", None)
    if name is None:
        raise InputError("msg", type(msg).__name__, "a message dataclass from area3d_msgs_py.msgs")
    return name


def service_types(srv_type_name: str) -> tuple[str, str]:
    """Request and response message type names of a service type such as ``nav_msgs/srv/GetPlan``."""
    try:
        return SERVICE_HALVES[srv_type_name]
    except KeyError:
        raise InputError(
            "srv_type_name", srv_type_name, f"one of {sorted(SERVICE_HALVES)}"
        ) from None


def serialize(msg: Any, type_name: str | None = None) -> bytes:
    """CDR bytes (little endian, with the 4-byte encapsulation header) exactly as a ROS 2 node sends."""
    return bytes(typestore.serialize_cdr(msg, type_name or type_name_of(msg)))


def deserialize(data: bytes | memoryview, type_name: str) -> Any:
    """Message from CDR bytes (either endianness, with the encapsulation header)."""
    return typestore.deserialize_cdr(data, type_name)


Header = get("std_msgs/msg/Header")
String = get("std_msgs/msg/String")
Time = get("builtin_interfaces/msg/Time")
Image = get("sensor_msgs/msg/Image")
CameraInfo = get("sensor_msgs/msg/CameraInfo")
RegionOfInterest = get("sensor_msgs/msg/RegionOfInterest")
PointCloud2 = get("sensor_msgs/msg/PointCloud2")
PointField = get("sensor_msgs/msg/PointField")
Pose = get("geometry_msgs/msg/Pose")
PoseStamped = get("geometry_msgs/msg/PoseStamped")
Point = get("geometry_msgs/msg/Point")
Quaternion = get("geometry_msgs/msg/Quaternion")
Transform = get("geometry_msgs/msg/Transform")
TransformStamped = get("geometry_msgs/msg/TransformStamped")
Vector3 = get("geometry_msgs/msg/Vector3")
Path = get("nav_msgs/msg/Path")
TFMessage = get("tf2_msgs/msg/TFMessage")
GetPlan_Request = get("nav_msgs/srv/GetPlan_Request")
GetPlan_Response = get("nav_msgs/srv/GetPlan_Response")
