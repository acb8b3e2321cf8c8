"""TF benchmark: a camera pose per frame from a robot's TF tree or from odometry
(`area3d bench tf`).

The tree of a mobile robot with a camera: map -> odom (localisation, 20 Hz), odom -> base_link
(odometry, 50 Hz), base_link -> camera_link -> camera_color_optical_frame (static). A 30 Hz camera
needs, per frame, the TF samples that arrived since the last frame decoded from their CDR and
added (about 2.3), then one lookup of map -> camera_color_optical_frame at the image's stamp, between samples
(interpolated). The same with a pose stream: 50 Hz nav_msgs/Odometry plus the fixed mount,
interpolated to the image's stamp. Ten seconds of history are kept, as tf2 does.
"""

from __future__ import annotations

import time

import numpy as np
from rich.console import Console
from rich.table import Table

from area3d_msgs_py import codecs, msgs
from area3d_msgs_py.rotations import matrix, rotation_to_quaternion
from area3d_msgs_py.transforms import (
    NS_PER_S,
    ODOMETRY_FIELDS,
    PoseStream,
    StampedTransform,
    TransformBuffer,
)

TARGET_US = 1000.0  # pose lookup and interpolation per frame (issue: < 1 ms)
CAMERA_HZ = 30.0
ODOMETRY_HZ = 50.0
LOCALISATION_HZ = 20.0
T0 = 1_700_000_000 * NS_PER_S


def _yaw(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _base_in_odom(t_s: float) -> np.ndarray:
    """A robot driving a 2 m circle at 0.5 m/s."""
    angle = 0.25 * t_s
    T = np.eye(4)
    T[:3, :3] = _yaw(angle + np.pi / 2)
    T[:3, 3] = (2.0 * np.cos(angle), 2.0 * np.sin(angle), 0.0)
    return T


def _map_to_odom(t_s: float) -> np.ndarray:
    """Localisation's slow drift correction."""
    T = np.eye(4)
    T[:3, :3] = _yaw(0.01 * np.sin(0.1 * t_s))
    T[:3, 3] = (0.05 * np.sin(0.05 * t_s), 0.02, 0.0)
    return T


CAMERA_MOUNT = matrix(np.array([0.2, 0.0, 0.5]), np.array([0.0, 0.0, 0.0, 1.0]))
OPTICAL = np.array(
    [[0.0, 0.0, 1.0, 0.0], [-1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, 0.0], [0, 0, 0, 1]]
)


def _cdr(edges: list[StampedTransform]) -> bytes:
    return msgs.serialize(codecs.transforms_to_tf_message(edges))


def _tf_stream(seconds: float) -> list[tuple[int, bytes]]:
    """(stamp_ns, CDR of a tf2_msgs/TFMessage) of the dynamic edges, in order of stamp."""
    messages = []
    for hz, parent, child, pose in (
        (ODOMETRY_HZ, "odom", "base_link", _base_in_odom),
        (LOCALISATION_HZ, "map", "odom", _map_to_odom),
    ):
        for i in range(int(seconds * hz)):
            stamp = T0 + int(i * NS_PER_S / hz)
            edge = StampedTransform(parent, child, stamp, pose(i / hz))
            messages.append((stamp, _cdr([edge])))
    return sorted(messages, key=lambda m: m[0])


def _odometry_stream(seconds: float) -> list[tuple[int, bytes]]:
    messages = []
    for i in range(int(seconds * ODOMETRY_HZ)):
        stamp = T0 + int(i * NS_PER_S / ODOMETRY_HZ)
        pose = codecs.matrix_to_pose(_base_in_odom(i / ODOMETRY_HZ))
        odometry = msgs.Odometry(header=codecs.header(stamp, "odom"), child_frame_id="base_link")
        odometry.pose.pose = pose
        messages.append((stamp, msgs.serialize(odometry)))
    return messages


def _add_tf(buffer: TransformBuffer, data: bytes) -> None:
    message = msgs.deserialize(data, "tf2_msgs/msg/TFMessage")
    for edge in message.transforms:
        t, q = edge.transform.translation, edge.transform.rotation
        buffer.add(
            edge.header.frame_id,
            edge.child_frame_id,
            codecs.stamp_to_ns(edge.header.stamp),
            (t.x, t.y, t.z),
            (q.x, q.y, q.z, q.w),
        )


def _add_odometry(stream: PoseStream, data: bytes) -> None:
    message = msgs.deserialize(data, "nav_msgs/msg/Odometry")
    p, q = message.pose.pose.position, message.pose.pose.orientation
    stream.add(
        codecs.stamp_to_ns(message.header.stamp),
        (p.x, p.y, p.z),
        (q.x, q.y, q.z, q.w),
        message.header.frame_id,
        message.child_frame_id,
    )


def _frames(
    messages: list[tuple[int, bytes]], seconds: float, add, lookup
) -> tuple[np.ndarray, np.ndarray]:
    """Per camera frame: µs to add what arrived since the last frame plus the lookup, and µs of
    the lookup alone. A frame is looked up once the samples after its stamp have arrived (as a
    tf2 message filter waits for them): those up to one localisation period later."""
    totals, lookups = [], []
    next_message = 0
    for k in range(1, int((seconds - 1.0 / LOCALISATION_HZ) * CAMERA_HZ)):  # within the stream
        image_ns = T0 + int(k * NS_PER_S / CAMERA_HZ)
        t0 = time.perf_counter_ns()
        arrived_ns = image_ns + int(NS_PER_S / LOCALISATION_HZ)
        while next_message < len(messages) and messages[next_message][0] <= arrived_ns:
            add(messages[next_message][1])
            next_message += 1
        t1 = time.perf_counter_ns()
        lookup(image_ns)
        t2 = time.perf_counter_ns()
        totals.append((t2 - t0) / 1e3)
        lookups.append((t2 - t1) / 1e3)
    return np.array(totals), np.array(lookups)


def run_bench(seconds: float = 60.0) -> dict:
    """Time both paths over `seconds` of robot motion; print a table; return the figures in µs."""
    buffer = TransformBuffer(tolerance_s=0.0, max_linear_speed=5.0, max_angular_speed=6.0)
    buffer.add(
        "base_link", "camera_link", 0, CAMERA_MOUNT[:3, 3], (0.0, 0.0, 0.0, 1.0), static=True
    )
    buffer.add(
        "camera_link",
        "camera_color_optical_frame",
        0,
        (0.0, 0.0, 0.0),
        rotation_to_quaternion(OPTICAL[:3, :3]),
        static=True,
    )
    tf_total, tf_lookup = _frames(
        _tf_stream(seconds),
        seconds,
        lambda data: _add_tf(buffer, data),
        lambda stamp: buffer.lookup("map", "camera_color_optical_frame", stamp),
    )
    # one answer checked against the trajectory itself: a wrong lookup is no benchmark
    last_s = seconds - 0.513  # between samples of both dynamic edges
    expected = _map_to_odom(last_s) @ _base_in_odom(last_s) @ CAMERA_MOUNT @ OPTICAL
    got = buffer.lookup("map", "camera_color_optical_frame", T0 + int(last_s * NS_PER_S))
    error_m = float(np.abs(got[:3, 3] - expected[:3, 3]).max())

    stream = PoseStream(
        "odom",
        "base_link",
        CAMERA_MOUNT @ OPTICAL,
        fields=ODOMETRY_FIELDS,
        max_linear_speed=5.0,
        max_angular_speed=6.0,
    )
    odom_total, odom_lookup = _frames(
        _odometry_stream(seconds), seconds, lambda data: _add_odometry(stream, data), stream.pose_at
    )

    rows = {
        "tf_frame": tf_total,
        "tf_lookup": tf_lookup,
        "odometry_frame": odom_total,
        "odometry_lookup": odom_lookup,
    }
    figures = {f"{name}_p50_us": float(np.median(v)) for name, v in rows.items()}
    figures |= {f"{name}_p95_us": float(np.percentile(v, 95)) for name, v in rows.items()}
    figures |= {"target_us": TARGET_US, "frames": int(len(tf_total)), "error_m": error_m}

    table = Table(
        title=(
            f"TF: {len(tf_total)} camera frames at {CAMERA_HZ:g} Hz over {seconds:g} s; "
            f"odometry {ODOMETRY_HZ:g} Hz, localisation {LOCALISATION_HZ:g} Hz, 10 s history"
        )
    )
    for column in ("per frame", "p50 µs", "p95 µs", "target µs", "target / p95"):
        table.add_column(column, justify="left" if column == "per frame" else "right")
    labels = {
        "tf_frame": "TF: decode + add + lookup",
        "tf_lookup": "  the lookup (4 edges)",
        "odometry_frame": "odometry: decode + add + pose",
        "odometry_lookup": "  the pose (interpolated)",
    }
    for name, label in labels.items():
        p95 = figures[f"{name}_p95_us"]
        target = name.endswith("frame")
        table.add_row(
            label,
            f"{figures[f'{name}_p50_us']:.0f}",
            f"{p95:.0f}",
            f"{TARGET_US:.0f}" if target else "",
            f"{TARGET_US / p95:.1f}x" if target else "",
        )
    Console().print(table)
    print(f"a lookup between samples against the trajectory itself: {error_m * 1e6:.2g} µm off")
    return figures


if __name__ == "__main__":
    run_bench()
