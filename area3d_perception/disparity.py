"""Operations on a disparity map (px, NaN = invalid, x_right = x - d) that the stereo backend
runs after the matching: the statistics of a window around each pixel, and the sub-pixel
refinement of each match on the images, and the left-right check's disagreement.

Arrays in, arrays out; no ROS here.
"""

from __future__ import annotations

from functools import lru_cache

import cv2
import numpy as np


@lru_cache(maxsize=4)
def _pixel_grid(h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
    """(columns, rows) (H, W) float32, each pixel's own coordinates: the identity maps of
    `cv2.remap`, made once per image size (read only)."""
    cols = np.ascontiguousarray(np.broadcast_to(np.arange(w, dtype=np.float32), (h, w)))
    rows = np.ascontiguousarray(np.broadcast_to(np.arange(h, dtype=np.float32)[:, None], (h, w)))
    cols.flags.writeable = rows.flags.writeable = False
    return cols, rows


def disparity_neighbourhood(disparity: np.ndarray, window_px: int) -> tuple[np.ndarray, np.ndarray]:
    """(spread, valid share), both (H, W) float32: the standard deviation of the valid disparities
    in a window around each pixel (px) and the share of the window's pixels that are valid."""
    valid = np.isfinite(disparity).astype(np.float32)
    d = np.where(valid > 0, disparity, 0.0).astype(np.float32)
    size = (window_px, window_px)
    count = cv2.boxFilter(valid, -1, size, normalize=False, borderType=cv2.BORDER_CONSTANT)
    total = cv2.boxFilter(d, -1, size, normalize=False, borderType=cv2.BORDER_CONSTANT)
    squares = cv2.boxFilter(d * d, -1, size, normalize=False, borderType=cv2.BORDER_CONSTANT)
    n = np.maximum(count, 1.0)
    mean = total / n
    spread = np.sqrt(np.maximum(squares / n - mean * mean, 0.0))
    return spread.astype(np.float32), (count / np.float32(window_px * window_px)).astype(np.float32)


REFINE_MAX_STEP_PX = 1.0  # a refinement stays within a pixel of SGBM's disparity


def refine_disparity(
    disparity: np.ndarray,
    left_grey: np.ndarray,
    right_grey: np.ndarray,
    window_px: int,
    min_gradient: float,
    max_spread_px: float,
) -> np.ndarray:
    """(H, W) float32: `disparity` (px, NaN = invalid, x_right = x - d) after one Gauss-Newton step
    on the images, against the pull of SGBM's sub-pixel estimate towards whole disparities.

    Each left pixel is compared with the right image at its own disparity, e = L(x) - R(x - d),
    with the right image's horizontal gradient g there; over a window the least-squares step is
    sum(g e) / sum(g^2), subtracted from every pixel's disparity (one linearisation: more steps
    add each pixel's own noise back into its neighbours' residuals). No step where the window's
    RMS gradient is below `min_gradient` (nothing to lock on), where its valid disparities spread
    more than `max_spread_px` or fewer than half its pixels are valid (two surfaces, or an edge
    of the valid matches); at most REFINE_MAX_STEP_PX. Invalid pixels stay NaN and add nothing."""
    h, w = disparity.shape
    columns, rows = _pixel_grid(h, w)
    valid = np.isfinite(disparity)
    d = np.where(valid, disparity, np.float32(0.0)).astype(np.float32)
    right = right_grey.astype(np.float32)
    map_x = columns - d
    # the right image at x - d, linearly interpolated, and the derivative of that interpolation:
    # the difference of the two pixels it lies between (a smoothed gradient such as Sobel's
    # underestimates it on fine texture, and the step overshoots)
    forward = np.zeros_like(right)
    np.subtract(right[:, 1:], right[:, :-1], out=forward[:, :-1])
    warped = cv2.remap(right, map_x, rows, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    slope = cv2.remap(
        forward, np.floor(map_x), rows, cv2.INTER_NEAREST, borderMode=cv2.BORDER_REPLICATE
    )
    mask = valid.astype(np.float32)
    g = slope * mask
    e = (left_grey.astype(np.float32) - warped) * mask
    size = (window_px, window_px)
    sums = cv2.boxFilter(cv2.merge([g * g, g * e]), -1, size, normalize=False)
    energy, correlation = sums[..., 0], sums[..., 1]
    spread, share = disparity_neighbourhood(disparity, window_px)
    ok = (
        valid
        & (d > 0)  # 0 is at infinity: nothing to refine
        & (energy > np.float32(min_gradient**2 * window_px * window_px))
        & (spread <= max_spread_px)
        & (share >= 0.5)
    )
    step = np.divide(correlation, energy, out=np.zeros_like(d), where=ok)
    np.clip(step, -REFINE_MAX_STEP_PX, REFINE_MAX_STEP_PX, out=step)
    refined = d - step
    # a step to zero or beyond would put the surface at or past infinity: none
    beyond = refined <= 0
    refined[beyond] = d[beyond]
    refined[~valid] = np.nan
    return refined


def lr_difference(disp_left: np.ndarray, disp_right: np.ndarray) -> np.ndarray:
    """|d_L(x) - d_R(x - d_L(x))| per left pixel, px; NaN where either side is invalid.

    disp_left: (H, W) left disparity (x_right = x - d), disp_right: (H, W) right disparity
    (x_left = x + d), both NaN = invalid.
    """
    h, w = disp_left.shape
    columns, rows = _pixel_grid(h, w)
    # the right pixel each left match lands on; -1 (outside: NaN) where the left one is invalid
    target = np.rint(columns - disp_left).astype(np.float32, copy=False)
    np.nan_to_num(target, copy=False, nan=-1.0, posinf=-1.0, neginf=-1.0)
    back = cv2.remap(  # whole-pixel maps: each left pixel reads exactly that right pixel
        disp_right, target, rows, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT,
        borderValue=float("nan"),
    )  # fmt: skip
    return np.abs(disp_left - back)
