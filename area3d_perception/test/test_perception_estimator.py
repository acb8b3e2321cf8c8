"""FrameEstimator: every backend turns a frame into metric depth and confidence in [0, 1]."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from area3d_msgs_py.depth_sensor import RgbdSensorParams
from area3d_msgs_py.errors import InputError
from area3d_perception.estimator import (
    NO_RETURN_REGION_PX,
    FrameEstimator,
    check_frame,
    declare_no_return,
    sanitize_depth,
)
from area3d_perception.feedforward import BackendUnavailableError, FeedForwardOutput

H, W = 48, 64
K = np.array([[W / 2, 0, W / 2], [0, W / 2, H / 2], [0, 0, 1.0]])
RGB = np.zeros((H, W, 3), np.uint8)


def wall(d: float = 2.0) -> np.ndarray:
    return np.full((H, W), d, np.float32)


def pose(centre) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = centre
    return T


def test_uniform_backend_gives_full_confidence_on_valid_pixels_only():
    depth = wall()
    depth[:5] = np.nan
    out = FrameEstimator("uniform").process(RGB, depth, K, np.eye(4))
    assert np.all(out.confidence[5:] == 1.0) and np.all(out.confidence[:5] == 0.0)
    np.testing.assert_array_equal(out.depth, depth)


def test_rgbd_backend_confidence_is_lower_far_away():
    est = FrameEstimator("rgbd")
    near = est.process(RGB, wall(1.0), K, np.eye(4)).confidence
    far = est.process(RGB, wall(4.0), K, np.eye(4)).confidence
    assert np.all(far[10:-10, 10:-10] < near[10:-10, 10:-10])


def test_every_depth_backend_passes_valid_depth_through_unaltered():
    rng = np.random.default_rng(1)
    depth = (2.0 + 0.01 * rng.standard_normal((H, W))).astype(np.float32)
    depth[3:6, 7:9] = np.nan
    for backend in ("rgbd", "uniform"):
        out = FrameEstimator(backend).process(RGB, depth, K, np.eye(4)).depth
        np.testing.assert_array_equal(out, depth)


def test_depth_keeps_rep_117_no_return_and_bad_values_become_missing_with_a_note_naming_the_count():
    depth = wall()
    depth[0, :3] = np.inf  # REP 117: no return within range, measured
    depth[1, :2] = -1.0
    depth[2, :4] = -np.inf  # REP 117: nearer than the camera measures: unknown
    out = FrameEstimator("rgbd").process(RGB, depth, K, np.eye(4))
    assert np.isposinf(out.depth[0, :3]).all()
    assert np.isnan(out.depth[1, :2]).all() and np.isnan(out.depth[2, :4]).all()
    assert np.all(out.confidence[:3, :4][~np.isfinite(out.depth[:3, :4])] == 0)
    assert out.notes == ["depth: 2 values <= 0 set to missing (NaN)"]  # REP 117's are not bad
    clean, notes = sanitize_depth(wall())
    assert notes == [] and np.array_equal(clean, wall())


def test_mismatched_sizes_are_rejected():
    with pytest.raises(InputError, match="^color: "):
        FrameEstimator("rgbd").process(np.zeros((H, W + 1, 3), np.uint8), wall(), K, np.eye(4))
    with pytest.raises(InputError, match="^camera_info: "):
        check_frame(RGB, wall(), (W, H + 2))
    check_frame(RGB, wall(), (W, H))


def test_unknown_backend_and_missing_weights_are_start_errors():
    with pytest.raises(InputError, match="^backend: "):
        FrameEstimator("lidar")
    with pytest.raises(BackendUnavailableError, match="nowhere/model.pt"):
        FrameEstimator("vggt", checkpoint="/nowhere/model.pt")


class FakeModel:
    """Predicts the true depth divided by `scale`, and camera centres in a rotated, scaled frame."""

    def __init__(self, truth, scale, R, t):
        self.truth, self.scale, self.R, self.t = truth, scale, R, t
        self.calls = []

    def predict_views(self, images):
        self.calls.append(len(images))
        n = len(images)
        centres = np.stack(self.truth["centres"][-n:])
        pred_centres = ((centres - self.t) @ self.R) / self.scale  # inverse of s R x + t
        conf = [np.full((H, W), 5.0, np.float32) for _ in images]
        return FeedForwardOutput([self.truth["depth"] / self.scale] * n, conf, pred_centres)


def test_feedforward_depth_is_scaled_by_the_metric_depth_when_present():
    truth = {"depth": wall(2.0), "centres": [np.zeros(3)]}
    model = FakeModel(truth, 7.0, np.eye(3), np.zeros(3))
    est = FrameEstimator("vggt", model_factory=lambda ckpt, dev: model)
    out = est.process(RGB, wall(2.0), K, pose([0, 0, 0]))
    np.testing.assert_allclose(out.depth, 2.0, rtol=1e-5)
    np.testing.assert_allclose(out.confidence, 1 - 1 / 5.0, rtol=1e-6)


def test_feedforward_depth_is_scaled_by_the_poses_without_a_depth_sensor():
    truth = {"depth": wall(3.0), "centres": []}
    R = Rotation.from_euler("xyz", [10, -40, 70], degrees=True).as_matrix()
    model = FakeModel(truth, 0.25, R, np.array([1.0, 2.0, 3.0]))
    est = FrameEstimator("vggt", window=3, model_factory=lambda ckpt, dev: model)
    centres = [
        np.array([0.0, 0, 0]),
        np.array([1.0, 0.2, 0]),
        np.array([0.3, 1.0, 0.5]),
        np.array([2.0, 2.0, 0.1]),
    ]
    outs = []
    for c in centres:
        truth["centres"].append(c)
        outs.append(est.process(RGB, None, K, pose(c)))
    assert model.calls == [1, 2, 3, 3]  # the window holds the new frame and two before it
    assert any("model units" in n for n in outs[0].notes)
    for out in outs[1:]:
        np.testing.assert_allclose(out.depth, 3.0, rtol=1e-6)
        assert out.notes == []


def test_feedforward_needs_color():
    model = FakeModel({"depth": wall(), "centres": [np.zeros(3)]}, 1.0, np.eye(3), np.zeros(3))
    est = FrameEstimator("depth_anything_3", model_factory=lambda ckpt, dev: model)
    with pytest.raises(InputError, match="^color: "):
        est.process(None, wall(), K, np.eye(4))


def test_a_depth_cameras_regions_without_a_return_are_declared_no_return_and_its_dropouts_not():
    """REP 117 out of a camera that says NaN for both: a region of no return (sky, open space
    beyond range) becomes +Inf, which the planner carves free; an isolated dropout (a dark or
    specular patch) stays NaN, unknown. `none` declares nothing, `all` every missing pixel."""
    depth = wall()
    depth[:, : W // 2] = np.nan  # open space left of the wall
    depth[H // 2, W - 5] = np.nan  # a dropout on the wall
    for rule, declared in (("none", 0), ("all", H * (W // 2) + 1)):
        out = FrameEstimator("rgbd", no_return=rule).process(RGB, depth, K, np.eye(4))
        assert int(np.isposinf(out.depth).sum()) == declared, rule
    out = FrameEstimator("rgbd").process(RGB, depth, K, np.eye(4))  # regions, the default
    far = W // 2 - NO_RETURN_REGION_PX  # columns farther than that from the wall's returns
    assert np.isposinf(out.depth[:, :far]).all()
    assert np.isnan(out.depth[:, far : W // 2]).all() and np.isnan(out.depth[H // 2, W - 5])
    assert np.array_equal(declare_no_return(depth.copy(), "regions"), out.depth, equal_nan=True)
    with pytest.raises(InputError, match="^no_return: "):
        FrameEstimator("rgbd", no_return="sky")


def test_a_blank_or_saturated_frame_declares_nothing_beyond_range_and_says_so():
    """All zeros, or all at a 16-bit driver's 65.535 m (beyond range): every pixel was a
    region of no return, +Inf, and the planner carved free space through the whole map in front
    of the camera (a walkthrough's map lost half its box). A frame with returns in under 1 % of
    its pixels is the camera failing: nothing declared, a note; one with a few returns is not."""
    for blank in (0.0, 65.535):
        for rule in ("regions", "all"):
            depth = np.full((H, W), blank, np.float32)
            out = FrameEstimator("rgbd", no_return=rule).process(RGB, depth, K, np.eye(4))
            assert not np.isposinf(out.depth).any() and not out.confidence.any()
            assert any("blank or saturated frame" in note for note in out.notes), out.notes
    depth = np.full((H, W), np.nan, np.float32)
    depth[: H // 10] = 2.0  # a tenth of the image sees a surface, the rest open space
    out = FrameEstimator("rgbd").process(RGB, depth, K, np.eye(4))
    assert np.isposinf(out.depth).any() and out.notes == []


def test_a_surface_nearer_than_the_cameras_minimum_range_is_no_estimate_never_no_return():
    """A wall too near fills the image (the camera says -Inf, REP 117, or a driver gives values
    below its minimum range): no estimate, however large the region, so nothing is carved through
    it; a region the camera declared empty beyond range (+Inf) stays so."""
    sensor = RgbdSensorParams(min_range=0.5)
    for too_near in (-np.inf, 0.3):
        depth = np.full((H, W), too_near, np.float32)
        depth[:, -8:] = np.inf
        for rule in ("regions", "all"):
            out = FrameEstimator("rgbd", sensor=sensor, no_return=rule).process(
                RGB, depth, K, np.eye(4)
            )
            assert np.isnan(out.depth[:, :-8]).all() and np.isposinf(out.depth[:, -8:]).all()
            assert not out.confidence.any() and out.notes == []
