"""The simulated camera core and the sim_bridge node on the wire (Cyclone DDS on loopback)."""

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from sim_bridge.camera import SimCamera, add_depth_noise, link_from_optical
from sim_bridge.render import RgbdRenderer
from sim_bridge.scenes import load_scene

REPO_ROOT = Path(__file__).resolve().parents[2]
DOMAIN_ID = 1 + (os.getpid() + 101) % 200
TIMEOUT_S = 40.0


def test_capture_renders_valid_goals_and_refuses_bad_ones():
    scene = load_scene("single_object")
    camera = SimCamera(scene, width=160, height=120)
    try:
        good = camera.capture(scene.initial_views[0])
        assert good.ok and good.rgb.shape == (120, 160, 3) and good.depth.shape == (120, 160)
        bad = scene.initial_views[0].copy()
        bad[:3, 3] = scene.workspace_max + 1.0
        refused = camera.capture(bad)
        assert not refused.ok and refused.rgb is None and "workspace" in refused.reason
    finally:
        camera.close()


def test_camera_link_is_x_forward_z_up_of_the_optical_frame():
    scene = load_scene("single_object")
    T = scene.initial_views[1]
    link = link_from_optical(T)
    assert np.allclose(link[:3, 0], T[:3, 2])  # link x = optical z (forward)
    assert np.allclose(link[:3, 2], -T[:3, 1])  # link z = -optical y (up)
    assert np.allclose(link[:3, 3], T[:3, 3])


def test_depth_noise_keeps_holes_and_grows_with_distance():
    rng = np.random.default_rng(0)
    depth = np.full((200, 200), 1.0, dtype=np.float32)
    depth[:, 100:] = 4.0
    depth[0, 0] = np.nan
    noisy = add_depth_noise(depth, rng)
    assert np.isnan(noisy[0, 0]) and noisy.dtype == np.float32
    near, far = np.nanstd(noisy[:, :100] - 1.0), np.std(noisy[:, 100:] - 4.0)
    assert 0.0005 < near < far


@pytest.fixture(scope="module")
def loopback():
    from area3d_msgs_py import dds_config

    with dds_config.loopback_domain(DOMAIN_ID):
        yield


def test_node_publishes_a_frame_per_valid_goal_and_a_status_per_goal(loopback):
    from area3d_msgs_py.node import Node

    from area3d_msgs_py import codecs, msgs

    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "sim_bridge.node",
            "--ros-args",
            "-p",
            "scene:=single_object",
            "-p",
            "width:=160",
            "-p",
            "height:=120",
        ],
        env=dict(os.environ, PYTHONPATH=str(REPO_ROOT)),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    node = Node("sim_bridge_probe", backend="dds")
    got = {k: [] for k in ("status", "color", "depth", "info", "pose", "tf", "tf_static")}
    topics = {
        "status": ("std_msgs/msg/String", "/area3d/camera/status", False),
        "color": ("sensor_msgs/msg/Image", "/area3d/camera/color/image_raw", False),
        "depth": ("sensor_msgs/msg/Image", "/area3d/camera/depth/image_raw", False),
        "info": ("sensor_msgs/msg/CameraInfo", "/area3d/camera/camera_info", False),
        "pose": ("geometry_msgs/msg/PoseStamped", "/area3d/camera/pose", False),
        "tf": ("tf2_msgs/msg/TFMessage", "/tf", False),
        "tf_static": ("tf2_msgs/msg/TFMessage", "/tf_static", True),
    }
    for key, (type_name, topic, latched) in topics.items():
        node.create_subscription(type_name, topic, got[key].append, latched=latched)
    goal_pub = node.create_publisher("geometry_msgs/msg/PoseStamped", "/area3d/camera/goal_pose")
    scene = load_scene("single_object")
    T = scene.initial_views[2]
    stamp_ok = 1_700_000_000_000_000_123

    def statuses():
        return [json.loads(m.data) for m in got["status"]]

    try:
        deadline = time.monotonic() + TIMEOUT_S
        while (
            not any(s["stamp_ns"] == stamp_ok for s in statuses()) and time.monotonic() < deadline
        ):
            goal_pub.publish(
                msgs.PoseStamped(
                    header=codecs.header(stamp_ok, "world"), pose=codecs.matrix_to_pose(T)
                )
            )
            t_end = time.monotonic() + 1.0
            while time.monotonic() < t_end:
                node.spin_once(0.05)
        assert any(s["stamp_ns"] == stamp_ok and s["ok"] for s in statuses()), proc.poll()

        # Invalid goals: a non-unit quaternion and a pose inside the object, each answered with a reason.
        bad_quat = msgs.PoseStamped(
            header=codecs.header(stamp_ok + 1, "world"), pose=codecs.matrix_to_pose(T)
        )
        bad_quat.pose.orientation.w = 3.0
        inside = T.copy()
        model, data = scene.model()
        inside[:3, 3] = data.xpos[model.body("obj0").id] + [0, 0, 0.06]
        goal_pub.publish(bad_quat)
        goal_pub.publish(
            msgs.PoseStamped(
                header=codecs.header(stamp_ok + 2, "world"), pose=codecs.matrix_to_pose(inside)
            )
        )
        deadline = time.monotonic() + TIMEOUT_S
        while (
            len({s["stamp_ns"] for s in statuses()} & {stamp_ok + 1, stamp_ok + 2}) < 2
            and time.monotonic() < deadline
        ):
            node.spin_once(0.05)
        by_stamp = {s["stamp_ns"]: s for s in statuses()}
        assert (
            by_stamp[stamp_ok + 1]["ok"] is False
            and "orientation" in by_stamp[stamp_ok + 1]["reason"]
        )
        assert (
            by_stamp[stamp_ok + 2]["ok"] is False and "geometry" in by_stamp[stamp_ok + 2]["reason"]
        )
        assert proc.poll() is None  # still running after bad input

        color = next(m for m in got["color"] if codecs.stamp_to_ns(m.header.stamp) == stamp_ok)
        depth = next(m for m in got["depth"] if codecs.stamp_to_ns(m.header.stamp) == stamp_ok)
        info = next(m for m in got["info"] if codecs.stamp_to_ns(m.header.stamp) == stamp_ok)
        pose = next(m for m in got["pose"] if codecs.stamp_to_ns(m.header.stamp) == stamp_ok)
        tf = next(
            m for m in got["tf"] if codecs.stamp_to_ns(m.transforms[0].header.stamp) == stamp_ok
        )
        assert color.encoding == "rgb8" and depth.encoding == "32FC1"
        with RgbdRenderer(scene, width=160, height=120) as renderer:
            rgb_ref, depth_ref = renderer.render(T)
        np.testing.assert_allclose(codecs.msg_to_image(depth), depth_ref, atol=1e-5)
        # same image up to rasterisation of a pose that went through a quaternion and back
        diff = np.abs(codecs.msg_to_image(color).astype(int) - rgb_ref.astype(int))
        assert np.mean(diff) < 0.5 and np.mean(diff > 8) < 0.01
        K, width, height = codecs.camera_info_to_intrinsics(info)
        assert (width, height) == (160, 120) and np.allclose(K, renderer.K)
        assert np.allclose(codecs.pose_to_matrix(pose.pose), T, atol=1e-6)
        # world -> camera_link (dynamic) composed with camera_link -> optical (static) = goal pose
        static = got["tf_static"][-1].transforms[0]
        assert (static.header.frame_id, static.child_frame_id) == (
            "camera_link",
            "camera_optical_frame",
        )
        link = tf.transforms[0]
        assert (link.header.frame_id, link.child_frame_id) == ("world", "camera_link")
        composed = codecs.transform_to_matrix(link.transform) @ codecs.transform_to_matrix(
            static.transform
        )
        assert np.allclose(composed, T, atol=1e-6)
    finally:
        node.shutdown()
        if proc.poll() is None:
            proc.terminate()
        try:
            proc.communicate(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.communicate()
