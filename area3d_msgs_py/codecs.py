"""numpy <-> ROS 2 message codecs (on the generated rclpy message classes): Image, PointCloud2,
Pose / Transform / PoseArray, CameraInfo, stamps, TF (TFMessage), the NextBestView service and
hard regions.

Conventions: images are (H, W, 3) uint8 in rgb order, (H, W) uint8 for mono8 and (H, W) float32
metres for depth (NaN = no return); poses are 4x4 float64 homogeneous matrices; stamps are int
nanoseconds since the Unix epoch.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any, NamedTuple

import numpy as np

from area3d_msgs_py import msgs
from area3d_msgs_py.errors import InputError
from area3d_msgs_py.hard_region import HARD_REGION_DTYPE
from area3d_msgs_py.transforms import (  # noqa: F401  (rotations live there; re-exported here)
    QUATERNION_NORM_TOLERANCE,
    StampedTransform,
    check_quaternion,
    quaternion_to_rotation,
    rotation_to_quaternion,
)

NS_PER_S = 1_000_000_000
# REP 118 / sensor_msgs image_encodings: bytes per pixel and the numpy element type.
IMAGE_ENCODINGS: dict[str, tuple[int, int, str]] = {
    # encoding: (channels, bytes per channel, numpy kind)
    "rgb8": (3, 1, "u1"),
    "bgr8": (3, 1, "u1"),
    "mono8": (1, 1, "u1"),
    "16UC1": (1, 2, "u2"),
    "32FC1": (1, 4, "f4"),
}
# 16UC1 depth is millimetres (REP 118), 0 = no return.
DEPTH_MM_PER_M = 1000.0
UINT16_MAX = 65535

# sensor_msgs/PointField datatypes.
POINTFIELD_DTYPES: dict[int, str] = {
    1: "i1",
    2: "u1",
    3: "i2",
    4: "u2",
    5: "i4",
    6: "u4",
    7: "f4",
    8: "f8",
}
_DTYPE_TO_POINTFIELD = {v: k for k, v in POINTFIELD_DTYPES.items()}

# Rotation orthonormality tolerance on max |R^T R - I| (float64 poses composed a few times).
ROTATION_TOLERANCE = 1e-5


def _bytes_of(data: Any) -> np.ndarray:
    """(N,) uint8 view of a message's byte sequence (array.array, bytes or a list of ints)."""
    try:
        return np.frombuffer(data, dtype=np.uint8)
    except TypeError:
        return np.asarray(data, dtype=np.uint8).reshape(-1)


# stamps --------------------------------------------------------------------------------------
def stamp_to_ns(stamp: Any) -> int:
    """builtin_interfaces/Time -> int nanoseconds."""
    return int(stamp.sec) * NS_PER_S + int(stamp.nanosec)


def ns_to_stamp(ns: int) -> Any:
    """int nanoseconds (>= 0) -> builtin_interfaces/Time."""
    ns = int(ns)
    if ns < 0:
        raise InputError("stamp_ns", ns, "a non-negative int of nanoseconds")
    sec, nanosec = divmod(ns, NS_PER_S)
    if sec > np.iinfo(np.int32).max:
        raise InputError("stamp_ns", ns, "a time before 2038 (int32 seconds)")
    return msgs.Time(sec=sec, nanosec=nanosec)


def header(stamp_ns: int, frame_id: str) -> Any:
    """std_msgs/Header with the given stamp and frame."""
    if not isinstance(frame_id, str):
        raise InputError("frame_id", frame_id, "a str")
    return msgs.Header(stamp=ns_to_stamp(stamp_ns), frame_id=frame_id)


# images --------------------------------------------------------------------------------------
def image_to_msg(array: np.ndarray, encoding: str, stamp_ns: int, frame_id: str) -> Any:
    """sensor_msgs/Image from an array.

    array: rgb8/bgr8 (H, W, 3) uint8 in rgb order (bgr8 swaps on the wire); mono8 (H, W) uint8;
    32FC1 (H, W) float metres; 16UC1 (H, W) float metres (stored as millimetres, NaN/<=0 -> 0) or
    uint16 millimetres as is.
    """
    if encoding not in IMAGE_ENCODINGS:
        raise InputError("encoding", encoding, f"one of {sorted(IMAGE_ENCODINGS)}")
    channels, _, kind = IMAGE_ENCODINGS[encoding]
    array = np.asarray(array)
    expected_shape = "(H, W, 3)" if channels == 3 else "(H, W)"
    if array.ndim != (3 if channels == 3 else 2) or (channels == 3 and array.shape[2] != 3):
        raise InputError("array.shape", array.shape, f"{expected_shape} for {encoding}")
    if array.shape[0] == 0 or array.shape[1] == 0:
        raise InputError("array.shape", array.shape, "a non-empty image")
    if encoding in ("rgb8", "bgr8", "mono8"):
        if array.dtype != np.uint8:
            raise InputError("array.dtype", str(array.dtype), f"uint8 for {encoding}")
        pixels = array[..., ::-1] if encoding == "bgr8" else array
    elif encoding == "32FC1":
        if array.dtype.kind != "f":
            raise InputError("array.dtype", str(array.dtype), "a float dtype (metres) for 32FC1")
        pixels = array.astype("<f4", copy=False)
    else:
        if array.dtype == np.uint16:
            pixels = array.astype("<u2", copy=False)
        elif array.dtype.kind == "f":
            mm = np.rint(np.nan_to_num(array, nan=0.0, posinf=0.0, neginf=0.0) * DEPTH_MM_PER_M)
            pixels = np.clip(mm, 0, UINT16_MAX).astype("<u2")
        else:
            raise InputError(
                "array.dtype", str(array.dtype), "float metres or uint16 millimetres for 16UC1"
            )
    height, width = array.shape[:2]
    data = np.ascontiguousarray(pixels).tobytes()
    return msgs.Image(
        header=header(stamp_ns, frame_id),
        height=int(height),
        width=int(width),
        encoding=encoding,
        is_bigendian=0,
        step=width * IMAGE_ENCODINGS[encoding][0] * IMAGE_ENCODINGS[encoding][1],
        data=data,
    )


def msg_to_image(msg: Any) -> np.ndarray:
    """Array from sensor_msgs/Image (own memory, writable).

    rgb8/bgr8 -> (H, W, 3) uint8 rgb order; mono8 -> (H, W) uint8; 32FC1 -> (H, W) float32 metres;
    16UC1 -> (H, W) float32 metres from millimetres with 0 -> NaN. Row padding (step) and
    big-endian data are handled.
    """
    encoding = msg.encoding
    if encoding not in IMAGE_ENCODINGS:
        raise InputError("encoding", encoding, f"one of {sorted(IMAGE_ENCODINGS)}")
    channels, size, kind = IMAGE_ENCODINGS[encoding]
    height, width, step = int(msg.height), int(msg.width), int(msg.step)
    row_bytes = width * channels * size
    if step < row_bytes:
        raise InputError("step", step, f">= width * bytes per pixel = {row_bytes} for {encoding}")
    data = _bytes_of(msg.data)
    if data.size != height * step:
        raise InputError("data", f"{data.size} bytes", f"height * step = {height * step} bytes")
    order = ">" if msg.is_bigendian and size > 1 else "<"
    rows = data.reshape(height, step)[:, :row_bytes].copy()
    pixels = rows.view(order + kind).reshape((height, width, channels))
    if encoding == "bgr8":
        return np.ascontiguousarray(pixels[..., ::-1])
    if encoding == "rgb8":
        return pixels
    if encoding == "mono8":
        return pixels[..., 0].copy()
    if encoding == "32FC1":
        return pixels[..., 0].astype(np.float32)
    metres = pixels[..., 0].astype(np.float32) / np.float32(DEPTH_MM_PER_M)
    metres[pixels[..., 0] == 0] = np.nan
    return metres


# point clouds --------------------------------------------------------------------------------
def pointcloud_to_msg(points: np.ndarray, stamp_ns: int, frame_id: str) -> Any:
    """sensor_msgs/PointCloud2 from a structured array.

    points: (N,) unorganised or (H, W) organised structured array; every field a scalar of int8,
    uint8, int16, uint16, int32, uint32, float32 or float64 (one byte order for all), offsets and
    padding as in the dtype. ``is_dense`` is False when any float field holds a non-finite value.
    """
    points = np.asarray(points)
    if points.dtype.names is None:
        raise InputError(
            "points.dtype", str(points.dtype), "a structured dtype such as [('x','<f4'),...]"
        )
    if points.ndim not in (1, 2):
        raise InputError("points.shape", points.shape, "(N,) or (H, W)")
    fields = []
    orders = set()
    for name in points.dtype.names:
        field_dtype, offset = points.dtype.fields[name][:2]
        if field_dtype.shape:
            raise InputError(
                f"field {name!r}", str(field_dtype), "a scalar field (PointField count 1)"
            )
        code = field_dtype.kind + str(field_dtype.itemsize)
        if code not in _DTYPE_TO_POINTFIELD:
            raise InputError(
                f"field {name!r}", str(field_dtype), "one of int8..uint32, float32, float64"
            )
        if field_dtype.itemsize > 1:
            big = field_dtype.byteorder == ">" or (
                field_dtype.byteorder == "=" and not np.little_endian
            )
            orders.add(big)
        fields.append(
            msgs.PointField(
                name=name, offset=int(offset), datatype=_DTYPE_TO_POINTFIELD[code], count=1
            )
        )
    if len(orders) > 1:
        raise InputError("points.dtype", str(points.dtype), "all fields in one byte order")
    is_bigendian = bool(orders.pop()) if orders else False
    height, width = (1, points.shape[0]) if points.ndim == 1 else points.shape
    flat = np.ascontiguousarray(points).reshape(-1)
    is_dense = True
    for name in points.dtype.names:
        if points.dtype.fields[name][0].kind == "f" and not np.isfinite(flat[name]).all():
            is_dense = False
            break
    point_step = points.dtype.itemsize
    return msgs.PointCloud2(
        header=header(stamp_ns, frame_id),
        height=int(height),
        width=int(width),
        fields=fields,
        is_bigendian=is_bigendian,
        point_step=point_step,
        row_step=point_step * width,
        data=flat.tobytes(),
        is_dense=is_dense,
    )


def pointcloud_dtype(msg: Any) -> np.dtype:
    """Structured dtype (itemsize = point_step) described by a PointCloud2's fields."""
    names, formats, offsets = [], [], []
    order = ">" if msg.is_bigendian else "<"
    point_step = int(msg.point_step)
    for field in msg.fields:
        if field.datatype not in POINTFIELD_DTYPES:
            raise InputError(
                f"field {field.name!r} datatype", field.datatype, "1..8 (INT8..FLOAT64)"
            )
        if field.count not in (0, 1):
            raise InputError(f"field {field.name!r} count", field.count, "1 (scalar fields only)")
        code = POINTFIELD_DTYPES[field.datatype]
        size = int(code[1])
        if field.offset + size > point_step:
            raise InputError(
                f"field {field.name!r} offset",
                field.offset,
                f"offset + {size} <= point_step {point_step}",
            )
        if field.name in names:
            raise InputError("fields", field.name, "unique field names")
        names.append(field.name)
        formats.append((order if size > 1 else "|") + code)
        offsets.append(int(field.offset))
    try:
        return np.dtype(
            {"names": names, "formats": formats, "offsets": offsets, "itemsize": point_step}
        )
    except ValueError as exc:
        raise InputError(
            "fields", [f.name for f in msg.fields], f"non-overlapping fields ({exc})"
        ) from None


def msg_to_pointcloud(msg: Any) -> np.ndarray:
    """Structured array from sensor_msgs/PointCloud2 (own memory, native byte order kept as sent).

    Returns (width,) when height == 1, else (height, width); row padding is dropped.
    """
    dtype = pointcloud_dtype(msg)
    height, width, row_step = int(msg.height), int(msg.width), int(msg.row_step)
    if row_step < width * dtype.itemsize:
        raise InputError("row_step", row_step, f">= width * point_step = {width * dtype.itemsize}")
    data = _bytes_of(msg.data)
    if data.size != height * row_step:
        raise InputError(
            "data", f"{data.size} bytes", f"height * row_step = {height * row_step} bytes"
        )
    rows = data.reshape(height, row_step)[:, : width * dtype.itemsize].copy()
    cloud = rows.view(dtype).reshape(height, width)
    return cloud[0] if height == 1 else cloud


# poses ---------------------------------------------------------------------------------------
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


# camera info ---------------------------------------------------------------------------------
def intrinsics_to_camera_info(
    K: np.ndarray, width: int, height: int, stamp_ns: int, frame_id: str, baseline: float = 0.0
) -> Any:
    """sensor_msgs/CameraInfo of an undistorted pinhole camera (plumb_bob, zero distortion).

    K: (3, 3) intrinsics in pixels; R = identity and P = [K | 0] as ROS fills them for a
    monocular camera (or the left camera of a rectified pair). baseline: metres; > 0 makes this the
    right camera of a rectified pair, whose P[0, 3] = Tx = -fx * baseline (ROS CameraInfo).
    """
    if not (np.isfinite(baseline) and baseline >= 0):
        raise InputError("baseline", baseline, "metres >= 0 (0 = monocular or left camera)")
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3) or not np.isfinite(K).all():
        raise InputError(
            "K", K.shape if K.shape != (3, 3) else K.tolist(), "a finite 3x3 intrinsics matrix"
        )
    if K[0, 0] <= 0 or K[1, 1] <= 0 or not np.allclose(K[2], (0.0, 0.0, 1.0)):
        raise InputError("K", K.tolist(), "fx > 0, fy > 0 and last row [0, 0, 1]")
    for name, value in (("width", width), ("height", height)):
        if int(value) != value or value <= 0:
            raise InputError(name, value, "a positive int of pixels")
    P = np.zeros((3, 4))
    P[:, :3] = K
    P[0, 3] = -K[0, 0] * baseline
    return msgs.CameraInfo(
        header=header(stamp_ns, frame_id),
        height=int(height),
        width=int(width),
        distortion_model="plumb_bob",
        d=[0.0] * 5,
        k=K.reshape(-1).copy(),
        r=np.eye(3).reshape(-1),
        p=P.reshape(-1),
        binning_x=0,
        binning_y=0,
        roi=msgs.RegionOfInterest(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False),
    )


def camera_info_to_intrinsics(msg: Any) -> tuple[np.ndarray, int, int]:
    """(K (3, 3) float64, width, height) from sensor_msgs/CameraInfo."""
    K = np.asarray(msg.k, dtype=np.float64).reshape(3, 3)
    if K[0, 0] <= 0 or K[1, 1] <= 0 or not np.isfinite(K).all():
        raise InputError("k", K.reshape(-1).tolist(), "a calibrated camera (fx > 0, fy > 0)")
    if msg.width <= 0 or msg.height <= 0:
        raise InputError("width/height", (msg.width, msg.height), "positive image size")
    return K, int(msg.width), int(msg.height)


def camera_info_to_baseline(msg: Any) -> float:
    """Baseline in metres of the right camera of a rectified stereo pair: B = -Tx / fx, with
    Tx = P[0, 3] and fx = P[0, 0] of its sensor_msgs/CameraInfo (ROS convention)."""
    P = np.asarray(msg.p, dtype=np.float64).reshape(3, 4)
    if not (np.isfinite(P).all() and P[0, 0] > 0):
        raise InputError("p", P.reshape(-1).tolist(), "a rectified projection with fx = P[0] > 0")
    baseline = -P[0, 3] / P[0, 0]
    if baseline <= 0:
        raise InputError(
            "p[3]", float(P[0, 3]), "Tx = -fx * baseline < 0: the right camera of a stereo pair"
        )
    return float(baseline)


# TF ------------------------------------------------------------------------------------------
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


# the next-best-view service (area3d_interfaces/srv/NextBestView) ------------------------------
#: Planning modes a request may name; "" leaves the planner's own `mode` parameter.
VIEW_MODES = ("closed_loop", "batch")
UINT32_MAX = 2**32 - 1


class ViewRequest(NamedTuple):
    """A NextBestView request: how many views, the mode ("" = the planner's), the camera's
    current pose (4x4 in frame_id) and the stamp of the last frame it was captured with."""

    count: int
    mode: str
    current: np.ndarray
    stamp_ns: int
    frame_id: str


class ViewAnswer(NamedTuple):
    """A NextBestView response: views (N, 4, 4) optical-frame poses in frame_id, best first, and
    the predicted gain of each (N,); success False with a message and no views when refused."""

    success: bool
    message: str
    views: np.ndarray
    gains: np.ndarray
    stamp_ns: int
    frame_id: str


def _check_mode(mode: Any) -> str:
    if mode not in ("", *VIEW_MODES):
        raise InputError("mode", mode, f"one of {', '.join(VIEW_MODES)} or empty")
    return mode


def view_request_to_msg(
    count: int, current: np.ndarray, stamp_ns: int, frame_id: str, mode: str = ""
) -> Any:
    """area3d_interfaces/srv/NextBestView.Request. count: views wanted, 0 = what the budget
    allows; current: 4x4 camera pose in frame_id, stamped with the last captured frame."""
    if not isinstance(count, int | np.integer) or isinstance(count, bool):
        raise InputError("count", count, "an int of views >= 0 (0 = as many as the budget allows)")
    if not 0 <= count <= UINT32_MAX:
        raise InputError("count", count, "an int of views >= 0 (0 = as many as the budget allows)")
    pose = matrix_to_pose(current, "current")
    return msgs.NextBestView.Request(
        count=int(count),
        mode=_check_mode(mode),
        current=msgs.PoseStamped(header=header(stamp_ns, frame_id), pose=pose),
    )


def msg_to_view_request(msg: Any) -> ViewRequest:
    """Checked fields of a NextBestView request (mode, current pose); see ViewRequest."""
    return ViewRequest(
        count=int(msg.count),
        mode=_check_mode(msg.mode),
        current=pose_to_matrix(msg.current.pose, "current.pose"),
        stamp_ns=stamp_to_ns(msg.current.header.stamp),
        frame_id=msg.current.header.frame_id,
    )


def view_answer_to_msg(views: np.ndarray, gains: np.ndarray, stamp_ns: int, frame_id: str) -> Any:
    """A successful NextBestView.Response: views (N, 4, 4) best first, gains (N,) finite."""
    views = np.asarray(views, dtype=np.float64)
    gains = np.asarray(gains, dtype=np.float32).reshape(-1)
    pose_array = matrices_to_pose_array(views, stamp_ns, frame_id)
    if gains.shape != (len(views),):
        raise InputError("gains", gains.shape, f"({len(views)},): one gain per view")
    if not np.isfinite(gains).all():
        raise InputError("gains", gains.tolist(), "finite predicted gains")
    return msgs.NextBestView.Response(success=True, message="", views=pose_array, gains=gains)


def view_refusal_to_msg(message: str, stamp_ns: int, frame_id: str) -> Any:
    """A NextBestView.Response that says why no view is given (success False, no views)."""
    if not isinstance(message, str) or not message:
        raise InputError("message", message, "the reason no view is given")
    return msgs.NextBestView.Response(
        success=False,
        message=message,
        views=msgs.PoseArray(header=header(stamp_ns, frame_id), poses=[]),
        gains=np.zeros(0, np.float32),
    )


def msg_to_view_answer(msg: Any) -> ViewAnswer:
    """Checked fields of a NextBestView response; see ViewAnswer."""
    views = pose_array_to_matrices(msg.views, "views.poses")
    gains = np.array(msg.gains, dtype=np.float32)
    if gains.shape != (len(views),):
        raise InputError("gains", gains.shape, f"({len(views)},): one gain per view")
    return ViewAnswer(
        success=bool(msg.success),
        message=msg.message,
        views=views,
        gains=gains,
        stamp_ns=stamp_to_ns(msg.views.header.stamp),
        frame_id=msg.views.header.frame_id,
    )


# hard regions (area3d_interfaces/msg/HardRegionArray) ---------------------------------------
def hard_regions_to_msg(regions: np.ndarray, stamp_ns: int, frame_id: str) -> Any:
    """(N,) HARD_REGION_DTYPE -> area3d_interfaces/HardRegionArray (order kept)."""
    regions = np.asarray(regions)
    if regions.dtype != HARD_REGION_DTYPE or regions.ndim != 1:
        raise InputError(
            "regions", f"{regions.dtype} {regions.shape}", "a (N,) array of HARD_REGION_DTYPE"
        )
    numbers = np.concatenate(
        [regions["centroid"], regions["extent"], regions["mean_uncertainty"][:, None]], axis=1
    )
    if not np.isfinite(numbers).all():
        raise InputError("regions", "non-finite values", "finite centroids, extents, uncertainty")
    if (regions["extent"] < 0).any():
        raise InputError("regions.extent", regions["extent"].tolist(), "sizes >= 0 m")
    return msgs.HardRegionArray(
        header=header(stamp_ns, frame_id),
        regions=[
            msgs.HardRegion(
                centroid=msgs.Point(x=float(c[0]), y=float(c[1]), z=float(c[2])),
                extent=msgs.Vector3(x=float(e[0]), y=float(e[1]), z=float(e[2])),
                voxel_count=int(n),
                direction_count=int(d),
                mean_uncertainty=float(u),
            )
            for c, e, n, d, u in zip(
                regions["centroid"],
                regions["extent"],
                regions["voxel_count"],
                regions["direction_count"],
                regions["mean_uncertainty"],
                strict=True,
            )
        ],
    )


def msg_to_hard_regions(msg: Any) -> np.ndarray:
    """area3d_interfaces/HardRegionArray -> (N,) HARD_REGION_DTYPE."""
    regions = np.zeros(len(msg.regions), HARD_REGION_DTYPE)
    for i, region in enumerate(msg.regions):
        c, e = region.centroid, region.extent
        regions[i] = (
            (c.x, c.y, c.z),
            (e.x, e.y, e.z),
            region.voxel_count,
            region.direction_count,
            region.mean_uncertainty,
        )
    return regions
