"""The rgbd sensor model: confidence falls with range, incidence and near edges; noise grows as d^2."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from area3d_msgs_py.errors import InputError
from area3d_perception.sensor_model import (
    RgbdSensorParams,
    add_depth_noise,
    discontinuity_mask,
    incidence_cosine,
    rgbd_confidence,
)

H, W = 120, 160
# 90 degree horizontal field of view, the paper's camera.
K = np.array([[W / 2, 0, W / 2], [0, W / 2, H / 2], [0, 0, 1.0]])


def plane_depth(distance: float, tilt_deg: float = 0.0, h: int = H, w: int = W) -> np.ndarray:
    """Depth of a plane through (0, 0, distance) whose normal is tilted by `tilt_deg` about x."""
    a = np.deg2rad(tilt_deg)
    n = np.array([0.0, np.sin(a), -np.cos(a)])
    u = (np.arange(w) + 0.5 - w / 2) / (w / 2)
    v = (np.arange(h) + 0.5 - h / 2) / (w / 2)
    uu, vv = np.meshgrid(u, v)
    rays = np.stack([uu, vv, np.ones_like(uu)], axis=-1)
    t = (n @ np.array([0, 0, distance])) / (rays @ n)
    t[t <= 0] = np.nan
    return t.astype(np.float32)


def nguyen_sigma(z: float) -> float:
    """Axial noise at normal incidence as published (Nguyen et al. 2012)."""
    return 0.0012 + 0.0019 * (z - 0.4) ** 2


def centre(a: np.ndarray, r: int = 5) -> np.ndarray:
    return a[H // 2 - r : H // 2 + r, W // 2 - r : W // 2 + r]


def test_confidence_falls_with_range_as_the_published_noise_curve():
    params = RgbdSensorParams()
    ranges = [0.5, 1.0, 2.0, 3.0, 4.0, 4.9]
    conf = [float(centre(rgbd_confidence(plane_depth(d), K, params)).mean()) for d in ranges]
    assert all(a > b for a, b in zip(conf, conf[1:], strict=False))
    for d, c in zip(ranges, conf, strict=True):
        expected = np.exp(-((nguyen_sigma(d) / params.sigma_ref) ** 2))  # near-normal incidence
        assert c == pytest.approx(expected, rel=0.01)


def test_confidence_falls_with_incidence_angle_as_cosine():
    # Full 640x480 resolution: a steep plane's per-pixel depth step stays below the edge threshold.
    h, w = 480, 640
    k = np.array([[w / 2, 0, w / 2], [0, w / 2, h / 2], [0, 0, 1.0]])
    mid = np.s_[h // 2 - 2 : h // 2 + 2, w // 2 - 2 : w // 2 + 2]
    base = float(rgbd_confidence(plane_depth(2.0, h=h, w=w), k)[mid].mean())
    previous = base
    for tilt in (20.0, 45.0, 60.0, 75.0):
        c = float(rgbd_confidence(plane_depth(2.0, tilt, h=h, w=w), k)[mid].mean())
        assert c < previous
        # At the image centre the viewing ray is the optical axis, so theta = tilt.
        assert c / base == pytest.approx(np.cos(np.deg2rad(tilt)), abs=0.03)
        previous = c


def test_incidence_cosine_of_a_fronto_parallel_plane_is_the_ray_angle():
    cos = incidence_cosine(plane_depth(1.0), K)
    # The ray through a corner pixel centre makes angle arctan(|(x, y)|) with the plane normal z.
    x, y = (0.5 - W / 2) / (W / 2), (0.5 - H / 2) / (W / 2)
    assert cos[0, 0] == pytest.approx(1.0 / np.sqrt(1 + x * x + y * y), abs=1e-3)


def test_confidence_is_reduced_near_depth_discontinuities_only():
    params = RgbdSensorParams()
    depth = np.full((H, W), 1.0, np.float32)
    depth[:, W // 2 :] = 1.5
    conf = rgbd_confidence(depth, K, params)
    row = H // 2
    flat = rgbd_confidence(np.full((H, W), 1.0, np.float32), K, params)
    # On the jump: confidence scaled by edge_confidence.
    assert conf[row, W // 2 - 1] == pytest.approx(
        params.edge_confidence * flat[row, W // 2 - 1], rel=1e-3
    )
    # Within the radius: reduced, but less than on the jump.
    inside = W // 2 - 1 - params.edge_radius_px
    assert conf[row, W // 2 - 1] < conf[row, inside] < flat[row, inside]
    # Beyond the radius: untouched.
    outside = W // 2 - 2 - params.edge_radius_px
    assert conf[row, outside] == pytest.approx(flat[row, outside], rel=1e-5)


def test_small_relative_steps_are_not_discontinuities():
    depth = np.full((H, W), 2.0, np.float32)
    depth[:, W // 2 :] = 2.0 * (1 + 0.5 * RgbdSensorParams().edge_jump_rel)
    assert not discontinuity_mask(depth, RgbdSensorParams().edge_jump_rel).any()


def test_silhouette_against_no_return_is_a_discontinuity():
    depth = np.full((H, W), 2.0, np.float32)
    depth[:, :10] = np.nan
    mask = discontinuity_mask(depth, 0.05)
    assert mask[:, 10].all() and not mask[:, 11].any() and not mask[:, :10].any()


def test_confidence_is_zero_where_depth_is_missing_or_beyond_range():
    depth = plane_depth(1.0)
    depth[10:20, 10:20] = np.nan
    depth[30:40, 30:40] = 6.0  # beyond the 5 m max range
    depth[50:60, 50:60] = -1.0
    depth[70:80, 70:80] = np.inf
    conf = rgbd_confidence(depth, K)
    for sl in (np.s_[10:20, 10:20], np.s_[30:40, 30:40], np.s_[50:60, 50:60], np.s_[70:80, 70:80]):
        assert np.all(conf[sl] == 0.0)
    assert np.all(conf[100:110, 100:110] > 0.5)


@settings(max_examples=40, deadline=None)
@given(
    hnp.arrays(
        np.float32,
        st.tuples(st.integers(1, 12), st.integers(1, 12)),
        elements=st.one_of(
            st.floats(-2.0, 8.0, width=32),
            st.sampled_from([np.nan, np.inf, -np.inf, 0.0]),
        ),
    )
)
def test_confidence_is_always_finite_in_unit_interval(depth):
    conf = rgbd_confidence(depth, K)
    assert conf.shape == depth.shape and conf.dtype == np.float32
    assert np.all(np.isfinite(conf)) and np.all((conf >= 0) & (conf <= 1))
    with np.errstate(invalid="ignore"):
        missing = ~(np.isfinite(depth) & (depth > 0) & (depth <= 5.0))
    assert np.all(conf[missing] == 0)


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


def test_bad_input_is_rejected_naming_the_field():
    with pytest.raises(InputError, match="^depth: "):
        rgbd_confidence(np.zeros((4, 4, 1), np.float32), K)
    with pytest.raises(InputError, match="^depth: "):
        rgbd_confidence(np.zeros((4, 4), np.int32), K)
    with pytest.raises(InputError, match="^K: "):
        rgbd_confidence(np.ones((4, 4), np.float32), np.eye(4))
    with pytest.raises(InputError, match="^K: "):
        add_depth_noise(np.ones((4, 4), np.float32), np.zeros((3, 3)), np.random.default_rng(0))
    with pytest.raises(InputError, match="^sigma_ref: "):
        RgbdSensorParams(sigma_ref=0.0)
    with pytest.raises(InputError, match="^edge_confidence: "):
        RgbdSensorParams(edge_confidence=1.5)


def test_sensor_noise_does_not_tilt_the_normals_of_a_frontal_plane():
    rng = np.random.default_rng(11)
    h, w = 480, 640  # at 1 m a pixel is 3 mm wide, comparable to the 2 mm axial noise
    k = np.array([[w / 2, 0, w / 2], [0, w / 2, h / 2], [0, 0, 1.0]])
    clean = plane_depth(1.0, h=h, w=w)
    mid = np.s_[h // 2 - 20 : h // 2 + 20, w // 2 - 20 : w // 2 + 20]
    conf_clean = rgbd_confidence(clean, k)[mid]
    conf_noisy = rgbd_confidence(add_depth_noise(clean, k, rng), k)[mid]
    # The range factor is unchanged by 2 mm of noise; a tilted normal would lower cos theta.
    assert float(np.median(conf_noisy)) == pytest.approx(float(np.median(conf_clean)), rel=0.03)
    assert np.percentile(conf_noisy, 10) > 0.9 * float(np.median(conf_clean))
