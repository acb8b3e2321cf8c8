"""The `stereo` backend: depth estimated from a rectified image pair, with what stereo knows about it.

Semi-global matching (Hirschmueller 2008, OpenCV's `StereoSGBM`) gives the left image's disparity d
in pixels; depth is z = fx * B / d. Confidence in [0, 1] is the product of three factors and 0
where the match is invalid:

    consistency  exp(-(|d_L(x) - d_R(x - d_L(x))| / lr_sigma_px)^2), 0 beyond lr_max_diff_px:
                 the right image's own disparity (a second SGBM on the mirrored pair, since the
                 `ximgproc` right matcher is only in opencv-contrib) must point back to the pixel;
                 occluded pixels (seen by the left camera only) and mismatches fail it
    texture      g^2 / (g^2 + texture_ref^2), g = RMS horizontal image gradient in a window: along
                 the epipolar line a blank (or horizontally striped) surface gives the matcher
                 nothing to lock on, and its match is decided by the smoothness term

Invalid means: SGBM found no unique minimum (`uniquenessRatio`), the speckle filter removed the
region, the pixel is in the left band where the full disparity range leaves the right image, or the
depth is beyond `max_range`.

Blank regions whose surroundings agree on a plane take that plane, at a low confidence of their own
(`blank_fill.py`, `blank_fill*` parameters).

Arrays in, arrays out; no ROS here.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import cv2
import numpy as np

from area3d_msgs_py.camera import PAPER_MAX_RANGE
from area3d_msgs_py.errors import InputError
from area3d_msgs_py.param_fields import described
from area3d_perception.blank_fill import fill_blank_planes
from area3d_perception.disparity import (
    disparity_neighbourhood,
    lr_difference,
    refine_disparity,
)

# OpenCV's StereoSGBM returns fixed-point disparities with 4 fractional bits.
SGBM_DISPARITY_SCALE = 16.0
SGBM_MODES = {
    "sgbm": cv2.STEREO_SGBM_MODE_SGBM,
    "3way": cv2.STEREO_SGBM_MODE_SGBM_3WAY,
    "hh": cv2.STEREO_SGBM_MODE_HH,
}


CONFIDENCE_MODELS = ("matcher", "calibrated")
CALIBRATION_WINDOW_PX = 5
# Weights of the calibrated confidence, fitted (logistic regression) to the simulator's 640 x 480,
# 90 degree, 6 cm pairs (read noise 1 grey level) of the initial and held-out views of the four
# bundled object scenes, matched with the defaults (downscale 1, refined) by `area3d bench
# stereo-confidence`, which prints them. Another camera, or other matcher settings, need their own.
CALIBRATION = (1.383, -1.868, 4.578, -6.200)


FOUR_FINITE = "four finite numbers"


def _four_finite(value) -> str | None:
    """None if `value` is four finite numbers, else what was expected."""
    try:
        v = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        return FOUR_FINITE
    return None if v.shape == (4,) and np.all(np.isfinite(v)) else FOUR_FINITE


@dataclass(frozen=True)
class StereoParams:
    """Tunables of the stereo backend (every one is a `stereo.*` node parameter)."""

    # Disparities searched at the matching resolution: 96 at full size covers depths from
    # fx B / 96 = 0.2 m at fx = 320 px (90 deg over 640 px), B = 6 cm; the planner's nearest views
    # are about 0.3 m from surfaces. The left band of this width has no match.
    num_disparities: int = described(
        96, "disparities searched at the matching resolution (a multiple of 16)", "pixels",
        (16, 1024),
    )  # fmt: skip
    block_size: int = described(5, "SGBM block size, odd (OpenCV: 3-11)", "pixels", (1, 63))
    # OpenCV's variants of semi-global matching (`StereoSGBM` modes SGBM, SGBM_3WAY, HH). On the
    # simulator's pairs "3way" puts 1.5-2x as many pixels within 1 cm of the true depth as "sgbm",
    # in less time (README: measured figures).
    mode: str = described(
        "3way", "OpenCV's semi-global matching variant", choices=tuple(SGBM_MODES)
    )
    # Smoothness penalties P1 = 8 * bs^2, P2 = 32 * bs^2 per channel (OpenCV's sample values).
    p1_per_px: int = described(
        8, "SGBM smoothness penalty P1 = p1_per_px block_size^2 per channel", "", (0, 1024)
    )
    p2_per_px: int = described(
        32, "SGBM smoothness penalty P2 = p2_per_px block_size^2 per channel", "", (1, 4096)
    )
    uniqueness_ratio: int = described(
        10, "SGBM uniqueness margin (OpenCV suggests 5-15)", "percent", (0, 100)
    )
    speckle_window_size: int = described(
        100, "SGBM speckle filter window (OpenCV suggests 50-200)", "pixels", (0, 10_000)
    )
    speckle_range: int = described(
        2, "SGBM speckle filter range (OpenCV suggests 1-2)", "pixels of disparity", (0, 64)
    )
    # at the matching resolution; our choice: a disagreement beyond one pixel is a mismatch, and
    # half a pixel gives exp(-1)
    lr_max_diff_px: float = described(
        1.0, "left-right check: a disagreement beyond this is a mismatch", "pixels", (1e-3, 64.0)
    )
    lr_sigma_px: float = described(
        0.5, "left-right check: a disagreement of this much gives confidence exp(-1)", "pixels",
        (1e-3, 64.0),
    )  # fmt: skip
    # A match the check refuses, or cannot make (the right image's match is missing), gets
    # confidence and weight 0; its depth stays unless this is true. That depth is right less often
    # than the others (on shelf_wall 5-70 % within 1 cm + 1 % per view, against 59-97 %) and the
    # planner takes it for a surface and carves free space along its ray. true: no estimate there.
    # Off by default: the planner's views got worse with it on the thin_objects hold-out (README).
    lr_drop_refused: bool = described(
        False, "a match the left-right check refuses gets no depth (false: depth at confidence 0)"
    )
    texture_window_px: int = described(
        7, "window of the texture measure (about the SGBM block plus a margin)", "pixels", (1, 101)
    )
    # grey levels / px: RMS horizontal gradient where texture gives 0.5 (our choice: 1 grey level of
    # camera noise alone gives 0.43, so a blank surface stays below 0.16; on the simulator's
    # noise-free images larger values rank error worse, see the README)
    texture_ref: float = described(
        1.0, "RMS horizontal gradient at which texture confidence is 0.5",
        "grey levels per pixel", (1e-3, 255.0),
    )  # fmt: skip
    # SGBM's sub-pixel error on textured surfaces (pixel locking) at the matching resolution, px;
    # measured on generated planes
    disparity_sigma_px: float = described(
        0.25, "SGBM's sub-pixel disparity error on textured surfaces (measured)", "pixels",
        (1e-3, 64.0),
    )  # fmt: skip
    # One Gauss-Newton step on the image after SGBM (`refine_disparity`): SGBM's sub-pixel estimate
    # (a parabola through three aggregated costs) is pulled towards whole disparities, 0.25 px at
    # the matching size, 1-2 cm at 1.2 m. Our choices: a 7 px window (the texture window), no step
    # where the window's RMS gradient is below 0.7 grey levels per pixel (one grey level of
    # camera noise gives 0.43) or where its disparities spread over more than 0.5 px (a window
    # across two surfaces), at most 1 px.
    refine: bool = described(True, "refine each match's sub-pixel disparity on the images")
    refine_window_px: int = described(7, "window of the sub-pixel refinement", "pixels", (3, 31))
    refine_min_gradient: float = described(
        0.7, "least RMS horizontal gradient in the window for a refinement step",
        "grey levels per pixel", (0.0, 255.0),
    )  # fmt: skip
    refine_max_spread_px: float = described(
        0.5, "no refinement where the window's disparities spread more than this", "pixels",
        (0.0, 64.0),
    )  # fmt: skip
    precision_rel_ref: float = described(
        0.05, "relative depth error that halves confidence", "fraction", (1e-4, 10.0)
    )
    # Match at 1 / downscale of the resolution (2: four times fewer pixels, and the disparities
    # cover twice the range, for half the disparity precision); depth and confidence come back at
    # full size. 1: the reconstruction's completion at 1 cm needs full-size disparities (README:
    # measured figures); 2 quarters the time.
    downscale: int = described(
        1, "match at 1 / downscale of the image size (1, 2 or 4)", "", (1, 4)
    )
    max_range: float = described(
        PAPER_MAX_RANGE,
        "depths beyond this are no match (the paper's camera)",
        "metres",
        (0.01, 1000.0),
    )
    # Blank surfaces (`blank_fill.py`): a plane through the reliable matches around each blank
    # region. Our choices: blank = texture factor below 0.3 across and along the rows (a noise-free
    # blank patch gives 0, one grey level of camera noise 0.16); regions of at least 300 px (0.1 %
    # of 640 x 480); confidence 0.2, so that a matched view of the surface outweighs the plane.
    blank_fill: bool = described(
        True, "fill blank regions with the plane their matched surroundings agree on"
    )
    blank_texture: float = described(
        0.3, "texture factor below which a pixel is blank", "fraction", (0.0, 1.0)
    )
    blank_min_area_px: int = described(
        300, "smallest blank region filled (full-size pixels)", "pixels", (1, 10_000_000)
    )
    # A blank region the fill refuses: the matcher's values there are what its smoothness term
    # spread into the region (on the thin_objects hold-out's screen seen before the checkered
    # floor, the floor's disparity: 2-58 % of such pixels within 2 cm), and a depth there carves
    # free space through the surface. true: no estimate there (unknown, not empty). Off by
    # default: on the blank surfaces the evaluation renders, a wrong depth drawn in the surface's
    # one colour scores better than a hole (README: measured).
    blank_drop_refused: bool = described(
        False, "a blank region the fill refuses gets no estimate (false: the matcher's values stay)"
    )
    blank_fill_confidence: float = described(
        0.2, "confidence of a filled pixel (times the share of its ring on the plane)", "fraction",
        (0.0, 1.0),
    )  # fmt: skip
    # "matcher": the product of the matcher's factors above (consistency x precision x texture).
    # "calibrated": the chance that the depth is within 1 cm + 1 % of the truth, a logistic model of
    # the disparity, its spread and the share of valid pixels around it (`calibrated_confidence`),
    # with `calibration` fitted to rendered pairs of the camera (`area3d bench stereo-confidence`).
    confidence_model: str = described(
        "calibrated", "what a pixel's confidence says", choices=CONFIDENCE_MODELS
    )
    calibration: tuple = described(
        CALIBRATION,
        "calibrated model: weights of ln disparity, ln(1 + disparity spread), valid share, bias",
        check=_four_finite,
    )

    def validate(self) -> None:
        """Raise InputError naming the first parameter outside its domain."""
        checks = (
            ("num_disparities", self.num_disparities > 0 and self.num_disparities % 16 == 0,
             "a positive multiple of 16 (pixels)"),
            ("block_size", self.block_size >= 1 and self.block_size % 2 == 1,
             "an odd number of pixels >= 1"),
            ("mode", self.mode in SGBM_MODES, f"one of {sorted(SGBM_MODES)}"),
            ("p1_per_px", 0 <= self.p1_per_px < self.p2_per_px, "0 <= p1_per_px < p2_per_px"),
            ("uniqueness_ratio", 0 <= self.uniqueness_ratio <= 100, "a percentage in [0, 100]"),
            ("speckle_window_size", self.speckle_window_size >= 0, "pixels >= 0"),
            ("speckle_range", self.speckle_range >= 0, "pixels of disparity >= 0"),
            ("lr_max_diff_px", self.lr_max_diff_px > 0, "pixels > 0"),
            ("lr_sigma_px", self.lr_sigma_px > 0, "pixels > 0"),
            ("texture_window_px", self.texture_window_px >= 1, "pixels >= 1"),
            ("texture_ref", self.texture_ref > 0, "grey levels per pixel > 0"),
            ("disparity_sigma_px", self.disparity_sigma_px > 0, "pixels > 0"),
            ("refine_window_px", self.refine_window_px >= 3 and self.refine_window_px % 2 == 1,
             "an odd number of pixels >= 3"),
            ("refine_min_gradient", self.refine_min_gradient >= 0, "grey levels per pixel >= 0"),
            ("refine_max_spread_px", self.refine_max_spread_px >= 0, "pixels >= 0"),
            ("precision_rel_ref", self.precision_rel_ref > 0, "a relative error > 0"),
            ("downscale", self.downscale in (1, 2, 4), "1, 2 or 4"),
            ("max_range", self.max_range > 0, "metres > 0"),
            ("blank_texture", 0 <= self.blank_texture <= 1, "a texture factor in [0, 1]"),
            ("blank_min_area_px", self.blank_min_area_px >= 1, "pixels >= 1"),
            ("blank_fill_confidence", 0 <= self.blank_fill_confidence <= 1, "a value in [0, 1]"),
            ("confidence_model", self.confidence_model in CONFIDENCE_MODELS,
             f"one of {', '.join(CONFIDENCE_MODELS)}"),
            ("calibration", _four_finite(self.calibration) is None, FOUR_FINITE),
        )  # fmt: skip
        for name, ok, expected in checks:
            if not ok:
                raise InputError(f"stereo.{name}", getattr(self, name), expected)


@dataclass
class StereoResult:
    """depth (H, W) float32 metres, NaN = no valid match; confidence (H, W) float32 in [0, 1], 0
    where depth is NaN (`confidence_model`); disparity (H, W) float32 full-resolution px of the
    left image, NaN = invalid; weight (H, W) float32 in [0, 1], what a reconstruction integrates
    the depth with: the matcher's confidence whatever `confidence_model` (the TSDF's least weight
    is set for it; the calibrated model's weights let false matches into the surface)."""

    depth: np.ndarray
    confidence: np.ndarray
    disparity: np.ndarray
    weight: np.ndarray


def check_stereo_pair(
    left: np.ndarray | None, right: np.ndarray | None, baseline: float | None
) -> None:
    """Reject a pair that cannot be matched (raises InputError naming the field).

    left, right: (H, W, 3) uint8 rgb or (H, W) uint8 grey of the same size; baseline: metres > 0.
    """
    if right is None:
        raise InputError("right", None, "the right image of the stereo pair")
    if left is None:
        raise InputError("color", None, "the left (colour) image of the stereo pair")
    for name, image in (("color", left), ("right", right)):
        image = np.asarray(image)
        if image.dtype != np.uint8 or not (
            image.ndim == 2 or (image.ndim == 3 and image.shape[2] == 3)
        ):
            raise InputError(
                name, f"{image.dtype} {image.shape}", "an (H, W, 3) or (H, W) uint8 image"
            )
    if np.asarray(left).shape[:2] != np.asarray(right).shape[:2]:
        h, w = np.asarray(left).shape[:2]
        rh, rw = np.asarray(right).shape[:2]
        raise InputError("right", f"size {rw}x{rh}", f"the left image's size {w}x{h}")
    if baseline is None or not (np.isfinite(baseline) and baseline > 0):
        raise InputError(
            "baseline", baseline, "metres > 0 (from the right camera_info, P[3] = -fx B)"
        )


def _grey(image: np.ndarray) -> np.ndarray:
    image = np.asarray(image)
    return cv2.cvtColor(image, cv2.COLOR_RGB2GRAY) if image.ndim == 3 else image


def texture_factor(grey: np.ndarray, window_px: int, texture_ref: float) -> np.ndarray:
    """(H, W) float32 in [0, 1): g^2 / (g^2 + ref^2), g = RMS horizontal Sobel gradient over a
    window (grey levels per pixel). A uniform patch gives 0, strong texture approaches 1."""
    g = grey.astype(np.float32)
    gx = cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3) / 8.0  # Sobel's gain is 8: back to levels/px
    energy = cv2.boxFilter(gx * gx, -1, (window_px, window_px))
    return (energy / (energy + np.float32(texture_ref) ** 2)).astype(np.float32)


def calibration_features(disparity: np.ndarray, downscale: int = 1) -> np.ndarray:
    """(H, W, 3) float32 features of the calibrated confidence: ln d, ln(1 + s) and v, d the
    disparity and s its spread in pixels of the matching size (d at least 0.5), v the share of
    valid pixels in the CALIBRATION_WINDOW_PX window around the pixel."""
    spread, share = disparity_neighbourhood(disparity, CALIBRATION_WINDOW_PX)
    scale = np.float32(downscale)
    with np.errstate(invalid="ignore"):
        d = np.maximum(np.nan_to_num(disparity, nan=0.0) / scale, np.float32(0.5))
    return np.stack([np.log(d), np.log1p(spread / scale), share], axis=-1).astype(np.float32)


def calibrated_confidence(
    disparity: np.ndarray, calibration: tuple, downscale: int = 1
) -> np.ndarray:
    """(H, W) float32 chance that each valid pixel's depth is within 1 cm + 1 % of the truth:
    sigmoid(w . features + b) (`calibration_features`: the disparity carries the range, relative
    depth error ~ disparity error / d; its spread and the share of valid pixels around it the
    local consistency of the match: an isolated match in a field of failures is rarely right);
    0 where the disparity is invalid."""
    p = confidence_of_features(calibration_features(disparity, downscale), calibration)
    p[~np.isfinite(disparity)] = 0.0
    return p


def confidence_of_features(features: np.ndarray, calibration: tuple) -> np.ndarray:
    """(...) float32 sigmoid(w . features + b) of (..., 3) `calibration_features` and the model's
    `calibration` (w_1, w_2, w_3, b)."""
    w = np.asarray(calibration[:3], np.float32)
    z = np.asarray(features, np.float32) @ w + np.float32(calibration[3])
    with np.errstate(over="ignore"):  # exp overflows to inf for z << 0: the chance is 0
        return (1.0 / (1.0 + np.exp(-z))).astype(np.float32)


class StereoMatcher:
    """SGBM on a rectified pair -> depth + confidence. Holds the two OpenCV matchers (left and the
    mirrored right one) and runs them side by side on two threads (OpenCV releases the GIL)."""

    def __init__(self, params: StereoParams | None = None) -> None:
        self.params = params or StereoParams()
        self.params.validate()
        self._left = self._sgbm()
        self._right = self._sgbm()
        self._pool = ThreadPoolExecutor(max_workers=2, thread_name_prefix="sgbm")

    def _sgbm(self) -> cv2.StereoSGBM:
        p = self.params
        area = p.block_size * p.block_size
        return cv2.StereoSGBM_create(
            minDisparity=0,
            numDisparities=p.num_disparities,
            blockSize=p.block_size,
            P1=p.p1_per_px * area,
            P2=p.p2_per_px * area,
            disp12MaxDiff=-1,  # the consistency check is ours, with a graded result
            uniquenessRatio=p.uniqueness_ratio,
            speckleWindowSize=p.speckle_window_size,
            speckleRange=p.speckle_range,
            mode=SGBM_MODES[p.mode],
        )

    def disparities(
        self, left_grey: np.ndarray, right_grey: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """(left, right) disparity (H, W) float32 px, NaN = invalid. The right one comes from
        matching the mirrored pair, in which the right image plays the left image's part."""
        mirrored = (
            np.ascontiguousarray(right_grey[:, ::-1]),
            np.ascontiguousarray(left_grey[:, ::-1]),
        )
        job_left = self._pool.submit(self._left.compute, left_grey, right_grey)
        job_right = self._pool.submit(self._right.compute, *mirrored)
        return _to_px(job_left.result()), _to_px(job_right.result()[:, ::-1])

    def match(
        self, left: np.ndarray, right: np.ndarray, fx: float, baseline: float
    ) -> StereoResult:
        """Depth and confidence of the left image.

        left, right: (H, W, 3) uint8 rgb or (H, W) uint8 grey, rectified (rows are epipolar lines,
        the right camera B metres along the left's optical x axis). fx: pixels. baseline: metres.
        """
        check_stereo_pair(left, right, baseline)
        if not (np.isfinite(fx) and fx > 0):
            raise InputError("fx", fx, "a focal length in pixels > 0")
        p = self.params
        left_grey, right_grey = _grey(left), _grey(right)
        disp_left, diff = self._matched(left_grey, right_grey)
        texture = texture_factor(left_grey, p.texture_window_px, p.texture_ref)
        support = np.zeros_like(texture)
        if p.blank_fill:
            vertical = texture_factor(left_grey.T, p.texture_window_px, p.texture_ref).T
            disp_left, support, blank = fill_blank_planes(
                disp_left,
                diff,
                texture,
                vertical,
                left_grey,
                right_grey,
                p.blank_texture,
                p.blank_min_area_px,
                p.downscale,
                p.blank_drop_refused,
            )
        filled = support > 0
        with np.errstate(divide="ignore", invalid="ignore"):
            depth = np.float32(fx * baseline) / disp_left
            # also drops d = 0 (inf), NaN and a depth <= 0 (none leaves the backend)
            depth[~((depth > 0) & (depth <= p.max_range))] = np.nan
            if p.lr_drop_refused:
                depth[~((diff <= p.lr_max_diff_px) | filled)] = np.nan
        weight = self._matcher_confidence(disp_left, diff, texture, filled, support)
        weight[~np.isfinite(depth)] = 0.0
        weight = weight.astype(np.float32)
        if p.confidence_model == "calibrated":
            confidence = calibrated_confidence(disp_left, p.calibration, p.downscale)  # float32
            # fitted on the pixels that pass the left-right check (or are filled): a pixel that
            # fails it is no estimate, as with the matcher's confidence
            with np.errstate(invalid="ignore"):
                confidence[~((diff <= p.lr_max_diff_px) | filled)] = 0.0
            confidence[~np.isfinite(depth)] = 0.0
        else:
            confidence = weight.copy()
        if p.blank_fill:
            # a blank region the fill refused: the matcher had nothing to go on there, so its
            # depth (the smoothness term's spread, kept for the reconstruction at its weight) is
            # no measurement: confidence 0, whatever the calibrated model makes of its smoothness
            confidence[blank & ~filled] = 0.0
        return StereoResult(depth.astype(np.float32), confidence, disp_left, weight)

    def _matcher_confidence(
        self,
        disp_left: np.ndarray,
        diff: np.ndarray,
        texture: np.ndarray,
        filled: np.ndarray,
        support: np.ndarray,
    ) -> np.ndarray:
        """consistency x precision x texture per pixel; a filled pixel's matcher evidence is void:
        its confidence is the fill's own (blank_fill_confidence x support x precision)."""
        p = self.params
        with np.errstate(divide="ignore", invalid="ignore"):
            consistency = np.exp(-((diff / np.float32(p.lr_sigma_px)) ** 2))
            consistency[~(diff <= p.lr_max_diff_px)] = 0.0
            sigma_px = p.disparity_sigma_px * p.downscale  # in full-size pixels
            relative_sigma = np.float32(sigma_px / p.precision_rel_ref) / disp_left
            precision = 1.0 / (1.0 + relative_sigma**2)
        confidence = consistency * precision * texture
        confidence[filled] = (np.float32(p.blank_fill_confidence) * support * precision)[filled]
        return confidence

    def _matched(
        self, left_grey: np.ndarray, right_grey: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """(left disparity in full-size px, refined on the full-size images when `refine`;
        left-right difference in px of the matching size, of SGBM's disparities), both (H, W)
        float32: a one-pixel disagreement means the same at any `downscale`."""
        disp_left, diff = self._sgbm_matched(left_grey, right_grey)
        p = self.params
        if p.refine:
            disp_left = refine_disparity(
                disp_left, left_grey, right_grey, p.refine_window_px, p.refine_min_gradient,
                p.refine_max_spread_px,
            )  # fmt: skip
        return disp_left, diff

    def _sgbm_matched(
        self, left_grey: np.ndarray, right_grey: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """`_matched` before the refinement: SGBM's disparities and their left-right check."""
        s = self.params.downscale
        if s == 1:
            disp_left, disp_right = self.disparities(left_grey, right_grey)
            return disp_left, lr_difference(disp_left, disp_right)
        h, w = left_grey.shape
        small = [
            cv2.resize(g, (w // s, h // s), interpolation=cv2.INTER_AREA)
            for g in (left_grey, right_grey)
        ]
        disp_left, disp_right = self.disparities(*small)
        diff = lr_difference(disp_left, disp_right)
        # nearest, so no disparity is invented between two surfaces at an occlusion edge
        size = (w, h)
        return (
            cv2.resize(disp_left * np.float32(s), size, interpolation=cv2.INTER_NEAREST),
            cv2.resize(diff, size, interpolation=cv2.INTER_NEAREST),
        )

    def close(self) -> None:
        self._pool.shutdown(wait=False)


def _to_px(raw: np.ndarray) -> np.ndarray:
    # SGBM marks invalid pixels with (minDisparity - 1) * 16 = -16; d = 0 is "at infinity".
    disp = raw.astype(np.float32) / np.float32(SGBM_DISPARITY_SCALE)
    disp[raw < 0] = np.nan
    return disp
