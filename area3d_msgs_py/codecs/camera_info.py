"""sensor_msgs/CameraInfo <-> intrinsics: an undistorted pinhole camera, and the right camera of a
rectified stereo pair."""

from __future__ import annotations

from typing import Any

import numpy as np

from area3d_msgs_py import msgs
from area3d_msgs_py.codecs.header import header
from area3d_msgs_py.errors import InputError


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
