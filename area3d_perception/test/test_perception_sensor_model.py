"""The rgbd sensor model: confidence falls with range, incidence and near edges; noise grows as d^2."""

import cv2
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
    edge_distance,
    incidence_cosine,
    rgbd_confidence,
    surface_terms,
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


# Straightforward per-pixel references of the compiled kernels (the module docstring's model as
# it reads), for the tests below that check the fast paths against them.
def reference_surface_terms(depth, k, jump_rel, max_range, smoothing_px, step):
    """(cos, edges) of `surface_terms`, one pixel at a time in float64."""
    h, w = depth.shape
    fx, fy, cx, cy = k[0, 0], k[1, 1], k[0, 2], k[1, 2]

    def present(d):
        return bool(np.isfinite(d) and 0 < d <= max_range)

    smooth = depth.astype(np.float32).copy()
    if smoothing_px > 0:
        for v in range(h):
            for u in range(w):
                d = depth[v, u]
                window = depth[
                    max(v - smoothing_px, 0) : v + smoothing_px + 1,
                    max(u - smoothing_px, 0) : u + smoothing_px + 1,
                ].ravel()
                same = [float(x) for x in window if present(x) and abs(x - d) <= jump_rel * d]
                smooth[v, u] = np.float32(np.mean(same)) if present(d) else np.nan

    def point(v, u):
        s = float(smooth[v, u])
        return np.array([(u + 0.5 - cx) / fx * s, (v + 0.5 - cy) / fy * s, s])

    def tangent(v, u, dv, du):
        s = float(smooth[v, u])
        best = None
        for sign in (-1, 1):
            vv, uu = v + sign * dv, u + sign * du
            if not (0 <= vv < h and 0 <= uu < w):
                continue
            sn = float(smooth[vv, uu])
            if np.isfinite(sn) and sn > 0 and (best is None or abs(sn - s) < best[0]):
                best = (abs(sn - s), sign * (point(vv, uu) - point(v, u)))
        return None if best is None else best[1]

    cos = np.zeros((h, w), np.float32)
    edges = np.zeros((h, w), bool)
    for v in range(h):
        for u in range(w):
            d = depth[v, u]
            if not present(d):
                continue
            for vv, uu in ((v, u - 1), (v, u + 1), (v - 1, u), (v + 1, u)):
                if 0 <= vv < h and 0 <= uu < w:
                    dn = depth[vv, uu]
                    edges[v, u] |= not present(dn) or abs(dn - d) > jump_rel * min(d, dn)
            tu, tv = tangent(v, u, 0, step), tangent(v, u, step, 0)
            if tu is None or tv is None:
                continue
            n, p = np.cross(tu, tv), point(v, u)
            if np.linalg.norm(n) > 0:
                cos[v, u] = min(abs(n @ p) / (np.linalg.norm(n) * np.linalg.norm(p)), 1.0)
    return cos, edges


def reference_confidence(depth, k, params):
    """`rgbd_confidence` as the module docstring writes it, in numpy."""
    depth = depth.astype(np.float32)
    cos, edges = reference_surface_terms(
        depth,
        k,
        params.edge_jump_rel,
        params.max_range,
        params.normal_smoothing_px,
        params.normal_step_px,
    )
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(depth) & (depth > 0) & (depth <= params.max_range)
    z = np.where(valid, depth, 1.0).astype(np.float64)
    sigma = params.sigma_a + params.sigma_b * (z - params.sigma_z0) ** 2
    conf = np.exp(-((sigma / params.sigma_ref) ** 2)) * np.maximum(cos, 0) ** params.incidence_power
    if edges.any():
        dist = cv2.distanceTransform((~edges).view(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_5)
        ramp = np.clip(dist / (params.edge_radius_px + 1), 0.0, 1.0)
        conf *= params.edge_confidence + (1 - params.edge_confidence) * ramp
    return np.where(valid, np.clip(conf, 0.0, 1.0), 0.0)


# Depths that exercise every branch: one surface with small steps, a second one a jump away,
# missing (NaN, 0, < 0), infinite and beyond-range pixels.
depth_images = hnp.arrays(
    np.float32,
    st.tuples(st.integers(1, 10), st.integers(1, 12)),
    elements=st.one_of(
        st.floats(0.9375, 1.0625, width=32),
        st.floats(1.875, 2.125, width=32),
        st.sampled_from([np.nan, 0.0, -1.0, np.inf, 6.0]),
    ),
)


@settings(max_examples=60, deadline=None)
@given(
    depth_images,
    st.sampled_from([(1, 2), (0, 1), (2, 3), (1, 1)]),
    st.sampled_from([5.0, np.inf]),
)
def test_surface_terms_equal_the_per_pixel_definition(depth, smoothing_and_step, max_range):
    smoothing_px, step = smoothing_and_step
    k = np.array([[8.0, 0, 6.0], [0, 9.0, 5.0], [0, 0, 1]])
    cos, edges = surface_terms(depth, k, 0.05, max_range, smoothing_px, step)
    ref_cos, ref_edges = reference_surface_terms(depth, k, 0.05, max_range, smoothing_px, step)
    np.testing.assert_array_equal(edges, ref_edges)
    np.testing.assert_allclose(cos, ref_cos, rtol=0, atol=1e-5)


@settings(max_examples=40, deadline=None)
@given(
    depth_images,
    st.sampled_from(
        [
            RgbdSensorParams(),
            RgbdSensorParams(incidence_power=2.0, edge_radius_px=1, edge_confidence=0.5),
            RgbdSensorParams(edge_confidence=1.0, max_range=1.5),
            RgbdSensorParams(edge_radius_px=6),  # past the bounded window: the full transform
        ]
    ),
)
def test_confidence_equals_the_model_written_out(depth, params):
    k = np.array([[8.0, 0, 6.0], [0, 9.0, 5.0], [0, 0, 1]])
    np.testing.assert_allclose(
        rgbd_confidence(depth, k, params), reference_confidence(depth, k, params), atol=1e-5
    )


@settings(max_examples=60, deadline=None)
@given(
    hnp.arrays(
        bool,
        st.tuples(st.integers(1, 40), st.integers(1, 40)),
        elements=st.booleans() | st.just(False),
    ),
    st.sampled_from([0.0, 1.0, 1.4, 2.0, 3.0, 4.5, 7.0, np.inf]),
)
def test_bounded_edge_distance_is_the_full_transform_cut_at_the_bound(edges, max_px):
    full = (
        cv2.distanceTransform((~edges).view(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_5)
        if edges.any()
        else np.full(edges.shape, np.inf, np.float32)
    )
    expected = np.where(full <= max_px, full, np.inf)
    np.testing.assert_array_equal(edge_distance(edges, max_px), expected)


@pytest.mark.parametrize("fraction", [0.005, 0.3])
def test_bounded_edge_distance_on_a_full_frame_sparse_or_dense(fraction):
    """A 640x480 frame with few edges (each edge pixel's window) and with many (one OpenCV
    pass, cut at the bound) gives the full transform cut at the bound either way."""
    edges = np.random.default_rng(5).random((480, 640)) < fraction
    full = cv2.distanceTransform((~edges).view(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_5)
    for max_px in (2.0, 3.0):
        expected = np.where(full <= max_px, full, np.inf)
        np.testing.assert_array_equal(edge_distance(edges, max_px), expected)


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
