"""`roi_pixels`: the pixels whose depth puts them inside a box of the world."""

from __future__ import annotations

import numpy as np

from area3d_msgs_py.backproject import roi_pixels


def test_roi_pixels_are_those_with_a_positive_finite_depth_landing_in_the_box():
    K = np.array([[10.0, 0.0, 2.0], [0.0, 10.0, 1.0], [0.0, 0.0, 1.0]])
    depth = np.full((2, 4), 1.0, np.float32)  # pixel centres: x = (u + 0.5 - 2) / 10
    depth[0, 0], depth[0, 1], depth[1, 0] = np.nan, np.inf, 0.0
    T = np.eye(4)
    T[:3, 3] = (0.0, 0.0, 0.5)  # the camera half a metre up the z axis: points at z = 1.5
    mask = roi_pixels(depth, K, T, (-0.1, -1.0, 1.4), (0.1, 1.0, 1.6))
    # u = 1 and 2 (x = -0.05, 0.05) are in, u = 0 and 3 (x = -0.15, 0.15) out; row 0's first two have no depth,
    # row 1's first is at 0 m (the camera's centre, z = 0.5, below the box anyway)
    expected = np.array([[False, False, True, False], [False, True, True, False]])
    assert np.array_equal(mask, expected)
    # a zero depth is refused even where the camera's centre lies inside the box
    inside = roi_pixels(depth, K, np.eye(4), (-1.0, -1.0, -0.1), (1.0, 1.0, 2.0))
    assert not inside[1, 0] and inside[1, 1]
