"""The stereo backend on generated rectified pairs whose true depth is known."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest

from area3d_msgs_py.errors import InputError
from area3d_perception.disparity import lr_difference, refine_disparity
from area3d_perception.estimator import FrameEstimator
from area3d_perception.stereo import (
    CALIBRATION,
    CONFIDENCE_MODELS,
    StereoMatcher,
    StereoParams,
    calibrated_confidence,
)

W, H = 640, 480
FX = (W / 2) / np.tan(np.deg2rad(90.0) / 2)  # 90 degree FOV, as the simulated camera
K = np.array([[FX, 0.0, W / 2], [0.0, FX, H / 2], [0.0, 0.0, 1.0]])
BASELINE = 0.06
TEXEL_M = 0.002  # texture cell on the surface, metres (1.6 texels per pixel at 1 m)


def _texture(seed: int, textured: bool) -> np.ndarray:
    """A 2 x 2 m surface pattern: blurred noise (textured) or one flat grey (textureless)."""
    n = int(2.0 / TEXEL_M)
    if not textured:
        return np.full((n, n), 128.0, np.float32)
    noise = np.random.default_rng(seed).uniform(0, 255, (n, n)).astype(np.float32)
    return cv2.GaussianBlur(noise, (0, 0), 1.0)


def _view(cam_x: float, surfaces: list[tuple], seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(rgb (H, W, 3) uint8, depth (H, W) float32) of a camera at (cam_x, 0, 0) looking along +z.

    surfaces: (z, x_min, x_max, texture) fronto-parallel rectangles, nearest wins; the texture is
    fixed to the surface (world x, y), so both cameras see the same pattern.
    """
    u = (np.arange(W) + 0.5 - K[0, 2]) / FX
    v = (np.arange(H) + 0.5 - K[1, 2]) / FX
    uu, vv = np.meshgrid(u, v)
    depth = np.full((H, W), np.inf, np.float32)
    image = np.zeros((H, W), np.float32)
    for z, x_min, x_max, tex in sorted(surfaces, key=lambda s: -s[0]):
        X, Y = cam_x + uu * z, vv * z
        hit = (X >= x_min) & (X <= x_max) & (z < depth)
        map_x = ((X + 1.0) / TEXEL_M).astype(np.float32)
        map_y = ((Y + 1.0) / TEXEL_M).astype(np.float32)
        sample = cv2.remap(tex, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        image[hit], depth[hit] = sample[hit], z
    image += np.random.default_rng(seed).normal(0.0, 1.0, image.shape)  # sensor noise, 1 grey level
    grey = np.clip(np.rint(image), 0, 255).astype(np.uint8)
    return np.repeat(grey[..., None], 3, axis=2), depth


def _pair(surfaces: list[tuple]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    left, depth = _view(0.0, surfaces, seed=1)
    right, _ = _view(BASELINE, surfaces, seed=2)
    return left, right, depth


@pytest.fixture(scope="module")
def matcher():
    m = StereoMatcher(StereoParams(num_disparities=32, downscale=1, confidence_model="matcher"))
    yield m
    m.close()


def _centre(a: np.ndarray) -> np.ndarray:
    # the band x < num_disparities has no full disparity range; the borders lack a full block
    return a[20:-20, 52:-20]


def test_textured_plane_is_confident_and_within_two_percent(matcher):
    left, right, truth = _pair([(1.0, -5, 5, _texture(0, True))])
    out = matcher.match(left, right, FX, BASELINE)
    conf, depth = _centre(out.confidence), _centre(out.depth)
    assert np.median(conf) > 0.8
    assert np.isfinite(depth).mean() > 0.95
    rel = np.abs(depth - 1.0)[np.isfinite(depth)] / 1.0
    # 1 m is 19.2 px of disparity; SGBM's sub-pixel fit pulls towards whole pixels (about 0.15 px
    # here, 0.8 %), so 2 % leaves room without hiding a wrong focal length or baseline.
    assert np.median(rel) < 0.02


@pytest.mark.parametrize("mode", ["sgbm", "3way", "hh"])
def test_every_matching_mode_reaches_opencv_and_keeps_the_textured_plane_within_two_percent(mode):
    left, right, _ = _pair([(1.0, -5, 5, _texture(0, True))])
    m = StereoMatcher(StereoParams(num_disparities=32, downscale=1, mode=mode))
    try:
        expected = {"sgbm": cv2.STEREO_SGBM_MODE_SGBM, "3way": cv2.STEREO_SGBM_MODE_SGBM_3WAY,
                    "hh": cv2.STEREO_SGBM_MODE_HH}[mode]  # fmt: skip
        assert m._left.getMode() == expected and m._right.getMode() == expected
        depth = _centre(m.match(left, right, FX, BASELINE).depth)
    finally:
        m.close()
    assert np.isfinite(depth).mean() > 0.95
    assert np.median(np.abs(depth[np.isfinite(depth)] - 1.0)) < 0.02


def test_an_unknown_matching_mode_is_refused_naming_the_parameter():
    with pytest.raises(InputError, match=r"^stereo\.mode: got 'bm'.*'3way'"):
        StereoMatcher(StereoParams(mode="bm"))


def test_half_resolution_matching_keeps_the_textured_plane_within_five_percent():
    left, right, _ = _pair([(1.0, -5, 5, _texture(0, True))])
    half = StereoMatcher(StereoParams(num_disparities=16, downscale=2))
    out = half.match(left, right, FX, BASELINE)
    depth = _centre(out.depth)
    assert out.depth.shape == (H, W) and np.isfinite(depth).mean() > 0.95
    # 9.6 px of disparity at half size: pixel locking may move it by up to ~0.4 px (4 %), while a
    # disparity left unscaled to full size would be off by 100 %
    assert np.median(np.abs(depth[np.isfinite(depth)] - 1.0)) < 0.05
    assert np.median(_centre(out.confidence)) > 0.5


def test_textureless_plane_at_the_same_pose_is_not_trusted(matcher):
    left, right, _ = _pair([(1.0, -5, 5, _texture(0, False))])
    out = matcher.match(left, right, FX, BASELINE)
    conf = _centre(out.confidence)
    assert np.mean(conf) < 0.02  # SGBM finds no unique match on most of it
    assert np.percentile(conf, 99) < 0.2  # and the texture factor holds the rest down


def test_occluded_band_beside_a_foreground_edge_gets_no_confidence(matcher):
    # A board at 0.8 m covering x >= 0 in front of a wall at 1.6 m: the wall between x = -B and 0
    # is seen by the left camera only (the right one, B to the right, sees the board there). In
    # the left image that is the band of fx B / 1.6 = 12 px just left of the board's edge.
    wall, board = _texture(3, True), _texture(4, True)
    left, right, _ = _pair([(1.6, -5, 5, wall), (0.8, 0.0, 5, board)])
    out = matcher.match(left, right, FX, BASELINE)
    rows = slice(20, H - 20)
    edge = int(K[0, 2])  # first board column (x = 0 at u = cx)
    width = int(FX * BASELINE / 1.6)
    occluded = out.confidence[rows, edge - width + 1 : edge - 1]
    open_wall = out.confidence[rows, 60 : edge - width - 8]
    board_seen = out.confidence[rows, edge + 8 : W - 20]
    assert np.mean(occluded) < 0.15
    assert np.median(open_wall) > 0.6 and np.median(board_seen) > 0.6


def test_left_right_difference_of_consistent_disparities_is_zero():
    d_left = np.full((4, 10), 2.0, np.float32)
    d_right = np.full((4, 10), 2.0, np.float32)
    d_right[:, 3] = 5.0  # the right pixel that left pixel 5 points to disagrees
    diff = lr_difference(d_left, d_right)
    assert np.isnan(diff[:, :2]).all()  # x - d leaves the right image
    assert diff[0, 5] == 3.0 and diff[0, 6] == 0.0
    # a sub-pixel match reads the right pixel nearest x - d; invalid on either side: no check
    d_left[1, 7], d_left[2, 8], d_right[3, 6] = 1.4, np.nan, np.nan  # 7 - 1.4 -> 6
    d_right[1, 6] = 1.0
    diff = lr_difference(d_left, d_right)
    assert diff[1, 7] == pytest.approx(0.4) and np.isnan(diff[2, 8]) and np.isnan(diff[3, 8])
    assert np.isfinite(diff[:, 2:]).sum() == 4 * 8 - 2


def test_pixels_whose_right_match_points_elsewhere_get_no_depth_and_no_confidence(
    matcher, monkeypatch
):
    """A match the left-right check refuses has no confidence and no weight, and with
    lr_drop_refused no depth (the planner would take it for a surface and carve along its ray)."""
    left, right, _ = _pair([(1.0, -5, 5, _texture(0, True))])
    d_left = np.full((H, W), 19.2, np.float32)
    d_right = d_left.copy()
    d_right[:, 300:320] = 22.0  # right pixels 300-319 disagree: left pixels 319-338 fail the check
    d_right[:, 400:420] = 19.6  # 0.4 px off: consistent, a little less confident
    d_right[:, 500:520] = np.nan  # no right match to check against: left pixels 519-538
    monkeypatch.setattr(matcher, "disparities", lambda _l, _r: (d_left, d_right))
    out = matcher.match(left, right, FX, BASELINE)
    conf = out.confidence
    texture = conf[:, 200:280]
    dropping = StereoMatcher(dataclasses.replace(matcher.params, lr_drop_refused=True))
    try:
        monkeypatch.setattr(dropping, "disparities", lambda _l, _r: (d_left, d_right))
        dropped = dropping.match(left, right, FX, BASELINE)
    finally:
        dropping.close()
    for refused in (slice(320, 338), slice(520, 538)):
        assert (conf[:, refused] == 0).all() and (out.weight[:, refused] == 0).all()
        assert np.isfinite(out.depth[:, refused]).all()  # the default keeps the depth
        assert np.isnan(dropped.depth[:, refused]).all()
        assert (dropped.confidence[:, refused] == 0).all()
    np.testing.assert_array_equal(dropped.depth[:, 200:280], out.depth[:, 200:280])
    np.testing.assert_array_equal(dropped.confidence, out.confidence)
    assert np.median(texture) > 0.5
    assert 0.2 * np.median(texture) < np.median(conf[:, 420:438]) < 0.9 * np.median(texture)


@pytest.mark.parametrize(
    ("left", "right", "baseline", "field"),
    [
        (np.zeros((48, 64, 3), np.uint8), None, 0.06, "right"),
        (np.zeros((48, 64, 3), np.uint8), np.zeros((48, 60, 3), np.uint8), 0.06, "right"),
        (np.zeros((48, 64, 3), np.uint8), np.zeros((48, 64, 3), np.float32), 0.06, "right"),
        (np.zeros((48, 64, 4), np.uint8), np.zeros((48, 64, 3), np.uint8), 0.06, "color"),
        (np.zeros((48, 64, 3), np.uint8), np.zeros((48, 64, 3), np.uint8), 0.0, "baseline"),
    ],
)
def test_bad_pairs_are_refused_naming_the_field(matcher, left, right, baseline, field):
    with pytest.raises(InputError) as err:
        matcher.match(left, right, FX, baseline)
    assert err.value.field == field


@pytest.mark.parametrize("z", [0.83, 1.0, 1.4])
def test_refinement_takes_out_the_pull_towards_whole_disparities(z):
    """SGBM's sub-pixel estimate is pulled towards whole disparities (0.07-0.29 px on these
    planes); one step on the images takes most of it out (measured 0.02-0.04 px). A step of the
    wrong sign or size would double the error or leave it."""
    left, right, _ = _pair([(z, -5, 5, _texture(0, True))])
    truth = FX * BASELINE / z
    errors = {}
    for refine in (False, True):
        m = StereoMatcher(StereoParams(num_disparities=32, refine=refine))
        try:
            d = _centre(m.match(left, right, FX, BASELINE).disparity)
        finally:
            m.close()
        assert np.isfinite(d).mean() > 0.95
        errors[refine] = np.median(np.abs(d[np.isfinite(d)] - truth))
    assert errors[True] < 0.5 * errors[False] and errors[True] < 0.06, errors


def test_refinement_leaves_blank_windows_two_surfaces_and_invalid_pixels_as_they_were():
    rng = np.random.default_rng(3)
    left = rng.integers(0, 256, (60, 80)).astype(np.uint8)
    right = np.roll(left, -10, axis=1)  # disparity 10 everywhere
    blank = np.full((60, 80), 128, np.uint8)
    disparity = np.full((60, 80), 9.75, np.float32)
    disparity[:, :5] = np.nan
    args = (7, 0.7, 0.5)
    # nothing to lock on: no step
    assert np.array_equal(
        refine_disparity(disparity, blank, blank, *args), disparity, equal_nan=True
    )
    refined = refine_disparity(disparity, left, right, *args)
    assert np.isnan(refined[:, :5]).all()  # invalid stays invalid
    inner = refined[10:-10, 20:-10]
    assert np.abs(inner - 10.0).max() < 0.1  # textured, one surface: moved to the truth
    # a window across two surfaces (a 3 px step at column 40): those pixels keep their value
    stepped = disparity.copy()
    stepped[:, 40:] += 3.0
    refined = refine_disparity(stepped, left, right, *args)
    assert np.array_equal(refined[:, 37:43], stepped[:, 37:43])
    # never more than a pixel from the matcher's value
    far = np.full((60, 80), 7.0, np.float32)
    assert np.abs(refine_disparity(far, left, right, *args) - far).max() <= 1.0 + 1e-6
    # never to zero or below (a depth at or past infinity): a surface at infinity (disparity 0)
    # matched at 0.4 px, and one matched at 0 itself, keep positive or zero disparities
    for matched in (0.4, 0.0):
        near_zero = np.full((60, 80), matched, np.float32)
        refined = refine_disparity(near_zero, left, left, *args)
        assert (refined > 0).all() if matched > 0 else np.array_equal(refined, near_zero)


def test_bad_parameters_are_refused():
    with pytest.raises(InputError, match="stereo.num_disparities"):
        StereoMatcher(StereoParams(num_disparities=40))
    with pytest.raises(InputError, match=r"^stereo\.refine_window_px: got 4"):
        StereoMatcher(StereoParams(refine_window_px=4))
    with pytest.raises(InputError, match=r"^stereo\.confidence_model: got 'learned'"):
        StereoMatcher(StereoParams(confidence_model="learned"))
    for bad in ((1.0, 2.0, 3.0), (1.0, 2.0, float("nan"), 4.0), "abcd"):
        with pytest.raises(InputError, match=r"^stereo\.calibration: got .*four finite numbers"):
            StereoMatcher(StereoParams(calibration=bad))


def test_calibrated_confidence_rises_with_disparity_and_falls_with_spread_and_isolation():
    field = np.full((40, 40), 20.0, np.float32)
    near = calibrated_confidence(field, CALIBRATION)[20, 20]
    far = calibrated_confidence(field / 4, CALIBRATION)[20, 20]  # 4x the range
    assert 0.0 < far < near < 1.0
    noisy = field + np.random.default_rng(0).normal(0.0, 3.0, field.shape).astype(np.float32)
    assert calibrated_confidence(noisy, CALIBRATION)[20, 20] < near
    alone = np.full_like(field, np.nan)
    alone[20, 20] = 20.0  # the same match with no valid neighbour
    lone = calibrated_confidence(alone, CALIBRATION)
    assert lone[20, 20] < 0.5 * near
    assert (lone[np.isnan(alone)] == 0).all()  # no disparity, no confidence
    # at downscale 2 the same full-size disparity is half as many pixels of the matching size
    assert calibrated_confidence(field, CALIBRATION, downscale=2)[20, 20] < near


def test_calibrated_textured_planes_rank_by_range_and_fail_the_left_right_check_at_zero(
    monkeypatch,
):
    m = StereoMatcher(StereoParams(num_disparities=32, downscale=1, confidence_model="calibrated"))
    try:
        near = m.match(*_pair([(1.0, -5, 5, _texture(0, True))])[:2], FX, BASELINE)
        far = m.match(*_pair([(2.5, -5, 5, _texture(0, True))])[:2], FX, BASELINE)
        assert np.median(_centre(near.confidence)) > 0.8  # 19 px of disparity, a dense field
        assert np.median(_centre(far.confidence)) < np.median(_centre(near.confidence))
        left, right, _ = _pair([(1.0, -5, 5, _texture(0, True))])
        d_left = np.full((H, W), 19.2, np.float32)
        d_right = d_left.copy()
        d_right[:, 300:320] = 22.0  # left pixels 319-338 fail the check
        monkeypatch.setattr(m, "disparities", lambda _l, _r: (d_left, d_right))
        conf = m.match(left, right, FX, BASELINE).confidence
        assert (conf[:, 320:338] == 0).all() and np.median(conf[:, 200:280]) > 0.8
    finally:
        m.close()


def test_the_fusion_weight_is_the_matchers_confidence_whatever_the_model_the_planner_reads():
    left, right, _ = _pair([(1.0, -5, 5, _texture(0, True)), (2.5, -12, 12, _texture(1, True))])
    outs = {}
    for model in CONFIDENCE_MODELS:
        est = FrameEstimator(
            "stereo", stereo=StereoParams(num_disparities=32, downscale=1, confidence_model=model)
        )
        outs[model] = est.process(left, None, K, np.eye(4), right=right, baseline=BASELINE)
    matcher, calibrated = outs["matcher"], outs["calibrated"]
    np.testing.assert_array_equal(matcher.weight, matcher.confidence)
    np.testing.assert_array_equal(calibrated.depth, matcher.depth)
    np.testing.assert_array_equal(calibrated.weight, matcher.confidence)  # bit for bit
    estimated = np.isfinite(matcher.depth)
    assert not np.allclose(calibrated.confidence[estimated], calibrated.weight[estimated])
    # perception's w/o feed-forward ablation weighs every pixel the backend keeps 1, in the
    # reconstruction too; a match the left-right check refused (a depth at confidence 0) stays 0
    est = FrameEstimator(
        "stereo",
        stereo=StereoParams(num_disparities=32, downscale=1, confidence_model="calibrated"),
        uniform_confidence=True,
    )
    uniform = est.process(left, None, K, np.eye(4), right=right, baseline=BASELINE)
    refused = estimated & (calibrated.confidence == 0)
    assert refused.any()  # the occluded band beside the near board
    np.testing.assert_array_equal(uniform.weight, (estimated & ~refused).astype(np.float32))
    np.testing.assert_array_equal(uniform.confidence, uniform.weight)


def test_estimator_stereo_backend_needs_the_right_image_and_ignores_sensor_depth():
    left, right, truth = _pair([(1.0, -5, 5, _texture(0, True))])
    est = FrameEstimator(backend="stereo", stereo=StereoParams(num_disparities=32, downscale=1))
    with pytest.raises(InputError, match="right"):
        est.process(left, truth, K, np.eye(4))
    out = est.process(left, np.full_like(truth, 3.0), K, np.eye(4), right=right, baseline=BASELINE)
    assert abs(float(np.nanmedian(_centre(out.depth))) - 1.0) < 0.02
    # a pixel stereo could not match is unknown (NaN), never a return beyond range (+Inf): the
    # planner carves nothing through it, whatever the depth camera's no_return rule
    assert np.isnan(out.depth).any() and not np.isinf(out.depth).any()
    stereo = StereoParams(num_disparities=32, downscale=1)
    assert (
        FrameEstimator("stereo", stereo=stereo, no_return="all")
        .process(left, None, K, np.eye(4), right=right, baseline=BASELINE)
        .depth.tobytes()
        == out.depth.tobytes()
    )
