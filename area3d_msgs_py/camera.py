"""The paper's camera, and the pinhole convention every part of the graph builds intrinsics with.

Paper, supplement, Table "Hyperparameters for frustum-based uncertainty decay": field of view
90 degrees, maximum depth 5 m. The simulated camera, the planner's candidate views, fusion, the
sensor model and the evaluation default to these; a robot's camera brings its own (CameraInfo,
`max_range` parameters).
"""

from __future__ import annotations

import numpy as np

PAPER_HFOV_DEG = 90.0  # horizontal field of view, degrees (paper, supplement: FOV 90 degrees)
PAPER_MAX_RANGE = 5.0  # metres (paper, supplement: max depth 5 m)


def intrinsics(width: int, height: int, hfov_deg: float = PAPER_HFOV_DEG) -> np.ndarray:
    """(3, 3) float64 K of an undistorted pinhole camera with square pixels: fx = fy =
    (W / 2) / tan(hfov / 2), cx = W / 2, cy = H / 2 (pixel centres at +0.5)."""
    f = (width / 2) / np.tan(np.deg2rad(hfov_deg) / 2)
    return np.array([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]])
