"""The depth sensor's description and what a depth image says about its surface: incidence
angles, discontinuities and the distance to them, checked against their per-pixel definitions."""

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from area3d_msgs_py.depth_sensor import RgbdSensorParams
from area3d_msgs_py.depth_surface import (
    discontinuity_mask,
    edge_distance,
    incidence_cosine,
    surface_terms,
)
from area3d_msgs_py.errors import InputError
from tests.depth_planes import H, K, W, plane_depth


def test_incidence_cosine_of_a_fronto_parallel_plane_is_the_ray_angle():
    cos = incidence_cosine(plane_depth(1.0), K)
    # The ray through a corner pixel centre makes angle arctan(|(x, y)|) with the plane normal z.
    x, y = (0.5 - W / 2) / (W / 2), (0.5 - H / 2) / (W / 2)
    assert cos[0, 0] == pytest.approx(1.0 / np.sqrt(1 + x * x + y * y), abs=1e-3)


def test_small_relative_steps_are_not_discontinuities():
    depth = np.full((H, W), 2.0, np.float32)
    depth[:, W // 2 :] = 2.0 * (1 + 0.5 * RgbdSensorParams().edge_jump_rel)
    assert not discontinuity_mask(depth, RgbdSensorParams().edge_jump_rel).any()


def test_silhouette_against_no_return_is_a_discontinuity():
    depth = np.full((H, W), 2.0, np.float32)
    depth[:, :10] = np.nan
    mask = discontinuity_mask(depth, 0.05)
    assert mask[:, 10].all() and not mask[:, 11].any() and not mask[:, :10].any()


def test_bad_parameters_are_rejected_naming_the_field():
    with pytest.raises(InputError, match="^sigma_ref: "):
        RgbdSensorParams(sigma_ref=0.0)
    with pytest.raises(InputError, match="^edge_confidence: "):
        RgbdSensorParams(edge_confidence=1.5)


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
