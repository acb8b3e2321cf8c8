"""The numpy side of the Gaussian-splatting path, and its message when the GPU stack is absent."""

import sys

import numpy as np
import pytest

from area3d_eval.splat import (
    SplatUnavailable,
    cameras_to_gsplat,
    init_points_from_frames,
    initial_scales,
    rgb_to_sh0,
    train_gaussians,
)
from area3d_msgs_py.backproject import backproject
from area3d_msgs_py.camera import intrinsics
from area3d_msgs_py.camera_pose import look_at


def frame(seed: int = 0):
    rng = np.random.default_rng(seed)
    rgb = rng.integers(0, 256, (12, 16, 3), dtype=np.uint8)
    depth = rng.uniform(0.5, 2.0, (12, 16)).astype(np.float32)
    depth[rng.random((12, 16)) < 0.3] = np.nan
    T = look_at([1.0, 0.5, 0.8], [0, 0, 0])
    return rgb, depth, intrinsics(16, 12), T


def test_initial_points_are_the_back_projected_pixels_with_their_colours():
    rgb, depth, K, T = frame()
    points, colours = init_points_from_frames([(rgb, depth, K, T)])
    expected, pixel = backproject(depth, K, T)
    np.testing.assert_allclose(points, expected, atol=1e-5)
    np.testing.assert_allclose(colours, rgb.reshape(-1, 3)[pixel] / 255.0, atol=1e-6)


def test_initial_points_are_capped_at_max_points():
    points, colours = init_points_from_frames([frame(0), frame(1)], max_points=50)
    assert points.shape == (50, 3) and colours.shape == (50, 3)


def test_initial_scale_is_the_neighbour_spacing():
    grid = (
        np.stack(np.meshgrid(np.arange(5), np.arange(5), [0.0], indexing="ij"), -1).reshape(-1, 3)
        * 0.01
    )
    scales = initial_scales(grid.astype(np.float32))
    assert scales[12] == pytest.approx(0.01)  # an inner point: its 3 nearest are 1 cm away


def test_sh0_renders_back_to_the_colour():
    colours = np.array([[0.0, 0.5, 1.0]])
    np.testing.assert_allclose(rgb_to_sh0(colours) * 0.28209479177387814 + 0.5, colours, atol=1e-6)


def test_viewmats_invert_the_poses_and_project_like_our_camera():
    T = look_at([0.3, -1.0, 0.5], [0, 0, 0.1])
    K = intrinsics(64, 48)
    viewmats, Ks = cameras_to_gsplat(T[None], K)
    np.testing.assert_allclose(viewmats[0] @ T, np.eye(4), atol=1e-6)
    p = np.array([0.0, 0.0, 0.1, 1.0])  # the look-at target projects to the principal point
    uvw = Ks[0] @ (viewmats[0] @ p)[:3]
    np.testing.assert_allclose(uvw[:2] / uvw[2], [32.0, 24.0], atol=1e-4)


def test_training_without_the_gpu_stack_says_what_to_install(monkeypatch):
    monkeypatch.setitem(sys.modules, "gsplat", None)  # as if not installed, even where it is
    with pytest.raises(SplatUnavailable, match=r"pip install -e \"\.\[ml\]\" gsplat lpips"):
        train_gaussians([frame()], iters=1)
