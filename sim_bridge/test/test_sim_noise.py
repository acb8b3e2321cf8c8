"""The simulated camera's depth noise: axial noise grows as the published curve, edges jitter and
drop out, grazing pixels drop out; seeded, it repeats bit for bit."""

from pathlib import Path

import numpy as np
import pytest

from area3d_msgs_py.depth_sensor import RgbdSensorParams
from area3d_msgs_py.depth_surface import surface_terms
from area3d_msgs_py.errors import InputError
from sim_bridge.noise import add_depth_noise
from tests.depth_planes import H, K, W, centre, nguyen_sigma, plane_depth


def test_axial_noise_matches_the_published_curve_and_grows_with_depth_squared():
    rng = np.random.default_rng(3)
    h, w = 240, 320
    k = np.array([[w / 2, 0, w / 2], [0, w / 2, h / 2], [0, 0, 1.0]])
    stds = {}
    for d in (1.0, 3.0):
        clean = plane_depth(d, h=h, w=w)
        noisy = add_depth_noise(clean, k, rng)
        crop = np.s_[
            h // 2 - 30 : h // 2 + 30, w // 2 - 30 : w // 2 + 30
        ]  # within ~10 deg of the axis
        residual = (noisy - clean)[crop]
        assert np.isfinite(residual).all()
        stds[d] = float(residual.std())
        assert stds[d] == pytest.approx(nguyen_sigma(d), rel=0.06)
        assert abs(float(residual.mean())) < 3 * stds[d] / np.sqrt(residual.size)
    # Linear growth would give a ratio of 3; the quadratic curve gives about 7.5.
    assert stds[3.0] / stds[1.0] > 6.0


def test_noise_drops_pixels_at_grazing_incidence_and_on_edges():
    rng = np.random.default_rng(0)
    params = RgbdSensorParams()
    frontal = add_depth_noise(plane_depth(1.0), K, rng, params)
    assert np.isnan(centre(frontal, 20)).sum() == 0
    grazing = add_depth_noise(plane_depth(1.0, 84.0), K, rng, params)
    assert np.isnan(centre(grazing, 3)).mean() > 0.6
    step = np.full((H, W), 1.0, np.float32)
    step[:, W // 2 :] = 2.0
    noisy = add_depth_noise(step, K, rng, params)
    edge_cols = noisy[:, W // 2 - 1 : W // 2 + 1]
    assert 0.2 < np.isnan(edge_cols).mean() < 0.8  # edge_dropout = 0.5 of the jump pixels
    assert np.isnan(noisy[:, : W // 2 - 5]).sum() == 0


def test_noise_jitters_edges_laterally_but_keeps_values_from_either_surface():
    rng = np.random.default_rng(1)
    params = RgbdSensorParams(sigma_a=0.0, sigma_b=0.0, sigma_angle=0.0, edge_dropout=0.0)
    step = np.full((H, W), 1.0, np.float32)
    step[:, W // 2 :] = 2.0
    noisy = add_depth_noise(step, K, rng, params)
    band = noisy[:, W // 2 - 2 : W // 2 + 2]
    assert np.all(np.isin(band, [1.0, 2.0]))
    assert np.any(band != step[:, W // 2 - 2 : W // 2 + 2])  # some edge pixels moved across
    assert np.array_equal(noisy[:, : W // 2 - 3], step[:, : W // 2 - 3])


def test_noise_is_repeatable_with_the_same_seed():
    a = add_depth_noise(plane_depth(2.0), K, np.random.default_rng(7))
    b = add_depth_noise(plane_depth(2.0), K, np.random.default_rng(7))
    assert np.array_equal(a, b, equal_nan=True)


def test_axial_noise_is_sigma_z_of_depth_and_incidence_times_a_standard_normal():
    # A tilted plane filling the image: no discontinuity, no grazing pixel, so the only random
    # draw is the per-pixel normal.
    h, w = 60, 80
    k = np.array([[w / 2, 0, w / 2], [0, w / 2, h / 2], [0, 0, 1.0]])
    clean = plane_depth(2.0, 20.0, h=h, w=w)
    params = RgbdSensorParams()
    noisy = add_depth_noise(clean, k, np.random.default_rng(4), params)
    cos, edges = surface_terms(
        clean, k, params.edge_jump_rel, np.inf, params.normal_smoothing_px, params.normal_step_px
    )
    assert not edges.any() and np.all(np.arccos(cos) < np.deg2rad(params.grazing_start_deg))
    theta = np.arccos(cos).astype(np.float64)
    t = theta / (np.pi / 2 - theta)
    sigma = (
        params.sigma_a
        + params.sigma_b * (clean - params.sigma_z0) ** 2
        + params.sigma_angle / np.sqrt(clean) * t * t
    )
    normal = np.random.default_rng(4).standard_normal((h, w), dtype=np.float32)
    np.testing.assert_allclose(noisy, clean + sigma * normal, rtol=0, atol=1e-6)


def test_bad_input_is_rejected_naming_the_field():
    with pytest.raises(InputError, match="^K: "):
        add_depth_noise(np.ones((4, 4), np.float32), np.zeros((3, 3)), np.random.default_rng(0))
    with pytest.raises(InputError, match="^depth: "):
        add_depth_noise(np.zeros((4, 4), np.int32), K, np.random.default_rng(0))


def test_a_seeded_noisy_frame_is_the_one_recorded_bit_for_bit():
    """The noise of one frame with every case (a tilted plane, a box in front of it: depth edges, a
    grazing plane, returns beyond range, no return), seed 7, as recorded in data/noise_seed7.npy
    when the noise was perception's `add_depth_noise`: moving the model may not change a bit."""
    h, w = 48, 64
    depth = plane_depth(1.5, 30.0, h, w)
    depth[:, 40:] = plane_depth(2.0, 82.0, h, w)[:, 40:]
    depth[10:25, 8:24] = 0.9
    depth[30:40, 30:38] = 6.0
    depth[2:6, 50:60] = np.nan
    k = np.array([[32.0, 0, 32], [0, 32.0, 24], [0, 0, 1]])
    recorded = np.load(Path(__file__).parent / "data" / "noise_seed7.npy")
    noisy = add_depth_noise(depth, k, np.random.default_rng(7))
    assert noisy.dtype == recorded.dtype == np.float32
    np.testing.assert_array_equal(noisy.view(np.uint32), recorded.view(np.uint32))
    assert np.isnan(noisy).sum() > np.isnan(depth).sum()  # edges and grazing pixels dropped out


def test_a_camera_class_gets_its_noise_at_its_focal_length_and_nothing_nearer_than_its_minimum():
    """Depth from disparity: the axial noise of coefficients fitted at a 580 px focal length is
    twice as large at 290 px, and the lateral noise in pixels half; a surface nearer than the
    minimum range is not measured (REP 117: -Inf), whatever the noise."""
    params = RgbdSensorParams(reference_focal_px=580.0)
    assert params.at_focal(580.0) is params
    half = params.at_focal(290.0)
    assert half.sigma_a == pytest.approx(2 * params.sigma_a)
    assert half.sigma_b == pytest.approx(2 * params.sigma_b)
    assert half.lateral_l0_px == pytest.approx(params.lateral_l0_px / 2)
    assert RgbdSensorParams().at_focal(290.0) == RgbdSensorParams()  # 0: as given
    h = w = 200
    wall = np.full((h, w), 1.5, np.float32)
    spread = {}
    for fx in (580.0, 290.0):
        k = np.array([[fx, 0, w / 2], [0, fx, h / 2], [0, 0, 1]])
        noisy = add_depth_noise(wall, k, np.random.default_rng(3), params)
        spread[fx] = float(np.std(noisy[10:-10, 10:-10] - 1.5))
    assert spread[290.0] / spread[580.0] == pytest.approx(2.0, rel=0.05)
    near = RgbdSensorParams(min_range=0.5, max_range=4.0)
    k = np.array([[100.0, 0, w / 2], [0, 100.0, h / 2], [0, 0, 1]])
    depth = wall.copy()
    depth[:, : w // 2] = 0.3  # the left half nearer than the camera measures
    noisy = add_depth_noise(depth, k, np.random.default_rng(3), near)
    assert np.isneginf(noisy[:, : w // 2 - 5]).all()
    assert np.isfinite(noisy[:, w // 2 + 5 :]).mean() > 0.95
    with pytest.raises(InputError, match="^min_range: "):
        RgbdSensorParams(min_range=5.0, max_range=4.0)
