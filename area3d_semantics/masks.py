"""Soft image masks of grid regions: the named 4x3 cell, mildly dilated, with a Gaussian edge taper.

A mask is separable, M(v, u) = m_y(v) * m_x(u), so a whole weight map is one small matrix product.
"""

from __future__ import annotations

import numpy as np

from area3d_msgs_py.errors import InputError
from area3d_semantics.region import COLUMNS, ROWS, Region

# "Mild dilation for recall" (paper, Sec. 3.3): grow the cell by 10% of its size on every side.
DEFAULT_DILATION = 0.10
# "Gaussian edge tapering" (paper, Sec. 3.3); the width is not published: sigma = 15% of the cell,
# so the mask falls to ~3% at the centre of the neighbouring cell.
DEFAULT_TAPER_SIGMA = 0.15


def cell_bounds(column: str, row: str) -> tuple[float, float, float, float]:
    """(x0, x1, y0, y1) of a grid cell as fractions of the image width and height."""
    if column not in COLUMNS:
        raise InputError("column", column, f"one of {', '.join(COLUMNS)}")
    if row not in ROWS:
        raise InputError("row", row, f"one of {', '.join(ROWS)}")
    c, r = COLUMNS.index(column), ROWS.index(row)
    nc, nr = len(COLUMNS), len(ROWS)
    return c / nc, (c + 1) / nc, r / nr, (r + 1) / nr


def axis_profile(
    lo: float, hi: float, n: int, dilation: float, taper_sigma: float, extent_scale: float = 1.0
) -> np.ndarray:
    """(n,) float32 1-D taper over pixel centres: 1 inside [lo, hi] (fractions of the axis) grown by
    `dilation` * (hi - lo) on each side, Gaussian fall-off with sigma = taper_sigma * (hi - lo)
    outside. `extent_scale` scales the half-width about the centre before dilation."""
    centre, half = 0.5 * (lo + hi), 0.5 * (hi - lo)
    half_in = half * extent_scale + dilation * (hi - lo)
    t = (np.arange(n, dtype=np.float32) + 0.5) / n
    outside = np.maximum(np.abs(t - centre) - half_in, 0.0)
    if taper_sigma <= 0:
        return (outside == 0).astype(np.float32)
    sigma = taper_sigma * (hi - lo)
    return np.exp(-0.5 * (outside / sigma) ** 2).astype(np.float32)


def region_profiles(
    region: Region,
    height: int,
    width: int,
    dilation: float = DEFAULT_DILATION,
    taper_sigma: float = DEFAULT_TAPER_SIGMA,
    extent_scale: float = 1.0,
) -> tuple[np.ndarray, np.ndarray]:
    """The separable factors (m_y (H,), m_x (W,)) of a region's mask."""
    x0, x1, y0, y1 = cell_bounds(region.column, region.row)
    m_y = axis_profile(y0, y1, height, dilation, taper_sigma, extent_scale)
    m_x = axis_profile(x0, x1, width, dilation, taper_sigma, extent_scale)
    return m_y, m_x


def region_mask(
    region: Region,
    height: int,
    width: int,
    dilation: float = DEFAULT_DILATION,
    taper_sigma: float = DEFAULT_TAPER_SIGMA,
    extent_scale: float = 1.0,
) -> np.ndarray:
    """(H, W) float32 soft mask in [0, 1] of one region: 1 on its (dilated) cell, tapering outside.

    dilation and taper_sigma are fractions of the cell size along each axis; extent_scale grows or
    shrinks the cell about its centre (used for the region's SIZE, see SemanticParams.size_extent).
    """
    if height < 1 or width < 1:
        raise InputError("height, width", (height, width), "positive image size")
    m_y, m_x = region_profiles(region, height, width, dilation, taper_sigma, extent_scale)
    return np.outer(m_y, m_x)
