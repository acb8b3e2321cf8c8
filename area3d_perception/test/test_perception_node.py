"""The perception node in-process: pairing, publishing, bad input and a failing backend in its
status, callbacks called directly."""

import numpy as np
import pytest
import rclpy
from rclpy.parameter import Parameter

from area3d_msgs_py import codecs, msgs
from area3d_msgs_py.diagnostics import ERROR, OK, WARN, assess
from area3d_msgs_py.guard import guarded
from area3d_msgs_py.topics import (
    CAMERA_INFO,
    COLOR,
    DEPTH,
    PERCEPTION_CONFIDENCE,
    PERCEPTION_DEPTH,
    PERCEPTION_WEIGHT,
    POSE,
    RIGHT_CAMERA_INFO,
    RIGHT_IMAGE,
)
from area3d_perception.estimator import FrameEstimator
from area3d_perception.feedforward import FeedForwardOutput
from area3d_perception.node import MAX_FRAMES_WITHOUT_INFO, PerceptionNode
from area3d_perception.stereo import StereoMatcher, StereoParams

COLOR_TOPIC, DEPTH_TOPIC, INFO_TOPIC, POSE_TOPIC = (
    COLOR.name,
    DEPTH.name,
    CAMERA_INFO.name,
    POSE.name,
)
RIGHT_TOPIC, RIGHT_INFO_TOPIC = RIGHT_IMAGE.name, RIGHT_CAMERA_INFO.name
OUT_DEPTH_TOPIC, OUT_CONFIDENCE_TOPIC = PERCEPTION_DEPTH.name, PERCEPTION_CONFIDENCE.name
OUT_WEIGHT_TOPIC = PERCEPTION_WEIGHT.name

H, W = 48, 64
K = np.array([[W / 2, 0, W / 2], [0, W / 2, H / 2], [0, 0, 1.0]])
S = 1_000_000_000
FRAME = "camera_optical_frame"


class Log:
    def __init__(self):
        self.lines = []

    def info(self, m):
        self.lines.append(("info", m))

    def warning(self, m, **throttle):
        self.lines.append(("warning", m))

    def error(self, m):
        self.lines.append(("error", m))

    def warnings(self):
        return [m for level, m in self.lines if level == "warning"]


UNIT_NAMESPACE = "/perception_unit_tests"


class Pub:
    def __init__(self):
        self.sent = []

    def publish(self, msg):
        self.sent.append(msg)


@pytest.fixture(scope="module", autouse=True)
def ros_context():
    # the nodes here are real participants on the worker's domain, never spun: in a namespace of
    # their own, no test that looks for a running graph's `perception` finds them
    context = rclpy.Context()
    rclpy.init(context=context, args=["--ros-args", "-r", f"__ns:={UNIT_NAMESPACE}"])
    pytest.perception_context = context
    yield context
    context.try_shutdown()


@pytest.fixture(autouse=True)
def destroy_fake_nodes():
    """Each test's FakeNodes are destroyed when it ends."""
    yield
    while FakeNode.made:
        FakeNode.made.pop().destroy_node()


class InlineWorker:
    """The node's FrameWorker, run in the caller's thread: a frame's outputs are published when
    its last part's callback returns (the real worker's order and backlog have their own tests,
    area3d_msgs_py/test/test_msgs_scheduling.py)."""

    def __init__(self, worker):
        self._process, self._on_done = worker._process, worker._on_done
        self.backlog, self.waiting, self.dropped = worker.backlog, 0, 0
        self.alive, self.stopping = True, False
        worker.stop(1.0)

    def submit(self, stamp, frame, K):
        self._on_done(stamp, self._process(stamp, frame, K), True)
        return True

    def stop(self, timeout_s):
        self.stopping = True


# every frame is a keyframe unless a test says otherwise (the sim camera's setting)
EVERY_FRAME = {"keyframe_distance": 0.0, "keyframe_angle_deg": 0.0, "keyframe_interval_s": 0.0}
# the tests stamp frames seconds after the epoch, decades behind the node's clock: no lag check
# unless a test asks for one
NO_LAG_CHECK = {"max_stamp_lag_s": 0.0}


class FakeNode:
    """A real PerceptionNode whose outputs and log are captured and whose callbacks are called
    directly (no transport): `subs[topic](msg)`, `pubs[topic].sent`, `log.warnings()`."""

    made: list = []  # the nodes of the test running

    def __init__(self, parameters=None):
        parameters = {**EVERY_FRAME, **NO_LAG_CHECK, **(parameters or {})}
        overrides = [Parameter(k, value=v) for k, v in parameters.items()]
        self.node = PerceptionNode(context=pytest.perception_context, parameter_overrides=overrides)
        FakeNode.made.append(self.node)
        self.node.worker = InlineWorker(self.node.worker)
        self.log = Log()
        self.node.get_logger = lambda: self.log
        self.pubs = {OUT_DEPTH_TOPIC: Pub(), OUT_CONFIDENCE_TOPIC: Pub(), OUT_WEIGHT_TOPIC: Pub()}
        self.node.pub_depth = self.pubs[OUT_DEPTH_TOPIC]
        self.node.pub_conf = self.pubs[OUT_CONFIDENCE_TOPIC]
        self.node.pub_weight = self.pubs[OUT_WEIGHT_TOPIC]
        self.subs = {
            COLOR_TOPIC: guarded(self.node, self.node.on_color, COLOR_TOPIC),
            DEPTH_TOPIC: guarded(self.node, self.node.on_depth, DEPTH_TOPIC),
            INFO_TOPIC: guarded(self.node, self.node.on_camera_info, INFO_TOPIC),
            POSE_TOPIC: guarded(self.node, self.node.on_pose, POSE_TOPIC),
            RIGHT_TOPIC: guarded(self.node, self.node.on_right, RIGHT_TOPIC),
            RIGHT_INFO_TOPIC: guarded(self.node, self.node.on_right_camera_info, RIGHT_INFO_TOPIC),
        }


def send_frame(
    node,
    stamp,
    depth=None,
    rgb=None,
    info=True,
    order=("color", "depth", "pose"),
    x=0.0,
    stamps=None,
):
    """One frame's parts; `x` moves the camera along x, `stamps` ({key: stamp}) stamps parts
    apart."""
    depth = np.full((H, W), 2.0, np.float32) if depth is None else depth
    rgb = np.zeros((H, W, 3), np.uint8) if rgb is None else rgb
    if info:
        node.subs[INFO_TOPIC](codecs.intrinsics_to_camera_info(K, W, H, stamp, FRAME))
    T = np.eye(4)
    T[:3, 3] = [x, 0.0, 1.0]
    at = {"color": stamp, "depth": stamp, "pose": stamp, **(stamps or {})}
    pose = msgs.PoseStamped(
        header=codecs.header(at["pose"], "world"), pose=codecs.matrix_to_pose(T)
    )
    parts = {
        "color": (COLOR_TOPIC, codecs.image_to_msg(rgb, "rgb8", at["color"], FRAME)),
        "depth": (DEPTH_TOPIC, codecs.image_to_msg(depth, "32FC1", at["depth"], FRAME)),
        "pose": (POSE_TOPIC, pose),
    }
    for key in order:
        topic, msg = parts[key]
        node.subs[topic](msg)


def test_a_complete_frame_is_published_with_its_stamp_and_frame():
    node = FakeNode()
    send_frame(node, 5 * S, order=("pose", "depth", "color"))
    (depth_msg,) = node.pubs[OUT_DEPTH_TOPIC].sent
    (conf_msg,) = node.pubs[OUT_CONFIDENCE_TOPIC].sent
    for msg in (depth_msg, conf_msg):
        assert codecs.stamp_to_ns(msg.header.stamp) == 5 * S
        assert msg.header.frame_id == FRAME and msg.encoding == "32FC1"
    np.testing.assert_array_equal(codecs.msg_to_image(depth_msg), np.full((H, W), 2.0, np.float32))
    conf = codecs.msg_to_image(conf_msg)
    assert np.all((conf > 0) & (conf <= 1))


def test_a_streaming_camera_integrates_keyframes_only_and_counts_the_rest_as_skipped():
    """30 Hz from a camera at rest, then moving: a frame is integrated when the camera moved
    keyframe_distance or a keyframe_interval_s passed since the last one; the rest are skipped,
    counted, and never reach the backend."""
    node = FakeNode(
        {"keyframe_distance": 0.1, "keyframe_angle_deg": 10.0, "keyframe_interval_s": 1.0}
    )
    period = S // 30
    for i in range(45):  # 1.5 s at rest: the first frame, and the one a second later
        send_frame(node, S + i * period)
    stamps = [codecs.stamp_to_ns(m.header.stamp) for m in node.pubs[OUT_DEPTH_TOPIC].sent]
    assert stamps == [S, S + 31 * period]  # the first frame a second (or more) later
    # moving 4 cm a frame: the first frame more than a second after the last keyframe, then the
    # one 12 cm (>= 10 cm) from it
    for i in range(1, 6):
        send_frame(node, 3 * S + i * period, x=0.04 * i)
    stamps = [codecs.stamp_to_ns(m.header.stamp) for m in node.pubs[OUT_DEPTH_TOPIC].sent]
    assert stamps[2:] == [3 * S + period, 3 * S + 4 * period]
    status = node.node._status()
    assert status["frames_integrated"] == 4 and status["frames_skipped"] == 46
    assert status["frames_published"] == 4 and status["frames_paired"] == 50


def test_parts_stamped_apart_pair_within_the_slop_and_go_out_with_the_colour_stamp():
    node = FakeNode({"sync_slop_s": 0.01})
    send_frame(node, 5 * S, stamps={"depth": 5 * S + 3_000_000, "pose": 5 * S - 2_000_000})
    (depth_msg,) = node.pubs[OUT_DEPTH_TOPIC].sent
    assert codecs.stamp_to_ns(depth_msg.header.stamp) == 5 * S
    exact = FakeNode()
    send_frame(exact, 5 * S, stamps={"depth": 5 * S + 3_000_000})
    assert exact.pubs[OUT_DEPTH_TOPIC].sent == []


def test_a_pairing_rate_below_the_threshold_is_a_standing_warning_on_diagnostics():
    """A third of the depth images lost: the colour frames that lose theirs are dropped at the
    age limit; the rate (about 2/3) falls below min_pairing_rate and /diagnostics warns."""
    node = FakeNode({"sync_max_age_s": 0.5, "min_pairing_rate": 0.8})
    period = S // 30
    for i in range(60):
        keys = ("color", "pose") if i % 3 == 0 else ("color", "depth", "pose")
        send_frame(node, S + i * period, order=keys)
    status = node.node._status()
    assert status["frames_paired"] == 40
    assert 0.55 < status["pairing_rate"] < 0.75
    (warning,) = status["warnings"]
    assert "pairing rate" in warning and "min_pairing_rate 0.8" in warning
    result = assess(status, status)
    assert result.level == WARN and "pairing rate" in result.message


def test_frames_pairing_long_after_their_stamps_warn_until_one_pairs_in_time():
    """A camera host whose clock runs 20 s behind: its frames are used, and /diagnostics says
    WARN naming the lag until a frame pairs within max_stamp_lag_s again."""
    node = FakeNode({"max_stamp_lag_s": 5.0})
    now = node.node.get_clock().now().nanoseconds
    send_frame(node, now - 20 * S)
    status = node.node._status()
    assert status["frames_published"] == 1  # used all the same
    assert 19.0 < status["arrival_lag_s"] < 60.0
    (warning,) = status["warnings"]
    assert "after its stamp (max_stamp_lag_s 5)" in warning and "clock" in warning
    assert assess(status, status).level == WARN
    send_frame(node, node.node.get_clock().now().nanoseconds, x=0.5)
    status = node.node._status()
    assert status["warnings"] == [] and status["arrival_lag_s"] < 5.0
    assert assess(status, status).level == OK
    off = FakeNode({"max_stamp_lag_s": 0.0})  # 0: no check
    send_frame(off, now - 20 * S)
    assert off.node._status()["warnings"] == []


def test_uniform_backend_parameter_is_honoured():
    node = FakeNode({"backend": "uniform"})
    send_frame(node, 1 * S)
    assert np.all(codecs.msg_to_image(node.pubs[OUT_CONFIDENCE_TOPIC].sent[0]) == 1.0)


def test_sensor_parameters_reach_the_model():
    near, far = FakeNode(), FakeNode({"sensor.sigma_ref": 0.005})
    send_frame(near, 1 * S)
    send_frame(far, 1 * S)
    a = codecs.msg_to_image(near.pubs[OUT_CONFIDENCE_TOPIC].sent[0])
    b = codecs.msg_to_image(far.pubs[OUT_CONFIDENCE_TOPIC].sent[0])
    assert np.all(b[10:-10, 10:-10] < a[10:-10, 10:-10])


def test_frames_wait_for_camera_info():
    node = FakeNode()
    send_frame(node, 1 * S, info=False)
    assert node.pubs[OUT_DEPTH_TOPIC].sent == []
    assert any("camera_info" in w for w in node.log.warnings())
    node.subs[INFO_TOPIC](codecs.intrinsics_to_camera_info(K, W, H, 1 * S, FRAME))
    assert len(node.pubs[OUT_DEPTH_TOPIC].sent) == 1


def test_stamps_that_go_back_are_a_warning_until_the_stream_is_past_its_newest_again():
    """A driver restarted with its clock 2 s behind: its frames were fused with the poses of
    another time and nothing said so (a walkthrough's mesh grew ghost surfaces 4 cm off). They
    are still used, and /diagnostics warns while the stream is behind its newest frame."""
    node = FakeNode()
    for i, t in enumerate((10.0, 10.5, 8.0, 8.5)):
        send_frame(node, int(t * S), x=0.1 * i)
    status = node.node._status()
    assert status["frames_published"] == 4 and status["stamp_jumps_back"] == 1
    (warning,) = status["warnings"]
    assert "stamps went back 2.5 s" in warning
    assert assess(status, status).level == WARN
    assert any("stamps went back" in w for w in node.log.warnings())
    send_frame(node, int(10.6 * S), x=0.5)  # past the newest again
    status = node.node._status()
    assert status["warnings"] == [] and status["stamp_jumps_back"] == 1
    send_frame(node, int(10.2 * S), x=0.6)  # out of order by less than a second: not a jump
    assert node.node._status()["stamp_jumps_back"] == 1
    # a frozen clock: every frame with the newest's stamp (the map stopped growing, unsaid)
    send_frame(node, int(10.6 * S), x=0.7)
    status = node.node._status()
    assert status["stamps_repeated"] == 1 and "stamp of the one before" in status["warnings"][0]
    send_frame(node, int(10.7 * S), x=0.8)
    assert node.node._status()["warnings"] == []


def test_without_undistortion_lens_distortion_is_a_standing_warning_and_binning_is_refused():
    """With `undistort` off, a camera info with distortion (plumb_bob with d non-zero, a fisheye
    model) is read as an undistorted pinhole camera (surfaces 1-4 cm off near the image's edges
    in a walkthrough): /diagnostics warns, naming the model and d, until an undistorted one
    comes. Binning or a region of interest describe another image than the one sent: refused by
    field."""
    node = FakeNode({"undistort": False})
    info = codecs.intrinsics_to_camera_info(K, W, H, 1 * S, FRAME)
    info.d = [0.1, -0.2, 0.001, 0.001, 0.05]
    node.subs[INFO_TOPIC](info)
    send_frame(node, 1 * S, info=False)
    assert len(node.pubs[OUT_DEPTH_TOPIC].sent) == 1  # still used
    status = node.node._status()
    (warning,) = status["warnings"]
    assert "distortion_model 'plumb_bob' with d [0.1, -0.2" in warning and "rectified" in warning
    assert assess(status, status).level == WARN
    fisheye = codecs.intrinsics_to_camera_info(K, W, H, 2 * S, FRAME)
    fisheye.distortion_model = "equidistant"
    node.subs[INFO_TOPIC](fisheye)
    assert "'equidistant'" in node.node._status()["warnings"][0]
    node.subs[INFO_TOPIC](codecs.intrinsics_to_camera_info(K, W, H, 3 * S, FRAME))
    assert node.node._status()["warnings"] == []
    assert node.node._status()["undistorted"] == {}
    binned = codecs.intrinsics_to_camera_info(K, W, H, 4 * S, FRAME)
    binned.binning_x = 2
    node.subs[INFO_TOPIC](binned)
    cropped = codecs.intrinsics_to_camera_info(K, W, H, 5 * S, FRAME)
    cropped.roi.width, cropped.roi.height = W // 2, H // 2
    node.subs[INFO_TOPIC](cropped)
    warnings = node.log.warnings()
    assert any("binning_x: got 2, expected 0 or 1" in w for w in warnings), warnings
    assert any("roi: got '32x24+0+0', expected all 0" in w for w in warnings), warnings


def test_mismatched_color_and_depth_sizes_reject_the_frame_with_a_reason():
    node = FakeNode()
    send_frame(node, 1 * S, rgb=np.zeros((H, W + 2, 3), np.uint8))
    assert node.pubs[OUT_DEPTH_TOPIC].sent == []
    assert any("rejected" in w and "color" in w for w in node.log.warnings())
    send_frame(node, 2 * S)  # the node keeps working
    assert len(node.pubs[OUT_DEPTH_TOPIC].sent) == 1


def test_rep_117_depth_passes_and_bad_depth_is_logged_and_treated_as_missing():
    node = FakeNode()
    depth = np.full((H, W), 2.0, np.float32)
    depth[0, :4] = np.inf  # no return within range (REP 117): published as such
    depth[1, :3] = -0.5
    depth[2, :2] = -np.inf  # too near (REP 117): no estimate
    send_frame(node, 1 * S, depth=depth)
    out = codecs.msg_to_image(node.pubs[OUT_DEPTH_TOPIC].sent[0])
    conf = codecs.msg_to_image(node.pubs[OUT_CONFIDENCE_TOPIC].sent[0])
    assert np.isposinf(out[0, :4]).all()
    assert np.isnan(out[1, :3]).all() and np.isnan(out[2, :2]).all()
    assert np.all(conf[:3, :4][~np.isfinite(out[:3, :4])] == 0)
    warnings = node.log.warnings()
    assert any("depth: 3 values <= 0" in w for w in warnings)
    assert not any("-inf" in w for w in warnings)  # REP 117's too near is not bad input


def test_a_pose_without_images_is_dropped_after_the_age_limit():
    node = FakeNode({"sync_max_age_s": 2.0})
    pose = msgs.PoseStamped(
        header=codecs.header(1 * S, "world"), pose=codecs.matrix_to_pose(np.eye(4))
    )
    node.subs[POSE_TOPIC](pose)
    send_frame(node, 5 * S)
    assert any("pose at stamp 1000000000 dropped" in w for w in node.log.warnings())
    assert len(node.pubs[OUT_DEPTH_TOPIC].sent) == 1


def test_a_pose_with_a_non_unit_quaternion_is_rejected_not_fatal():
    node = FakeNode()
    bad = codecs.matrix_to_pose(np.eye(4))
    bad.orientation.w = 3.0
    node.subs[POSE_TOPIC](msgs.PoseStamped(header=codecs.header(1 * S, "world"), pose=bad))
    assert any("pose at stamp" in w and "rejected" in w for w in node.log.warnings())


def test_a_missing_vggt_checkpoint_fails_at_start_naming_it():
    with pytest.raises(RuntimeError, match="nowhere/model.pt"):
        FakeNode({"backend": "vggt", "checkpoint": "/nowhere/model.pt"})


def test_a_backend_outside_the_choices_is_refused_at_start_naming_it():
    with pytest.raises(ValueError, match="backend: got 'nope', expected one of rgbd"):
        FakeNode({"backend": "nope"})


# -- stereo backend ----------------------------------------------------------------------------
STEREO = {
    "backend": "stereo",
    "stereo.num_disparities": 16,
    "stereo.speckle_window_size": 0,
    "stereo.downscale": 1,
}
SHIFT_PX, BASELINE = 8, 0.2  # every pixel 8 px apart: depth fx B / d = 32 * 0.2 / 8 = 0.8 m


def stereo_pair(shift=SHIFT_PX):
    grey = np.random.default_rng(0).integers(0, 256, (H, W)).astype(np.uint8)
    left = np.repeat(grey[..., None], 3, axis=2)
    return left, np.roll(left, -shift, axis=1)


def send_right(node, stamp, right, info=True, baseline=BASELINE, size=(W, H), encoding="rgb8"):
    if info:
        node.subs[RIGHT_INFO_TOPIC](
            codecs.intrinsics_to_camera_info(K, *size, stamp, FRAME, baseline=baseline)
        )
    node.subs[RIGHT_TOPIC](codecs.image_to_msg(right, encoding, stamp, FRAME))


def test_stereo_backend_matches_the_right_image_paired_by_stamp():
    node = FakeNode(STEREO)
    left, right = stereo_pair()
    send_right(node, 2 * S, right)
    send_frame(node, 1 * S, rgb=left)  # no right image with this stamp: waits
    assert node.pubs[OUT_DEPTH_TOPIC].sent == []
    send_frame(node, 2 * S, rgb=left, depth=np.full((H, W), 5.0, np.float32))
    (depth_msg,) = node.pubs[OUT_DEPTH_TOPIC].sent
    assert codecs.stamp_to_ns(depth_msg.header.stamp) == 2 * S
    depth = codecs.msg_to_image(depth_msg)[4:-4, 24:-4]  # the sensor's 5 m is not used
    assert np.nanmedian(np.abs(depth - 0.8)) < 0.01
    # the planner's confidence is the calibrated model's, the reconstruction's weight the
    # matcher's, each exactly what the matcher gives for this pair
    conf, weight = (
        codecs.msg_to_image(node.pubs[topic].sent[0])
        for topic in (OUT_CONFIDENCE_TOPIC, OUT_WEIGHT_TOPIC)
    )
    params = {k.removeprefix("stereo."): v for k, v in STEREO.items() if k.startswith("stereo.")}
    for model, published in (("calibrated", conf), ("matcher", weight)):
        m = StereoMatcher(StereoParams(**params, confidence_model=model))
        try:
            expected = m.match(left, right, float(K[0, 0]), BASELINE).confidence
        finally:
            m.close()
        np.testing.assert_array_equal(published, expected)
    assert np.median(weight[4:-4, 24:-4]) > 0.5 and np.median(conf[4:-4, 24:-4]) > 0.1


def test_stereo_frames_wait_for_the_right_camera_info():
    node = FakeNode(STEREO)
    left, right = stereo_pair()
    send_right(node, 1 * S, right, info=False)
    send_frame(node, 1 * S, rgb=left)
    assert node.pubs[OUT_DEPTH_TOPIC].sent == []
    assert any(RIGHT_INFO_TOPIC in w for w in node.log.warnings())
    node.subs[RIGHT_INFO_TOPIC](
        codecs.intrinsics_to_camera_info(K, W, H, 1 * S, FRAME, baseline=BASELINE)
    )
    assert len(node.pubs[OUT_DEPTH_TOPIC].sent) == 1


def test_a_frame_whose_right_image_never_comes_is_dropped_naming_it():
    node = FakeNode({**STEREO, "sync_max_age_s": 2.0})
    left, right = stereo_pair()
    send_frame(node, 1 * S, rgb=left)
    send_right(node, 5 * S, right)
    send_frame(node, 5 * S, rgb=left)
    assert any("at stamp 1000000000 dropped: no matching right" in w for w in node.log.warnings())
    assert len(node.pubs[OUT_DEPTH_TOPIC].sent) == 1


@pytest.mark.parametrize(
    ("right_kwargs", "expected"),
    [
        ({"right": np.zeros((H, W + 8, 3), np.uint8)}, "right: got 'size 72x48'"),
        ({"right": np.zeros((H, W), np.float32), "encoding": "32FC1"}, "right: got 'float32"),
        ({"size": (W + 8, H)}, "right camera_info: got 'size 72x48'"),
        ({"baseline": 0.0}, "right/camera_info at stamp 1000000000: rejected: p[3]"),
    ],
    ids=["image size", "encoding", "camera_info size", "no Tx"],
)
def test_bad_stereo_input_is_refused_with_a_reason_and_the_node_goes_on(right_kwargs, expected):
    node = FakeNode(STEREO)
    left, right = stereo_pair()
    kwargs = {"right": right, **right_kwargs}
    send_right(node, 1 * S, kwargs.pop("right"), **kwargs)
    send_frame(node, 1 * S, rgb=left)
    assert node.pubs[OUT_DEPTH_TOPIC].sent == []
    assert any(expected in w for w in node.log.warnings()), node.log.warnings()
    send_right(node, 2 * S, right)
    send_frame(node, 2 * S, rgb=left)  # a good pair afterwards is processed
    stamps = [codecs.stamp_to_ns(m.header.stamp) for m in node.pubs[OUT_DEPTH_TOPIC].sent]
    assert 2 * S in stamps


class FailingModel:
    """A feed-forward model that raises at its first call (a GPU out of memory), then predicts a
    constant depth of 2 model units with confidence 3."""

    def __init__(self):
        self.calls = 0

    def predict_views(self, images):
        self.calls += 1
        if self.calls == 1:
            raise RuntimeError("CUDA out of memory")
        n = len(images)
        return FeedForwardOutput(
            [np.full((H, W), 2.0, np.float32)] * n, [np.full((H, W), 3.0, np.float32)] * n, None
        )


def test_a_backend_that_fails_is_an_error_in_the_status_until_a_frame_succeeds():
    node = FakeNode()
    model = FailingModel()
    node.node.estimator = FrameEstimator("vggt", model_factory=lambda checkpoint, device: model)
    before = node.node._status()
    assert assess(before, before).level == OK and before["backend_error"] is None
    send_frame(node, 1 * S)
    failed = node.node._status()
    assert node.pubs[OUT_DEPTH_TOPIC].sent == []  # the frame is dropped ...
    assert failed["frames_dropped_backend_failure"] == 1  # ... counted ...
    assert any("vggt backend failed" in m for level, m in node.log.lines if level == "error")
    result = assess(failed, before)  # ... and the node's level is ERROR, naming the failure
    assert result.level == ERROR and "backend failed: RuntimeError: CUDA out of memory" in (
        result.message
    )
    send_frame(node, 2 * S)  # the next frame succeeds: no failed backend any more
    assert len(node.pubs[OUT_DEPTH_TOPIC].sent) == 1
    recovered = node.node._status()
    assert recovered["backend_error"] is None
    assert assess(recovered, before).level == WARN  # the dropped frame, within its period
    assert assess(recovered, failed).level == OK  # and OK once that period has passed


def test_frames_beyond_the_wait_for_camera_info_are_counted_as_dropped():
    node = FakeNode()
    for k in range(MAX_FRAMES_WITHOUT_INFO + 2):
        send_frame(node, (k + 1) * S, info=False)
    status = node.node._status()
    assert status["frames_waiting_for_camera_info"] == MAX_FRAMES_WITHOUT_INFO
    assert status["frames_dropped_without_camera_info"] == 2


def tf_message(*edges):
    """tf2_msgs/TFMessage of (parent, child, stamp_ns, 4x4) edges."""
    from area3d_msgs_py.transforms import StampedTransform

    return codecs.transforms_to_tf_message([StampedTransform(*e) for e in edges])


def test_with_pose_source_tf_a_frame_takes_its_pose_from_tf_at_its_stamp():
    """world -> camera_link interpolated to the image's stamp, composed with the latched
    camera_link -> optical frame; a frame whose TF has not arrived waits for it, and one whose
    TF never comes is dropped after pose_wait_s, counted by cause and logged once."""
    node = FakeNode({"pose_source": "tf", "pose_wait_s": 0.0})
    assert POSE_TOPIC not in node.node.sync.keys and node.node.poses is not None
    optical = np.eye(4)
    optical[:3, :3] = [[0, 0, 1], [-1, 0, 0], [0, -1, 0]]
    a, b = np.eye(4), np.eye(4)
    a[:3, 3], b[:3, 3] = [0.0, 0.0, 1.0], [0.2, 0.0, 1.0]
    node.node.poses._on_tf(tf_message(("camera_link", FRAME, 0, optical)), static=True)
    node.node.poses._on_tf(tf_message(("world", "camera_link", 5 * S, a)), static=False)
    send_frame(node, 5 * S + S // 4, order=("color", "depth"))  # 1/4 of the way to the next
    assert node.pubs[OUT_DEPTH_TOPIC].sent == []  # waits for the transform after its stamp
    node.node.poses._on_tf(tf_message(("world", "camera_link", 6 * S, b)), static=False)
    (depth_msg,) = node.pubs[OUT_DEPTH_TOPIC].sent
    assert codecs.stamp_to_ns(depth_msg.header.stamp) == 5 * S + S // 4
    status = node.node._status()
    assert status["frames_published"] == 1 and status["frames_dropped_no_pose"] == {}
    # a frame after the newest transform that never comes: dropped (pose_wait_s 0) and counted
    send_frame(node, 7 * S, order=("color", "depth"))
    send_frame(node, 8 * S, order=("color", "depth"))
    node.node.poses.release()
    status = node.node._status()
    assert status["frames_published"] == 1
    assert status["frames_dropped_no_pose"] == {"in_future": 2}
    logged = [w for w in node.log.warnings() if "no camera pose" in w]
    assert len(logged) == 1 and "in_future" in logged[0] and "not arrived yet" in logged[0]


def test_with_pose_source_tf_the_pose_is_the_interpolated_transform(monkeypatch):
    node = FakeNode({"pose_source": "tf"})
    given = []
    process = node.node.estimator.process
    monkeypatch.setattr(
        node.node.estimator,
        "process",
        lambda rgb, depth, K_, T, **kw: given.append(T) or process(rgb, depth, K_, T, **kw),
    )
    a, b = np.eye(4), np.eye(4)
    a[:3, 3], b[:3, 3] = [0.0, 0.0, 1.0], [0.2, 0.0, 1.0]
    node.node.poses._on_tf(
        tf_message(("world", FRAME, 5 * S, a), ("world", FRAME, 6 * S, b)), False
    )
    send_frame(node, 5 * S + S // 4, order=("color", "depth"))
    (T,) = given
    np.testing.assert_allclose(T[:3, 3], [0.05, 0.0, 1.0], atol=1e-12)


def test_a_bad_transform_is_refused_by_index_and_field_and_its_neighbours_are_kept():
    node = FakeNode({"pose_source": "tf"})
    bad = np.eye(4)
    good = np.eye(4)
    message = tf_message(("world", FRAME, 5 * S, good), ("world", "other", 5 * S, bad))
    message.transforms[1].transform.rotation.w = 2.0  # norm 2
    node.node.poses._on_tf(message, static=False)
    (warning,) = node.log.warnings()
    assert "/tf at stamp" in warning and "transforms[1].transform.rotation: got" in warning
    assert node.node.rejections.snapshot()["by_field"] == {"transforms[1].transform.rotation": 1}
    send_frame(node, 5 * S, order=("color", "depth"))
    assert len(node.pubs[OUT_DEPTH_TOPIC].sent) == 1  # the good transform of that message held


def test_a_torch_device_name_is_checked_before_a_backend_is_made():
    from area3d_msgs_py.errors import InputError
    from area3d_msgs_py.parameters import parameter_values
    from area3d_perception.node import PARAMS

    for device in ("auto", "cpu", "cuda", "cuda:1"):
        assert parameter_values(PARAMS, {"device": device})["device"] == device
    with pytest.raises(InputError, match="device: got 'tpu', expected auto, cpu, cuda or cuda:N"):
        parameter_values(PARAMS, {"device": "tpu"})


def test_a_distorted_cameras_frames_are_undistorted_into_k_and_said_so():
    """`undistort` (the default): a frame of a camera whose camera info has plumb_bob distortion
    is published as the pinhole camera k sees it, depth from the nearest raw pixel; no warning,
    and the status names the model. A model it cannot undistort stays a standing warning."""
    from area3d_msgs_py.lens import undistortion

    d = [-0.3, 0.1, 0.001, -0.002, 0.0]  # a wide-angle lens's barrel
    # a slanted plane, 1 cm deeper each pixel right or down, and a step of 1 m
    v, u = np.mgrid[0:H, 0:W]
    truth = (1.0 + 0.01 * (u + v) + (u >= W // 2 + 3)).astype(np.float32)
    # the raw image the camera sends: at each raw pixel, the pinhole image where its ray lands
    import cv2

    K_cv = K.copy()
    K_cv[:2, 2] -= 0.5
    raw_px = np.stack(np.meshgrid(np.arange(W), np.arange(H)), -1).reshape(-1, 1, 2)
    pinhole_px = cv2.undistortPoints(raw_px.astype(np.float64), K_cv, np.array(d), P=K_cv)
    map_x, map_y = pinhole_px.reshape(H, W, 2).transpose(2, 0, 1).astype(np.float32)
    raw = cv2.remap(truth, map_x, map_y, cv2.INTER_NEAREST, borderValue=float("nan"))

    node = FakeNode()
    info = codecs.intrinsics_to_camera_info(K, W, H, 1 * S, FRAME)
    info.d = d
    node.subs[INFO_TOPIC](info)
    send_frame(node, 1 * S, depth=raw, info=False)
    (depth_msg,) = node.pubs[OUT_DEPTH_TOPIC].sent
    published = codecs.msg_to_image(depth_msg)
    expected = undistortion(K, W, H, "plumb_bob", d)[0].depth(raw)
    np.testing.assert_array_equal(published, expected)
    # every depth is one the camera sent (none mixes the two sides of the step) ...
    assert np.isin(published[np.isfinite(published)], raw).all()
    # ... and, away from the step and the edges, k's own within the nearest pixel's 1-2 cm,
    # where the raw image was up to 7 pixels off
    inner = np.zeros((H, W), bool)
    inner[4:-4, 4:-4] = True
    inner[:, W // 2 - 3 : W // 2 + 9] = False
    assert np.mean(np.abs(published - truth)[inner] <= 0.0201) > 0.99
    assert np.mean(np.abs(raw - truth)[inner] > 0.0201) > 0.3
    status = node.node._status()
    assert status["warnings"] == [] and status["undistorted"] == {"left": "plumb_bob"}
    assert any("images undistorted into k" in m for level, m in node.log.lines)
    odd = codecs.intrinsics_to_camera_info(K, W, H, 2 * S, FRAME)
    odd.distortion_model, odd.d = "kannala_brandt_8", [0.1, 0.0]
    node.subs[INFO_TOPIC](odd)
    (warning,) = node.node._status()["warnings"]
    assert "'kannala_brandt_8'" in warning and "not one the graph can undistort" in warning
    assert node.node._status()["undistorted"] == {}


def test_where_an_undistorted_pixel_has_no_raw_pixel_nothing_is_estimated_or_carved():
    """A pincushion lens: the corners of the pinhole image k have no raw pixel. Without depth
    there, the rgbd backend would declare them beyond the camera's range (`no_return: all`), and
    the planner would carve free space where nothing was measured: they are no estimate."""
    from area3d_msgs_py.lens import undistortion

    d = [0.05, 0.0, 0.0, 0.0, 0.0]
    outside = undistortion(K, W, H, "plumb_bob", d)[0].outside
    assert 0 < outside.sum() < 0.2 * outside.size and outside[0, 0] and not outside[H // 2, W // 2]
    node = FakeNode({"no_return": "all"})
    info = codecs.intrinsics_to_camera_info(K, W, H, 1 * S, FRAME)
    info.d = d
    node.subs[INFO_TOPIC](info)
    depth = np.full((H, W), 2.0, np.float32)
    depth[H // 2, : W // 4] = np.nan  # a dropout inside the image: no return, as the rule says
    send_frame(node, 1 * S, depth=depth, info=False)
    published = codecs.msg_to_image(node.pubs[OUT_DEPTH_TOPIC].sent[0])
    confidence = codecs.msg_to_image(node.pubs[OUT_CONFIDENCE_TOPIC].sent[0])
    assert np.isnan(published[outside]).all() and (confidence[outside] == 0).all()
    assert np.isposinf(published[H // 2, 4 : W // 4 - 2]).all()
    assert (published[~outside & np.isfinite(published)] == 2.0).all()
