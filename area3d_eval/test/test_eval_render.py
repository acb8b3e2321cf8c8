"""Ray-cast rendering of meshes: depth along optical z, pixel-centre convention, colours."""

import numpy as np
import pytest
import trimesh

from area3d_eval.render import render_mesh
from area3d_msgs_py.camera import intrinsics
from area3d_msgs_py.camera_pose import look_at
from area3d_msgs_py.errors import InputError

W, H = 64, 48


def coloured_plane(
    x0: float, x1: float, y0: float, y1: float, colour=(51, 102, 153)
) -> trimesh.Trimesh:
    v = np.array([[x0, y0, 0], [x1, y0, 0], [x1, y1, 0], [x0, y1, 0]], float)
    mesh = trimesh.Trimesh(v, [[0, 1, 2], [0, 2, 3]], process=False)
    mesh.visual.vertex_colors = np.array([[*colour, 255]] * 4, np.uint8)
    return mesh


def test_plane_seen_face_on_has_its_distance_as_depth_everywhere():
    T = look_at([0.2, -0.1, 1.5], [0.2, -0.1, 0.0])
    rgb, depth = render_mesh(coloured_plane(-10, 10, -10, 10), intrinsics(W, H), T, W, H)
    assert depth.shape == (H, W) and depth.dtype == np.float32
    np.testing.assert_allclose(depth, 1.5, atol=1e-5)
    assert np.all(rgb == np.array([51, 102, 153], np.uint8))


def test_depth_is_along_the_optical_axis_not_along_the_ray():
    # a wall 2 m ahead, seen at 90 degree FOV: corner rays are longer, but depth stays 2 m
    wall = trimesh.Trimesh(
        [[2, -9, -9], [2, 9, -9], [2, 9, 9], [2, -9, 9]], [[0, 1, 2], [0, 2, 3]], process=False
    )
    T = look_at([0, 0, 0], [1, 0, 0])
    _, depth = render_mesh(wall, intrinsics(W, H), T, W, H)
    np.testing.assert_allclose(depth, 2.0, atol=1e-5)


def test_plane_edge_under_the_camera_centre_fills_exactly_half_the_columns():
    # pixel centres at u + 0.5 and cx = W / 2: columns u < W/2 look at x < 0, the rest at x > 0
    T = look_at([0, 0, 1.0], [0, 0, 0])
    half = coloured_plane(0, 10, -10, 10)
    rgb, depth = render_mesh(half, intrinsics(W, H), T, W, H)
    x_world = T[:3, 0]  # image x axis in world
    hit_cols = np.isfinite(depth).all(axis=0)
    assert hit_cols.sum() == W // 2
    assert hit_cols[W // 2 :].all() if x_world[0] > 0 else hit_cols[: W // 2].all()


def test_pixels_without_surface_are_black_and_nan():
    T = look_at([0, 0, 1.0], [0, 0, 2.0])  # looking away from the plane
    rgb, depth = render_mesh(coloured_plane(-1, 1, -1, 1), intrinsics(W, H), T, W, H)
    assert np.isnan(depth).all() and not rgb.any()


def test_vertex_colours_are_interpolated_barycentrically():
    v = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], float)
    mesh = trimesh.Trimesh(v, [[0, 1, 2], [0, 2, 3]], process=False)
    mesh.visual.vertex_colors = np.array(
        [[0, 0, 0, 255], [200, 0, 0, 255], [200, 0, 0, 255], [0, 0, 0, 255]], np.uint8
    )
    T = look_at([0, 0, 2.0], [0, 0, 0])
    K = intrinsics(W, H)
    rgb, _ = render_mesh(mesh, K, T, W, H)
    # red grows linearly with world x from 0 at x = -1 to 200 at x = +1
    u = np.arange(W) + 0.5
    x_world = T[0, 0] * (u - K[0, 2]) / K[0, 0] * 2.0 + T[0, 3]
    on_plane = np.abs(x_world) < 1.0
    assert on_plane.sum() == W // 2  # the 2 m wide plane fills half of the 4 m wide view
    np.testing.assert_allclose(rgb[H // 2, on_plane, 0], 100 * (x_world[on_plane] + 1), atol=1.5)


def test_bad_intrinsics_are_rejected_with_their_name():
    with pytest.raises(InputError, match="K"):
        render_mesh(coloured_plane(-1, 1, -1, 1), np.eye(2), np.eye(4), W, H)
