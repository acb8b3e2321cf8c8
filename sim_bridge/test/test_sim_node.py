"""The simulated camera core and the sim_bridge node on the wire (rclpy)."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from area3d_msgs_py.depth_sensor import RgbdSensorParams, axial_sigma
from area3d_msgs_py.spinning import Spinner
from sim_bridge.camera import SimCamera, link_from_optical, right_from_left
from sim_bridge.node import READER_TOPICS
from sim_bridge.render import RgbdRenderer
from sim_bridge.scenes import load_scene

REPO_ROOT = Path(__file__).resolve().parents[2]
TIMEOUT_S = 120.0  # generous: a loaded machine is slow (every wait ends once its condition holds)


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


def test_stereo_capture_adds_the_right_image_of_a_rectified_pair():
    scene = load_scene("single_object")
    T = scene.initial_views[0]
    right_pose = right_from_left(T, 0.06)
    assert np.allclose(right_pose[:3, 3], T[:3, 3] + 0.06 * T[:3, 0])  # along optical x
    assert np.allclose(right_pose[:3, :3], T[:3, :3])  # same orientation: rectified
    mono = SimCamera(scene, width=160, height=120)
    stereo = SimCamera(scene, width=160, height=120, stereo_baseline=0.06)
    try:
        assert mono.capture(T).rgb_right is None
        cap = stereo.capture(T)
        expected, _ = stereo.renderer.render(right_pose)
        np.testing.assert_array_equal(cap.rgb_right, expected)
        assert np.mean(np.abs(cap.rgb_right.astype(int) - cap.rgb.astype(int))) > 1.0
    finally:
        mono.close()
        stereo.close()


def test_camera_link_is_x_forward_z_up_of_the_optical_frame():
    scene = load_scene("single_object")
    T = scene.initial_views[1]
    link = link_from_optical(T)
    assert np.allclose(link[:3, 0], T[:3, 2])  # link x = optical z (forward)
    assert np.allclose(link[:3, 2], -T[:3, 1])  # link z = -optical y (up)
    assert np.allclose(link[:3, 3], T[:3, 3])


def test_the_camera_delivers_depth_with_a_sensors_noise_repeatable_per_seed():
    scene = load_scene("single_object")
    T = scene.initial_views[0]
    exact = SimCamera(scene, width=160, height=120)
    noisy = [SimCamera(scene, width=160, height=120, depth_noise=True, seed=s) for s in (3, 3, 4)]
    try:
        truth = exact.capture(T).depth
        a, b, c = (cam.capture(T).depth for cam in noisy)
        assert np.array_equal(a, b, equal_nan=True)  # same seed, same noise
        assert not np.array_equal(a, c, equal_nan=True)  # another seed, other noise
        both = np.isfinite(a) & np.isfinite(truth)
        err = (a - truth)[both]
        # axial noise of the model at these ranges (a few mm), zero mean; edges and grazing
        # surfaces lose pixels (dropouts), so the noisy image has holes the exact one has not
        expected = float(np.median(axial_sigma(truth[both], 0.0, RgbdSensorParams())))
        assert 0.5 * expected < float(np.median(np.abs(err))) / 0.6745 < 3.0 * expected
        assert abs(float(np.median(err))) < 0.5 * expected
        assert (np.isfinite(truth) & ~np.isfinite(a)).sum() > 0
    finally:
        exact.close()
        for cam in noisy:
            cam.close()


def test_a_reseeded_camera_repeats_its_noise_from_the_start():
    scene = load_scene("single_object")
    T = scene.initial_views[0]
    camera = SimCamera(scene, width=160, height=120, depth_noise=True, image_noise=2.0, seed=3)
    try:
        first, second = camera.capture(T), camera.capture(T)
        assert not np.array_equal(first.depth, second.depth, equal_nan=True)  # the stream goes on
        camera.reseed()
        again = camera.capture(T)
        assert np.array_equal(again.depth, first.depth, equal_nan=True)
        assert np.array_equal(again.rgb, first.rgb)
    finally:
        camera.close()


def test_the_camera_adds_read_noise_to_each_image_of_a_stereo_pair():
    scene = load_scene("single_object")
    T = scene.initial_views[0]
    exact = SimCamera(scene, width=160, height=120, stereo_baseline=0.06)
    noisy = SimCamera(scene, width=160, height=120, stereo_baseline=0.06, image_noise=2.0)
    try:
        clean, cap = exact.capture(T), noisy.capture(T)
        for a, b in ((cap.rgb, clean.rgb), (cap.rgb_right, clean.rgb_right)):
            diff = a.astype(float) - b.astype(float)
            inside = (b > 10) & (b < 245)  # away from clipping at 0 and 255
            assert np.std(diff[inside]) == pytest.approx(2.0, rel=0.1)
            assert abs(np.mean(diff[inside])) < 0.1
        left = cap.rgb.astype(float) - clean.rgb
        right = cap.rgb_right.astype(float) - clean.rgb_right
        assert abs(np.corrcoef(left.ravel(), right.ravel())[0, 1]) < 0.05  # independent
    finally:
        exact.close()
        noisy.close()
    with pytest.raises(ValueError, match="image_noise"):
        SimCamera(scene, image_noise=-1.0)


def _start_node() -> subprocess.Popen:
    """The sim_bridge node as a process of its own, waiting for the probe below as its reader."""
    readers = [f"readers.{key}:=[sim_bridge_probe]" for key in READER_TOPICS if "right" not in key]
    args = ["scene:=single_object", "width:=160", "height:=120", "readers.all:=[sim_bridge_probe]"]
    args.append("noise_seed:=5")
    return subprocess.Popen(
        [sys.executable, "-m", "sim_bridge.node", "--ros-args"]
        + [arg for pair in (("-p", a) for a in args + readers) for arg in pair],
        env=dict(os.environ, PYTHONPATH=str(REPO_ROOT)),
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )


def _stop_node(proc: subprocess.Popen) -> str:
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
    try:
        # ends at the exit; how promptly it exits is timed in tests/test_shutdown.py
        output, _ = proc.communicate(timeout=60)
    except subprocess.TimeoutExpired:
        proc.kill()
        output, _ = proc.communicate()
    return output


def _check_frame(got: dict, stamp: int, scene, T: np.ndarray) -> None:
    """The frame published for `stamp` is the scene rendered at T, with its intrinsics and TF."""
    from area3d_msgs_py import codecs

    def of_stamp(key):
        return next(m for m in got[key] if codecs.stamp_to_ns(m.header.stamp) == stamp)

    color, depth, info, pose = (of_stamp(k) for k in ("color", "depth", "info", "pose"))
    assert color.encoding == "rgb8" and depth.encoding == "32FC1"
    assert color.header.frame_id == depth.header.frame_id == "camera_optical_frame"
    with RgbdRenderer(scene, width=160, height=120) as renderer:
        rgb_ref, depth_ref = renderer.render(T)
    # depth and colour carry the camera's noise (on by default: depth noise and 1 grey level of
    # read noise), drawn from noise_seed: the same camera core at the pose the node received
    # gives the same images (this node captured nothing before this frame)
    twin = SimCamera(scene, width=160, height=120, depth_noise=True, seed=5, image_noise=1.0)
    try:
        expected = twin.capture(codecs.pose_to_matrix(pose.pose))
    finally:
        twin.close()
    published = codecs.msg_to_image(depth)
    np.testing.assert_array_equal(published, expected.depth)
    np.testing.assert_array_equal(codecs.msg_to_image(color), expected.rgb)
    assert not np.allclose(published, depth_ref, equal_nan=True)
    # the exact rendering up to the read noise and the rasterisation of a pose that went through
    # a quaternion and back
    diff = np.abs(codecs.msg_to_image(color).astype(int) - rgb_ref.astype(int))
    assert 0.2 < np.mean(diff) < 2.0 and np.mean(diff > 8) < 0.01
    K, width, height = codecs.camera_info_to_intrinsics(info)
    assert (width, height) == (160, 120) and np.allclose(K, renderer.K)
    assert np.allclose(codecs.pose_to_matrix(pose.pose), T, atol=1e-6)
    # TF: world -> camera_link at the frame's stamp, composed with the static camera_link ->
    # camera_optical_frame, is the optical frame's pose
    tf = next(m for m in got["tf"] if codecs.stamp_to_ns(m.transforms[0].header.stamp) == stamp)
    static = got["tf_static"][-1].transforms[0]
    assert (tf.transforms[0].header.frame_id, tf.transforms[0].child_frame_id) == (
        "world",
        "camera_link",
    )
    assert (static.header.frame_id, static.child_frame_id) == (
        "camera_link",
        "camera_optical_frame",
    )
    composed = codecs.transform_to_matrix(tf.transforms[0].transform) @ codecs.transform_to_matrix(
        static.transform
    )
    assert np.allclose(composed, T, atol=1e-6)


def test_node_publishes_a_frame_per_valid_goal_and_a_status_per_goal():
    from area3d_msgs_py import codecs, msgs, qos, topics
    from area3d_msgs_py.probe import Probe

    proc = _start_node()
    probe = Probe("sim_bridge_probe")
    keys = {
        "status": topics.CAMERA_STATUS,
        "color": topics.COLOR,
        "depth": topics.DEPTH,
        "info": topics.CAMERA_INFO,
        "pose": topics.POSE,
    }
    got = {key: probe.listen(t.msg_type, t.name, t.qos()) for key, t in keys.items()}
    diagnostics = probe.listen(msgs.DiagnosticArray, "/diagnostics", qos.reliable(100))
    got["tf"] = probe.listen(msgs.TFMessage, topics.TF.name, topics.TF.qos())
    got["tf_static"] = probe.listen(msgs.TFMessage, topics.TF_STATIC.name, topics.TF_STATIC.qos())
    goal_pub = probe.publisher(topics.GOAL.msg_type, topics.GOAL.name, topics.GOAL.qos())
    scene = load_scene("single_object")
    T = scene.initial_views[2]
    stamp_ok = 1_700_000_000_000_000_123

    def statuses():
        return [json.loads(m.data) for m in got["status"]]

    def goal(stamp, pose):
        return msgs.PoseStamped(header=codecs.header(stamp, "world"), pose=pose)

    try:
        assert probe.wait_for_readers(goal_pub, 1, TIMEOUT_S), proc.poll()
        # readers.*: the frame and its status wait until our readers have matched (at most
        # readers_timeout_s); the goal is sent again until its status arrives (same stamp, same
        # frame).
        deadline = time.monotonic() + TIMEOUT_S
        while not any(s["stamp_ns"] == stamp_ok for s in statuses()):
            assert time.monotonic() < deadline, proc.poll()
            goal_pub.publish(goal(stamp_ok, codecs.matrix_to_pose(T)))
            probe.wait_for(lambda: any(s["stamp_ns"] == stamp_ok for s in statuses()), 1.0)
        assert probe.wait_for(lambda: got["pose"], TIMEOUT_S)
        assert any(s["stamp_ns"] == stamp_ok and s["ok"] for s in statuses()), proc.poll()

        # Invalid goals: a non-unit quaternion and a pose inside the object, each answered with a reason.
        bad_quat = goal(stamp_ok + 1, codecs.matrix_to_pose(T))
        bad_quat.pose.orientation.w = 3.0
        inside = T.copy()
        model, data = scene.model()
        inside[:3, 3] = data.xpos[model.body("obj0").id] + [0, 0, 0.06]
        goal_pub.publish(bad_quat)
        goal_pub.publish(goal(stamp_ok + 2, codecs.matrix_to_pose(inside)))
        probe.wait_for(
            lambda: len({s["stamp_ns"] for s in statuses()} & {stamp_ok + 1, stamp_ok + 2}) == 2,
            TIMEOUT_S,
        )
        by_stamp = {s["stamp_ns"]: s for s in statuses()}
        refused = by_stamp[stamp_ok + 1], by_stamp[stamp_ok + 2]
        assert refused[0]["ok"] is False and "orientation" in refused[0]["reason"]
        assert refused[1]["ok"] is False and "geometry" in refused[1]["reason"]
        assert proc.poll() is None  # still running after bad input
        _check_frame(got, stamp_ok, scene, T)

        # the camera's counters on /diagnostics: its captures, the refusals by reason, and a
        # warning for the malformed goal (a rejected input)
        def counters() -> dict:
            last = [s for a in list(diagnostics) for s in a.status if s.name.startswith("sim_")]
            return {kv.key: kv.value for kv in last[-1].values} if last else {}

        assert probe.wait_for(
            lambda: counters().get("goals_refused.by_reason.inside_geometry") == "1", TIMEOUT_S
        )
        facts = counters()
        # (the first goal is sent again until its status arrives: each capture has an ok status)
        captured = sum(s["ok"] for s in statuses())
        assert captured >= 1 and facts["captures"] == str(captured)
        assert facts["goals_refused.total"] == "2"
        assert facts["goals_refused.by_reason.bad_goal"] == "1"
        assert facts["rejected.by_field.orientation"] == "1"
        assert facts["readers_matched"] == "true" and facts["frames_held_for_readers"] == "0"
        assert any(
            "1 inputs rejected" in s.message
            for a in list(diagnostics)
            for s in a.status
            if s.name == "sim_bridge: status"
        )
    finally:
        probe.close()
        output = _stop_node(proc)
    assert proc.returncode == 0, output  # a quiet, prompt exit on SIGINT
    assert "Traceback" not in output


def test_the_first_frame_waits_for_its_readers_without_holding_up_the_node():
    """The goal callback never sleeps: while the first frame waits for a reader that is not
    there yet, later goals are answered; once the reader appears, the frame goes out."""
    import rclpy
    from rclpy.executors import MultiThreadedExecutor
    from rclpy.parameter import Parameter

    from area3d_msgs_py import codecs, msgs, topics
    from sim_bridge.node import SimBridgeNode

    context = rclpy.Context()
    rclpy.init(context=context)
    params = {"width": 160, "height": 120, "readers_timeout_s": 600.0}
    params |= {f"readers.{key}": ["late_reader"] for key in ("color", "depth", "pose")}
    params["readers.camera_info"] = ["late_reader"]
    node = SimBridgeNode(
        context=context, parameter_overrides=[Parameter(k, value=v) for k, v in params.items()]
    )
    feeder = rclpy.create_node("feeder", context=context)
    statuses = []
    feeder.create_subscription(
        msgs.String, topics.CAMERA_STATUS.name, statuses.append, topics.CAMERA_STATUS.qos()
    )
    goals = feeder.create_publisher(msgs.PoseStamped, topics.GOAL.name, topics.GOAL.qos())
    executor = MultiThreadedExecutor(context=context)
    for n in (node, feeder):
        executor.add_node(n)
    spinner = Spinner(executor)

    def wait_for(condition) -> bool:
        deadline = time.monotonic() + TIMEOUT_S
        while not condition() and time.monotonic() < deadline:
            time.sleep(0.01)
        return condition()

    def answered(stamp) -> list:
        return [s for s in (json.loads(m.data) for m in statuses) if s["stamp_ns"] == stamp]

    T = load_scene("single_object").initial_views[0]
    try:
        assert wait_for(
            lambda: goals.get_subscription_count() and node.pub_status.get_subscription_count()
        )
        goals.publish(
            msgs.PoseStamped(header=codecs.header(10, "world"), pose=codecs.matrix_to_pose(T))
        )
        assert wait_for(lambda: len(node.held) == 1)  # captured, held for its reader
        waiting = node._diagnostic_state()  # what /diagnostics says meanwhile
        assert waiting["frames_held_for_readers"] == 1 and not waiting["readers_matched"]
        assert waiting["readers_missing"][f"/{topics.COLOR.name}"] == ["late_reader"]
        assert waiting["captures"] == 0
        bad = msgs.PoseStamped(header=codecs.header(11, "world"), pose=codecs.matrix_to_pose(T))
        bad.pose.orientation.w = 3.0
        goals.publish(bad)
        assert wait_for(lambda: answered(11))  # the node went on meanwhile
        assert not answered(10) and len(node.held) == 1
        late = rclpy.create_node("late_reader", context=context)
        frames = []
        for topic in (topics.COLOR, topics.DEPTH, topics.CAMERA_INFO, topics.POSE):
            late.create_subscription(topic.msg_type, topic.name, frames.append, topic.qos())
        executor.add_node(late)
        assert wait_for(lambda: answered(10) and len(frames) == 4)
        assert answered(10)[0]["ok"] and not node.held
        done = node._diagnostic_state()
        assert done["captures"] == 1 and done["readers_missing"] == {}
        assert done["goals_refused"] == {"total": 1, "by_reason": {"bad_goal": 1}}
    finally:
        spinner.stop(10)
        context.try_shutdown()


def test_a_lens_distorts_the_images_sent_and_says_so_in_the_camera_info():
    """`lens_d`: the colour and depth images go out as a plumb_bob lens sends them (what
    perception's `undistort` takes out again), with the coefficients in the camera info; no
    lens with a stereo pair (coefficients below 1e-9 are none), and five finite coefficients."""
    import rclpy
    from rclpy.parameter import Parameter

    from area3d_msgs_py import codecs
    from area3d_msgs_py.errors import InputError
    from area3d_msgs_py.lens import distortion
    from sim_bridge.node import SimBridgeNode

    class Pub:
        def __init__(self):
            self.sent = []

        def publish(self, msg):
            self.sent.append(msg)

    d = [-0.2, 0.05, 0.0, 0.001, 0.0]
    base = {"scene": "single_object", "width": 160, "height": 120}
    context = rclpy.Context()
    rclpy.init(context=context)
    try:

        def node(**p):
            overrides = [Parameter(k, value=v) for k, v in {**base, **p}.items()]
            return SimBridgeNode(context=context, parameter_overrides=overrides)

        sim = node(lens_d=d)
        for name in ("pub_color", "pub_depth", "pub_info"):
            setattr(sim, name, Pub())
        T = sim.scene.initial_views[0]
        capture = sim.camera.capture(T)
        sim._send(1_000, capture)
        (info,) = sim.pub_info.sent
        assert list(info.d) == d and info.distortion_model == "plumb_bob"
        lens = distortion(sim.camera.K, 160, 120, d)
        rgb = codecs.msg_to_image(sim.pub_color.sent[0])
        depth = codecs.msg_to_image(sim.pub_depth.sent[0])
        np.testing.assert_array_equal(rgb, lens.color(capture.rgb))
        np.testing.assert_array_equal(depth, lens.depth(capture.depth))
        assert not np.array_equal(rgb, capture.rgb)
        sim.camera.close()
        sim.destroy_node()
        with pytest.raises(InputError, match="lens_d.*with stereo"):
            node(lens_d=d, stereo=True)
        # coefficients a driver publishes for none are no lens, with a pair too
        pair = node(lens_d=[1e-12, 0.0, 0.0, -1e-12, 0.0], stereo=True)
        assert pair.lens is None
        pair.pub_info = Pub()
        pair._send(2_000, pair.camera.capture(T))
        assert not any(pair.pub_info.sent[0].d)
        pair.camera.close()
        pair.destroy_node()
        with pytest.raises(InputError, match="5 finite coefficients"):
            node(lens_d=[0.1, 0.2])
    finally:
        context.try_shutdown()
