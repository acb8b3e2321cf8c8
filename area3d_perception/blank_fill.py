"""Disparity for blank surfaces: a plane through the reliable matches around each blank region.

Semi-global matching has nothing to match on a surface of one colour (a painted panel, a screen, a
lamp shade): its smoothness term spreads whatever disparity reaches the region, and the result is
streaks of wrong depth or none. Around such a region, though, its edges and the textured things
beside it are matched well. Where those reliable matches all around the region lie on one plane
in disparity space (a plane in the scene is a plane there: d = a u + b v + c), the region is taken
to be that plane, as in the refinement steps of stereo pipelines for untextured areas and invalid
disparities (Hirschmueller 2008, PAMI: segment-wise planes and interpolation; ELAS's support
points).

For each connected blank region (the texture factors of horizontal and of vertical gradients both
below `blank_texture`, at least `blank_min_area_px` pixels): the reliable pixels on a ring around it (valid, left-right
difference <= RELIABLE_LR_PX, textured) vote by RANSAC for a plane; the plane is kept only when
most of them agree (INLIER_SHARE within PLANE_TOL_PX) and the agreeing ones lie on all four sides
of the region (no extrapolation past a side nothing was matched on), and the band around the
region, its own edge, must look the same in the right image through the plane (a photometric check:
a blank board before a textured wall has the wall's matches all around it, and the wall's plane
would shift the board's edge onto the wall). The region's pixels then take the plane's disparity
(the matcher's values there had nothing to go on). A region whose border straddles two surfaces
(a blank panel against the sky, two walls at a corner) finds no plane that most of its ring agrees
on and stays as it was. A region reaching the image's top and a side (the sky over a horizon) is
bounded on two sides at most: no plane, and no estimate (`_open`).

The filled pixels are an inference, not a measurement: the backend gives them the confidence
`blank_fill_confidence` (times the share of the ring that agreed), low enough that every matched
view of the surface outweighs them in the TSDF, and the planner still sees them as uncertain.

Arrays in, arrays out; no ROS here.
"""

from __future__ import annotations

import cv2
import numpy as np

# A ring pixel is reliable when its left-right difference is at most this (pixels) and its texture
# factor at least RELIABLE_TEXTURE (our choices: half the check's own one-pixel limit; texture
# where SGBM's errors are those of a textured surface, README of the backend).
RELIABLE_LR_PX = 0.5
RELIABLE_TEXTURE = 0.5
RING_PX = 4  # width of the ring around a region, pixels
# a ring pixel agrees with a plane within this disparity, pixels of the matching size (a match's
# noise is in those: at downscale 2 twice this in full-size pixels; measured on a blank board in a
# textured frame, pixels within 2 cm: 62 % against 49 % with the unscaled tolerance)
PLANE_TOL_PX = 0.5
# The least share of the ring that must agree. A panel seen against something farther has its own
# textured edge (about half the texture window, 3 px) in the 4 px ring and, beyond its silhouette,
# the farther surface: at most about 74 % of the ring on the panel, and noise takes some of that
# (the thin_objects hold-out's screen: 69.9 % in one view, the plane 0.07 px from the truth, median).
# A plane tilted across a step between two surfaces in the middle of a region agrees with 63 % of
# its ring (test). Our choice between the two: 65 % (70 % before; README: measured).
INLIER_SHARE = 0.65
SIDE_SHARE = 0.1  # least share of the agreeing pixels on each side of the region's centre
MIN_RING = 30  # fewest reliable ring pixels to fit from
HYPOTHESES = 128  # RANSAC planes tried per region
SCORE_ROWS = 2000  # ring pixels a hypothesis is scored on, at most
# The photometric check of a plane: the band of EDGE_PX around the region (the texture window's
# half: the surface's own edge) seen through the plane; a pixel mismatches beyond PHOTO_LEVELS
# grey levels (our choice: several times a camera's noise), and at most PHOTO_SHARE of them may
# (on the hold-out scenes' blank panels the planes kept showed 0-0.8 %, the wall's plane around a
# blank board 20 %).
EDGE_PX = 3
PHOTO_LEVELS = 12.0
PHOTO_SHARE = 0.05


def _ransac_plane(
    A: np.ndarray, d: np.ndarray, rng: np.random.Generator, tol: float
) -> tuple[np.ndarray, np.ndarray] | None:
    """(coefficients (3,), inlier mask (N,)) of the plane d = A @ coef most of the rows agree on,
    refitted by least squares on its inliers (a row agrees within `tol`); None without a
    well-posed triple."""
    picks = rng.integers(0, len(d), (HYPOTHESES, 3))  # a repeated row makes M singular
    M, y = A[picks], d[picks]  # (K, 3, 3), (K, 3)
    ok = np.abs(np.linalg.det(M)) > 1e-6
    if not ok.any():
        return None
    coefs = np.linalg.solve(M[ok], y[ok][..., None])[..., 0]  # (K', 3)
    # scored on at most SCORE_ROWS of the rows (an even subset): the share agreeing is the same
    step = max(1, len(d) // SCORE_ROWS)
    agree = np.abs(coefs @ A[::step].T - d[None, ::step]) < tol  # (K', N')
    best = coefs[np.argmax(agree.sum(axis=1))]
    inliers = np.abs(A @ best - d) < tol
    coef, *_ = np.linalg.lstsq(A[inliers], d[inliers], rcond=None)
    return coef, np.abs(A @ coef - d) < tol


def _photo_mismatch(
    left: np.ndarray, right: np.ndarray, pu: np.ndarray, pv: np.ndarray, plane: np.ndarray
) -> float:
    """Share of the pixels (pu, pv) of the left grey image whose colour differs by more than
    PHOTO_LEVELS from the right image at u - plane (linear interpolation; outside it: a mismatch)."""
    ur = pu.astype(np.float32) - plane
    u0 = np.floor(ur).astype(np.int64)
    inside = (u0 >= 0) & (u0 + 1 < right.shape[1])
    u0c = np.clip(u0, 0, right.shape[1] - 2)
    t = ur - u0c
    sample = (1 - t) * right[pv, u0c] + t * right[pv, u0c + 1]
    mismatch = ~inside | (np.abs(sample - left[pv, pu]) > PHOTO_LEVELS)
    return float(mismatch.mean())


def _blank_labels(
    texture: np.ndarray, texture_vertical: np.ndarray, blank_texture: float
) -> tuple[np.ndarray, np.ndarray]:
    """(labels (H, W) int32, stats) of the 4-connected blank regions: both texture factors below
    `blank_texture` (label 0: the rest)."""
    blank = ((texture < blank_texture) & (texture_vertical < blank_texture)).astype(np.uint8)
    _, labels, stats, _ = cv2.connectedComponentsWithStats(blank, connectivity=4)
    return labels, stats


def _large_regions(stats: np.ndarray, min_area_px: int) -> np.ndarray:
    """Labels of the blank regions of at least `min_area_px` pixels (never 0, the rest)."""
    large = np.flatnonzero(stats[:, cv2.CC_STAT_AREA] >= min_area_px)
    return large[large != 0]


def _open(stat: np.ndarray, w: int) -> bool:
    """Whether a region (its `connectedComponentsWithStats` row) reaches the image's top and one
    of its sides: above the horizon of an upright camera, where the scene may hold nothing (the
    sky; a far ceiling, a blank wall filling that corner). Nothing matched bounds it there, and
    a plane through the rest of its ring (a pole's edge, a horizontal edge that matches at any
    disparity) extrapolates. A blank floor or table in a bottom corner, near the camera, is
    matched along its far edge and its inner side and keeps its plane."""
    x, y, bw = (int(v) for v in stat[:3])
    return y == 0 and (x == 0 or x + bw == w)


def fill_blank_planes(
    disparity: np.ndarray,
    lr_diff: np.ndarray,
    texture: np.ndarray,
    texture_vertical: np.ndarray,
    left: np.ndarray,
    right: np.ndarray,
    blank_texture: float,
    min_area_px: int,
    downscale: int = 1,
    drop_refused: bool = False,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(disparity with blank regions filled (H, W) float32 px, NaN = invalid; support (H, W)
    float32 in [0, 1]: the share of its ring that agreed with the plane a filled pixel took, 0
    where nothing was filled; blank (H, W) bool: the pixels of the blank regions tried, both
    texture factors below `blank_texture` in 4-connected regions of at least `min_area_px`).

    disparity: (H, W) float32 px, NaN = invalid; lr_diff: (H, W) left-right difference, px;
    texture: (H, W) texture factor in [0, 1) (`stereo.texture_factor`, of horizontal gradients:
    what the matcher has to go on); texture_vertical: the same of vertical gradients. Blank means
    both below `blank_texture`: a grey panel's top edge against a dark sky, or horizontal stripes,
    have vertical texture, so neither joins two surfaces into one region nor passes for blank.
    left, right: (H, W) uint8 grey rectified pair, to check a plane against the images: the band
    of EDGE_PX around the region (its own edge) must look the same in the right image at u - d.
    downscale: the disparities were matched at 1 / downscale of the size and scaled up (the plane
    tolerance grows with it). drop_refused: a region no plane was kept for loses the matcher's
    values (NaN, no estimate): there they are whatever its smoothness term spread into the region.
    Seeded per region: the same input gives the same output, and a region's plane depends on
    its own ring only (not on which other regions were fitted before it).
    """
    h, w = disparity.shape
    labels, stats = _blank_labels(texture, texture_vertical, blank_texture)
    with np.errstate(invalid="ignore"):
        reliable = (lr_diff <= RELIABLE_LR_PX) & (texture >= RELIABLE_TEXTURE)
    reliable &= np.isfinite(disparity)
    out = disparity.copy()
    support = np.zeros((h, w), np.float32)
    large = _large_regions(stats, min_area_px)
    kernel = cv2.getStructuringElement(cv2.MORPH_RECT, (2 * RING_PX + 1, 2 * RING_PX + 1))
    edge_kernel = cv2.getStructuringElement(cv2.MORPH_RECT, (2 * EDGE_PX + 1, 2 * EDGE_PX + 1))
    left_f, right_f = left.astype(np.float32), right.astype(np.float32)
    for k in large:
        x, y, bw, bh = stats[k, :4]
        x0, y0 = max(x - RING_PX, 0), max(y - RING_PX, 0)
        x1, y1 = min(x + bw + RING_PX, w), min(y + bh + RING_PX, h)
        region = (labels[y0:y1, x0:x1] == k).astype(np.uint8)
        pv, pu = np.nonzero(region)
        if _open(stats[k], w):
            # above the horizon, unbounded on two sides: no plane, and no estimate
            out[pv + y0, pu + x0] = np.nan
            continue
        plane = _region_plane(
            region,
            (pu.mean(), pv.mean()),
            x0,
            y0,
            disparity,
            reliable,
            left_f,
            right_f,
            np.random.default_rng(0),
            kernel,
            edge_kernel,
            downscale,
        )
        if plane is None:
            if drop_refused:  # the matcher had nothing to go on there: no estimate
                out[pv + y0, pu + x0] = np.nan
            continue
        coef, share = plane
        values = (coef[0] * (pu + x0) + coef[1] * (pv + y0) + coef[2]).astype(np.float32)
        ahead = values > 0  # a plane through zero disparity is at infinity beyond that line
        if drop_refused:
            out[pv[~ahead] + y0, pu[~ahead] + x0] = np.nan
        pu, pv = pu[ahead] + x0, pv[ahead] + y0
        out[pv, pu] = values[ahead]
        support[pv, pu] = np.float32(share)
    return out, support, np.isin(labels, large)


def _region_plane(
    region: np.ndarray,
    centre: tuple[float, float],
    x0: int,
    y0: int,
    disparity: np.ndarray,
    reliable: np.ndarray,
    left_f: np.ndarray,
    right_f: np.ndarray,
    rng: np.random.Generator,
    kernel: np.ndarray,
    edge_kernel: np.ndarray,
    downscale: int,
) -> tuple[np.ndarray, float] | None:
    """(plane coefficients (3,) in full-size pixels, share of the ring on it) for one blank
    `region` (a uint8 mask of the window whose corner is (x0, y0); `centre` (u, v) the mean of its
    pixels in the window), or None when refused: too few reliable ring pixels, no plane most of
    them agree on, agreement not on all four sides, or the region's edge looks different through
    the plane in the right image."""
    h, w = region.shape
    ring = (cv2.dilate(region, kernel) > 0) & (region == 0) & reliable[y0 : y0 + h, x0 : x0 + w]
    rv, ru = np.nonzero(ring)
    if len(ru) < MIN_RING:
        return None
    A = np.stack([ru + x0, rv + y0, np.ones_like(ru)], axis=1).astype(np.float64)
    d = disparity[y0 : y0 + h, x0 : x0 + w][rv, ru].astype(np.float64)
    fit = _ransac_plane(A, d, rng, PLANE_TOL_PX * downscale)
    if fit is None or fit[1].mean() < INLIER_SHARE:
        return None
    coef, inliers = fit
    cu, cv = centre
    iu, iv = ru[inliers], rv[inliers]
    sides = ((iu < cu).mean(), (iu > cu).mean(), (iv < cv).mean(), (iv > cv).mean())
    if min(sides) < SIDE_SHARE:
        return None
    # The region's edge must look the same through the plane in both images: a blank board
    # before a textured wall has the wall's matches all around it, and the wall's plane would
    # move the board's edge onto the wall in the right image.
    ev, eu = np.nonzero((cv2.dilate(region, edge_kernel) > 0) & (region == 0))
    edge_plane = (coef[0] * (eu + x0) + coef[1] * (ev + y0) + coef[2]).astype(np.float32)
    if _photo_mismatch(left_f, right_f, eu + x0, ev + y0, edge_plane) > PHOTO_SHARE:
        return None
    return coef, float(inliers.mean())
