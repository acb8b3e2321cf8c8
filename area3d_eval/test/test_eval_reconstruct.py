"""TSDF fusion of synthetic RGB-D reconstructs a known primitive."""

import numpy as np
import pytest
import trimesh

from area3d_eval.metrics import surface_metrics
from area3d_eval.reconstruct import TsdfFusion, TsdfParams, subsample, tsdf_reconstruct
from area3d_eval.render import render_mesh
from area3d_eval.synthetic import hemisphere_views
from area3d_msgs_py.camera import intrinsics
from area3d_msgs_py.errors import InputError

W, H = 256, 192
RADIUS = 0.1
COLOUR = np.array([200, 120, 40], np.uint8)


@pytest.fixture(scope="module")
def sphere_frames():
    sphere = trimesh.creation.icosphere(subdivisions=5, radius=RADIUS)
    sphere.visual.vertex_colors = np.array([[*COLOUR, 255]] * len(sphere.vertices), np.uint8)
    K = intrinsics(W, H)
    az = np.arange(12) * 30.0
    poses = hemisphere_views(np.zeros(3), 0.4, az, np.where(np.arange(12) % 2 == 0, 35.0, -35.0))
    frames = []
    for T in poses:
        rgb, depth = render_mesh(sphere, K, T, W, H)
        frames.append((rgb, depth, K, T))
    return sphere, frames


def test_sphere_from_twelve_views_is_reconstructed_within_tolerance(sphere_frames):
    sphere, frames = sphere_frames
    mesh = tsdf_reconstruct(frames)  # object-level defaults: 4 mm voxels
    assert len(mesh.triangles) > 1000
    radii = np.linalg.norm(np.asarray(mesh.vertices), axis=1)
    assert np.median(np.abs(radii - RADIUS)) < 0.002
    m = surface_metrics(mesh, sphere, tau=0.01, num_points=20_000)
    assert m["completion"] > 0.95 and m["fscore"] > 0.95
    assert m["chamfer"] < 0.004


def test_fused_colour_is_the_surface_colour(sphere_frames):
    _, frames = sphere_frames
    mesh = tsdf_reconstruct(frames)
    colours = np.asarray(mesh.vertex_colors) * 255
    np.testing.assert_allclose(np.median(colours, axis=0), COLOUR, atol=3)


def test_reconstruction_is_cropped_to_the_roi(sphere_frames):
    _, frames = sphere_frames
    lo, hi = np.array([-0.2, -0.2, 0.0]), np.array([0.2, 0.2, 0.2])
    mesh = tsdf_reconstruct(frames, roi_lo=lo, roi_hi=hi)
    v = np.asarray(mesh.vertices)
    assert len(v) > 100
    assert np.all(v >= lo - 1e-9) and np.all(v <= hi + 1e-9)
    assert v[:, 2].max() > 0.09  # the top of the sphere is kept


def test_no_frames_and_no_returns_give_an_empty_mesh(sphere_frames):
    _, frames = sphere_frames
    assert len(tsdf_reconstruct([]).triangles) == 0
    rgb, depth, K, T = frames[0]
    assert len(tsdf_reconstruct([(rgb, np.full_like(depth, np.nan), K, T)]).triangles) == 0


def test_subsampled_intrinsics_project_to_the_kept_pixel_centres():
    K = intrinsics(640, 480)
    for stride in (2, 3, 4):
        rgb = np.zeros((480, 640, 3), np.uint8)
        _, _, K2 = subsample(rgb, np.zeros((480, 640), np.float32), K, stride)
        o = stride // 2
        u2 = np.array([0, 7, 100])
        # the ray through original pixel centre (s u' + o + 0.5) must hit new pixel centre u' + 0.5
        x = (stride * u2 + o + 0.5 - K[0, 2]) / K[0, 0]
        np.testing.assert_allclose(K2[0, 0] * x + K2[0, 2], u2 + 0.5)


def test_room_level_uses_coarser_voxels_and_bad_levels_are_rejected():
    assert TsdfParams.for_level("room").voxel_length > TsdfParams.for_level("object").voxel_length
    with pytest.raises(InputError, match="level"):
        TsdfParams.for_level("galaxy")


def test_bad_rgb_is_rejected_with_its_name(sphere_frames):
    _, frames = sphere_frames
    rgb, depth, K, T = frames[0]
    with pytest.raises(InputError, match="rgb"):
        tsdf_reconstruct([(rgb.astype(np.float32), depth, K, T)])


def _surface_offsets(mesh, centre_radius: float) -> np.ndarray:
    """Radial distance of the mesh vertices from the sphere's true surface."""
    return np.linalg.norm(np.asarray(mesh.vertices), axis=1) - centre_radius


def test_a_confident_view_outweighs_an_earlier_poor_estimate_of_the_same_surface(sphere_frames):
    """Each frame is seen twice: first with depth 6 mm too far (inside the sphere) and low
    confidence, then exact and confident. Weighted by confidence the surface lands near the
    truth; with equal weights (no confidence) it lands between the two, millimetres inside."""
    _, frames = sphere_frames
    poor = [(rgb, depth + 0.006, K, T) for rgb, depth, K, T in frames]
    ones = [np.ones_like(f[1]) for f in frames]
    low = [np.full_like(f[1], 0.05) for f in frames]

    def fused(confidences_poor, confidences_good):
        fusion = TsdfFusion(TsdfParams())
        for (rgb, depth, K, T), c in zip(poor, confidences_poor, strict=True):
            fusion.integrate(rgb, depth, K, T, c)
        for (rgb, depth, K, T), c in zip(frames, confidences_good, strict=True):
            fusion.integrate(rgb, depth, K, T, c)
        return np.median(_surface_offsets(fusion.extract_mesh(), RADIUS))

    weighted = fused(low, ones)
    equal = fused(ones, ones)
    unweighted = fused([None] * len(frames), [None] * len(frames))
    print(f"median radial offset: weighted {weighted * 1e3:.2f} mm, equal {equal * 1e3:.2f} mm")
    assert abs(weighted) < 0.3 * abs(equal)
    assert -0.004 < equal < -0.001
    assert unweighted == pytest.approx(equal, abs=1e-6)  # no confidence = weight 1 per pixel


def test_pixels_with_no_confidence_add_nothing(sphere_frames):
    _, frames = sphere_frames
    rgb, depth, K, T = frames[0]
    fusion = TsdfFusion(TsdfParams())
    fusion.integrate(rgb, depth, K, T, np.zeros_like(depth))
    fusion.integrate(rgb, depth, K, T, np.full_like(depth, np.nan))
    assert len(fusion.extract_mesh().triangles) == 0
    with pytest.raises(InputError, match="confidence"):
        fusion.integrate(rgb, depth, K, T, np.ones((3, 3), np.float32))


def test_a_frame_with_depth_only_beyond_the_truncation_integrates_nothing_and_keeps_the_volume(
    sphere_frames,
):
    """Depth only beyond `depth_trunc` (a wall far behind the region), or a single usable pixel:
    nothing is integrated, where Open3D aborted the integration ("No block is touched"), and the
    frames after it are integrated as if it had not come."""
    _, frames = sphere_frames
    rgb, depth, K, T = frames[0]
    params = TsdfParams()
    far = np.where(np.isfinite(depth), params.depth_trunc + 1.0, np.nan).astype(np.float32)
    # depth exactly at depth_trunc (a 16-bit driver's 5000 mm): Open3D touches no block there
    at_trunc = np.where(np.isfinite(depth), params.depth_trunc, np.nan).astype(np.float32)
    # one usable pixel off the pixels Open3D looks for blocks at (a view of the region's edge):
    # Open3D touches no block and aborts
    row, col = np.argwhere(np.isfinite(depth))[0]
    lone = np.full_like(depth, np.nan)
    lone[row | 1, col | 1] = depth[row, col]
    with_far, without = TsdfFusion(params), TsdfFusion(params)
    with_far.integrate(rgb, far, K, T)
    with_far.integrate(rgb, at_trunc, K, T)
    with_far.integrate(rgb, lone, K, T)
    assert len(with_far.extract_mesh().triangles) == 0 and with_far.num_frames == 3
    for fusion in (with_far, without):
        for frame in frames[:4]:
            fusion.integrate(*frame)
    a, b = with_far.state(), without.state()
    for name in ("block_keys", "tsdf", "weight", "color"):
        np.testing.assert_array_equal(a[name], b[name], err_msg=name)


def _triangle_set(vertices, triangles) -> set:
    """Each triangle as its corners' positions (rounded to 1e-6 m), starting at the smallest
    corner, keeping its orientation; degenerate ones left out."""
    corners = np.round(np.asarray(vertices, np.float64)[np.asarray(triangles)], 6)
    out = set()
    for tri in corners:
        keys = [tuple(c) for c in tri]
        if len(set(keys)) < 3:
            continue
        k = keys.index(min(keys))
        out.add(tuple(keys[k:] + keys[:k]))
    return out


def test_the_surface_for_display_is_the_extracted_meshs_triangles_cropped_alike(sphere_frames):
    _, frames = sphere_frames
    lo, hi = np.array([-0.2, -0.2, 0.0]), np.array([0.2, 0.2, 0.2])  # the sphere's upper half
    fusion = TsdfFusion(TsdfParams(), lo, hi)
    assert all(len(a) == 0 for a in fusion.surface_arrays())
    for rgb, depth, K, T in frames[:6]:
        fusion.integrate(rgb, depth, K, T)
    vertices, triangles, colours = fusion.surface_arrays()
    mesh = fusion.extract_mesh()
    assert triangles.dtype == np.int32 and colours.shape == vertices.shape
    assert 0.0 <= colours.min() and colours.max() <= 1.0
    shown = _triangle_set(vertices, triangles)
    assert len(shown) > 500
    assert shown == _triangle_set(mesh.vertices, mesh.triangles)
    corners = vertices[triangles].reshape(-1, 3)
    assert np.all(corners >= lo) and np.all(corners <= hi)
