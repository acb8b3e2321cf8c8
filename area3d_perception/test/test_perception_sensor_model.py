"""The rgbd sensor model's confidence: it falls with range as the published noise curve, with
incidence as the cosine, and near depth edges; it equals the model written out."""

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from area3d_msgs_py.depth_sensor import RgbdSensorParams
from area3d_msgs_py.depth_surface import surface_terms
from area3d_msgs_py.errors import InputError
from area3d_perception.sensor_model import rgbd_confidence
from sim_bridge.noise import add_depth_noise
from tests.depth_planes import H, K, W, centre, nguyen_sigma, plane_depth


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


def test_bad_input_is_rejected_naming_the_field():
    with pytest.raises(InputError, match="^depth: "):
        rgbd_confidence(np.zeros((4, 4, 1), np.float32), K)
    with pytest.raises(InputError, match="^depth: "):
        rgbd_confidence(np.zeros((4, 4), np.int32), K)
    with pytest.raises(InputError, match="^K: "):
        rgbd_confidence(np.ones((4, 4), np.float32), np.eye(4))


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


def reference_confidence(depth, k, params):
    """`rgbd_confidence` as the module docstring writes it, in numpy, on the surface terms (their
    own per-pixel definition is checked in area3d_msgs_py's test_msgs_depth_sensor)."""
    depth = depth.astype(np.float32)
    cos, edges = surface_terms(
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
