"""The camera pose of each frame from TF or odometry (area3d_msgs_py.pose_source): interpolated to
the frame's stamp, frames waiting for late transforms, drops counted by cause, bad samples refused
by field."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from area3d_msgs_py.errors import InputError
from area3d_msgs_py.pose_source import (
    MOUNTED_CAMERA,
    CameraPoses,
    PoseSourceConfig,
    tf_fields,
)
from area3d_msgs_py.rotations import matrix, rotation_to_quaternion
from area3d_msgs_py.transforms import LookupFailure

S = 1_000_000_000
T0 = 1_700_000_000 * S
NOW = T0 + 3600 * S  # the node's clock: well after every stamp below
ODOM_HZ = 50
# the camera's optical frame on the body: 0.2 m ahead, 0.5 m up, looking along the body's x
MOUNT_T = (0.2, 0.0, 0.5)
MOUNT_Q = (-0.5, 0.5, -0.5, 0.5)


def body_at(t_s: float) -> np.ndarray:
    """T_odom_base of a body driving a circle of radius 2 m at 0.5 m/s, turning with it."""
    yaw = 0.25 * t_s
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("z", yaw).as_matrix()
    T[:3, 3] = [2.0 * np.sin(yaw), 2.0 - 2.0 * np.cos(yaw), 0.0]
    return T


def odometry_source(**kw) -> CameraPoses:
    config = PoseSourceConfig(
        pose_source="odometry",
        camera_mount="parameters",
        mount_translation=MOUNT_T,
        mount_rotation=MOUNT_Q,
        **kw,
    )
    return CameraPoses(config, "odom")


def feed_odometry(poses: CameraPoses, seconds: float, start_s: float = 0.0) -> None:
    for i in range(int(start_s * ODOM_HZ), int(seconds * ODOM_HZ) + 1):
        T = body_at(i / ODOM_HZ)
        poses.add_odometry(
            "odom", "base_link", T0 + i * S // ODOM_HZ, T[:3, 3], rotation_to_quaternion(T[:3, :3]),
            NOW,
        )  # fmt: skip


def test_odometry_is_interpolated_to_the_images_stamp_and_composed_with_the_mount():
    poses = odometry_source()
    feed_odometry(poses, 2.0)
    mount = matrix(np.array(MOUNT_T), np.array(MOUNT_Q))
    for t_s in (0.013, 0.5, 1.2345):  # images stamped between odometry samples
        (posed,) = poses.submit(T0 + int(t_s * S), "camera_color_optical_frame", "frame", NOW)
        assert posed.frame == "frame" and posed.stamp_ns == T0 + int(t_s * S)
        expected = body_at(t_s) @ mount
        # linear in translation between samples 20 ms apart on a 2 m circle: within 0.1 mm
        np.testing.assert_allclose(posed.T[:3, 3], expected[:3, 3], atol=1e-4)
        np.testing.assert_allclose(posed.T[:3, :3], expected[:3, :3], atol=1e-9)
    # the optical axis looks along the body's x axis
    np.testing.assert_allclose(mount[:3, 2], [1.0, 0.0, 0.0], atol=1e-12)


def test_the_mount_can_come_from_tf_static_and_tf_gives_the_images_frame():
    mount = matrix(np.array(MOUNT_T), np.array(MOUNT_Q))
    from_static = CameraPoses(PoseSourceConfig(pose_source="odometry"), "odom")
    link = (0.2, 0.0, 0.5), (0.0, 0.0, 0.0, 1.0)
    optical = (0.0, 0.0, 0.0), MOUNT_Q
    from_static.add_transform("base_link", "camera_link", 0, *link, static=True, now_ns=NOW)
    from_static.add_transform("camera_link", "cam_optical", 0, *optical, static=True, now_ns=NOW)
    feed_odometry(from_static, 1.0)
    (posed,) = from_static.submit(T0 + S // 2, "cam_optical", None, NOW)
    np.testing.assert_allclose(posed.T, body_at(0.5) @ mount, atol=1e-4)

    tf = CameraPoses(PoseSourceConfig(pose_source="tf"), "map")
    tf.add_transform("camera_link", "cam_optical", 0, *optical, static=True, now_ns=NOW)
    tf.add_transform("map", "odom", T0, (1.0, 0.0, 0.0), (0, 0, 0, 1), static=False, now_ns=NOW)
    tf.add_transform("map", "odom", T0 + S, (1.0, 0.0, 0.0), (0, 0, 0, 1), static=False, now_ns=NOW)
    for i in range(ODOM_HZ + 1):
        T = body_at(i / ODOM_HZ)
        q = rotation_to_quaternion(T[:3, :3])
        stamp = T0 + i * S // ODOM_HZ
        tf.add_transform("odom", "base_link", stamp, T[:3, 3], q, static=False, now_ns=NOW)
    tf.add_transform("base_link", "camera_link", 0, *link, static=True, now_ns=NOW)
    (posed,) = tf.submit(T0 + S // 2, "cam_optical", None, NOW)
    expected = body_at(0.5) @ mount
    expected[0, 3] += 1.0  # map -> odom
    np.testing.assert_allclose(posed.T, expected, atol=1e-4)


def test_a_frame_waits_for_the_odometry_after_its_stamp_then_is_posed():
    poses = odometry_source()
    feed_odometry(poses, 1.0)
    stamp = T0 + S + S // 100  # 10 ms after the newest sample: not arrived yet
    assert poses.submit(stamp, "cam", "late", NOW) == [] and len(poses) == 1
    assert poses.release(NOW) == [] and len(poses) == 1
    feed_odometry(poses, 1.1, start_s=1.02)
    (posed,) = poses.release(NOW)
    assert posed.frame == "late" and len(poses) == 0 and poses.pop_drops() == []
    assert poses.status() == {"frames_waiting_for_pose": 0, "frames_dropped_no_pose": {}}


def test_frames_without_a_pose_are_dropped_and_counted_by_cause_logged_once_each():
    poses = odometry_source(pose_wait_s=2.0, pose_history_s=10.0)
    assert poses.submit(T0, "cam", "before any odometry", NOW) == []
    feed_odometry(poses, 20.0)  # 20 s of odometry: 10 s are kept
    # the first frame's stamp lies before the 10 s of history now kept: never posed
    assert poses.release(NOW) == []
    (too_old,) = poses.pop_drops()
    assert (too_old.cause, too_old.first) == (LookupFailure.TOO_OLD, True)
    assert "history_s 10" in too_old.message and f"stamp {T0}" in too_old.message
    assert poses.submit(T0 + 5 * S, "cam", "old", NOW) == []  # dropped at once
    (again,) = poses.pop_drops()
    assert again.cause == LookupFailure.TOO_OLD and not again.first  # logged once per cause
    future = T0 + 30 * S
    assert poses.submit(future, "cam", "future", NOW) == []
    assert poses.release(NOW + 2 * S) == [] and poses.pop_drops() == []  # still waiting
    assert poses.release(NOW + 2 * S + 1) == []
    (late,) = poses.pop_drops()
    assert (late.cause, late.first) == (LookupFailure.IN_FUTURE, True)
    assert "pose_wait_s 2" in late.message and "not arrived yet" in late.message
    assert poses.status() == {
        "frames_waiting_for_pose": 0,
        "frames_dropped_no_pose": {"too_old": 2, "in_future": 1},
    }


def test_a_frame_taken_during_an_odometry_outage_is_dropped_not_posed_by_interpolation():
    poses = odometry_source()  # pose_max_interval_s 1 s by default
    feed_odometry(poses, 1.0)
    feed_odometry(poses, 5.0, start_s=4.0)  # no odometry from 1 s to 4 s
    # waiting after the outage: the samples around its stamp are in, 3 s apart
    assert poses.submit(T0 + 2 * S, "cam", "during", NOW) == []
    (gap,) = poses.pop_drops()
    assert (gap.cause, gap.first) == (LookupFailure.GAP, True)
    assert "3.000 s apart" in gap.message and "max_interval_s 1" in gap.message
    # a frame stamped during the outage, before its end arrived, waits and is dropped once it has
    late = odometry_source()
    feed_odometry(late, 1.0)
    assert late.submit(T0 + 2 * S, "cam", "during", NOW) == [] and len(late) == 1
    feed_odometry(late, 5.0, start_s=4.0)
    assert late.release(NOW) == [] and len(late) == 0
    assert [d.cause for d in late.pop_drops()] == [LookupFailure.GAP]
    (after,) = late.submit(T0 + 4 * S + S // 100, "cam", "after", NOW)  # posed again
    assert poses.status()["frames_dropped_no_pose"] == {"gap": 1}
    assert after.frame == "after"
    # with no limit, as tf2, the outage is interpolated across
    unlimited = odometry_source(pose_max_interval_s=0.0)
    feed_odometry(unlimited, 1.0)
    feed_odometry(unlimited, 5.0, start_s=4.0)
    (across,) = unlimited.submit(T0 + 2 * S, "cam", "during", NOW)
    assert across.frame == "during" and unlimited.pop_drops() == []


def test_an_unknown_image_frame_waits_then_is_dropped_as_no_transform():
    tf = CameraPoses(PoseSourceConfig(pose_source="tf", pose_wait_s=1.0), "world")
    tf.add_transform("world", "camera_link", T0, (0, 0, 1), (0, 0, 0, 1), static=False, now_ns=NOW)
    assert tf.submit(T0, "camera_optical_frame", "f", NOW) == []  # its static edge not yet in
    optical = (0.0, 0.0, 0.0), MOUNT_Q
    tf.add_transform("camera_link", "camera_optical_frame", 0, *optical, static=True, now_ns=NOW)
    (posed,) = tf.release(NOW)  # the static edge arrived: posed
    assert posed.frame == "f"
    assert tf.submit(T0, "elsewhere", "g", NOW) == []
    tf.release(NOW + 2 * S)
    (drop,) = tf.pop_drops()
    assert drop.cause == LookupFailure.NO_TRANSFORM and "'elsewhere'" in drop.message


def test_waiting_frames_are_bounded():
    poses = CameraPoses(PoseSourceConfig(pose_source="tf"), "world", capacity=3)
    for i in range(5):
        poses.submit(T0 + i, "cam", i, NOW)
    assert len(poses) == 3 and [d.stamp_ns for d in poses.pop_drops()] == [T0, T0 + 1]


@pytest.mark.parametrize(
    "change, field",
    [
        ({"frame_id": "map"}, "header.frame_id"),
        ({"child_frame_id": "base_footprint"}, "child_frame_id"),
        ({"orientation": (0.0, 0.0, 0.0, 2.0)}, "pose.pose.orientation"),
        ({"orientation": (0.0, 0.0, 0.0, 0.0)}, "pose.pose.orientation"),
        ({"position": (np.nan, 0.0, 0.0)}, "pose.pose.position"),
        ({"stamp_ns": NOW + 3600 * S}, "header.stamp"),
        ({"position": (5.0, 0.0, 0.0)}, "pose.pose.position"),  # 5 m in 20 ms: a jump
        ({"orientation": (1.0, 0.0, 0.0, 0.0)}, "pose.pose.orientation"),  # 180 deg in 20 ms
    ],
)
def test_bad_odometry_is_refused_naming_the_field_and_the_map_keeps_the_good(change, field):
    poses = odometry_source(pose_max_linear_speed=5.0, pose_max_angular_speed=10.0)
    feed_odometry(poses, 0.0)  # one sample at T0, the body at the origin
    sample = {
        "frame_id": "odom",
        "child_frame_id": "base_link",
        "stamp_ns": T0 + S // ODOM_HZ,
        "position": (0.0, 0.0, 0.0),
        "orientation": (0.0, 0.0, 0.0, 1.0),
    } | change
    with pytest.raises(InputError) as refused:
        poses.add_odometry(**sample, now_ns=NOW)
    assert refused.value.field == field
    assert MOUNTED_CAMERA in poses.buffer.frames()
    (posed,) = poses.submit(T0, "cam", None, NOW)  # the sample before it still holds
    np.testing.assert_allclose(posed.T[:3, 3], MOUNT_T, atol=1e-12)


def test_bad_tf_is_refused_naming_the_transform_and_its_field():
    tf = CameraPoses(PoseSourceConfig(pose_source="tf", pose_max_linear_speed=2.0), "world")
    fields = tf_fields(3)
    assert fields.rotation == "transforms[3].transform.rotation"
    cases = [
        ((0, 0, 1), (0, 0, 0, 2.0), T0, "transforms[3].transform.rotation"),
        ((np.inf, 0, 1), (0, 0, 0, 1.0), T0, "transforms[3].transform.translation"),
        ((0, 0, 1), (0, 0, 0, 1.0), NOW + 10 * S, "transforms[3].header.stamp"),
    ]
    for t, q, stamp, field in cases:
        with pytest.raises(InputError) as refused:
            tf.add_transform(
                "world", "camera_link", stamp, t, q, static=False, now_ns=NOW, fields=fields
            )
        assert refused.value.field == field
    tf.add_transform("world", "camera_link", T0, (0, 0, 1), (0, 0, 0, 1), static=False, now_ns=NOW)
    with pytest.raises(InputError, match="a jump") as jump:
        tf.add_transform(
            "world", "camera_link", T0 + S // 10, (3, 0, 1), (0, 0, 0, 1), static=False,
            now_ns=NOW, fields=fields,
        )  # fmt: skip
    assert jump.value.field == "transforms[3].transform.translation"


def test_a_mount_that_is_not_a_rigid_transform_is_refused_at_start():
    with pytest.raises(InputError) as refused:
        CameraPoses(
            PoseSourceConfig(
                pose_source="odometry", camera_mount="parameters", mount_rotation=(0, 0, 0, 3.0)
            ),
            "odom",
        )
    assert refused.value.field == "mount_rotation"
    with pytest.raises(InputError, match="body_frame"):
        CameraPoses(PoseSourceConfig(pose_source="odometry", body_frame="odom"), "odom")
    with pytest.raises(InputError, match="pose_source"):
        CameraPoses(PoseSourceConfig(pose_source="topic"), "world")
