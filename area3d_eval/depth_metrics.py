"""Per-pixel depth error against ground truth, and how well a confidence map ranks it.

- abs_rel      |d - d*| / d* per pixel valid in both maps (d* the ground truth)
- median_abs_rel, share_off_5pct: the median of abs_rel and the share of pixels with abs_rel > 5 %
- density      share of the ground truth's valid pixels that have an estimate
- sparsification curve (Ilg et al., "Uncertainty Estimates and Multi-Hypotheses Networks for
  Optical Flow", ECCV 2018): remove the fraction f of pixels the confidence trusts least, report the
  mean error of the rest; the oracle removes the largest errors first. AUSE is the area between the
  two curves over f in [0, 1): 0 when confidence orders pixels exactly as their errors, larger the
  worse it ranks them. A random ordering gives a flat curve (its AUSE is the oracle curve's gap to
  the mean error).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from area3d_msgs_py.errors import InputError

# Fractions removed, 0 to 0.98 in steps of 0.02 (50 points, as is common for AUSE).
SPARSIFICATION_STEPS = 50
OFF_THRESHOLD = 0.05  # a pixel is "off" beyond 5 % relative error
# a depth is right within 1 cm + 1 % of the true depth (the stereo backend's calibration target)
RIGHT_ABS_M = 0.01
RIGHT_REL = 0.01


def depth_right(estimate: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """bool array: the estimate within RIGHT_ABS_M + RIGHT_REL x the true depth of it (metres;
    a NaN on either side is not right)."""
    truth = np.asarray(truth)
    with np.errstate(invalid="ignore"):
        return np.abs(np.asarray(estimate) - truth) <= RIGHT_ABS_M + RIGHT_REL * truth


@dataclass
class DepthErrors:
    """abs_rel: (N,) relative error of each pixel valid in both maps; confidence: (N,) the
    estimate's confidence at those pixels (None if not given); density: share of the ground
    truth's valid pixels that have an estimate."""

    abs_rel: np.ndarray
    confidence: np.ndarray | None
    density: float

    @property
    def median_abs_rel(self) -> float:
        return float(np.median(self.abs_rel)) if self.abs_rel.size else float("nan")

    @property
    def share_off(self) -> float:
        return float(np.mean(self.abs_rel > OFF_THRESHOLD)) if self.abs_rel.size else float("nan")


def depth_errors(
    estimate: np.ndarray, truth: np.ndarray, confidence: np.ndarray | None = None
) -> DepthErrors:
    """Errors of an (H, W) depth estimate against (H, W) ground truth, metres, NaN = missing."""
    estimate, truth = np.asarray(estimate, np.float64), np.asarray(truth, np.float64)
    if estimate.shape != truth.shape:
        raise InputError("estimate", f"shape {estimate.shape}", f"the truth's shape {truth.shape}")
    with np.errstate(invalid="ignore"):
        has_truth = np.isfinite(truth) & (truth > 0)
        both = has_truth & np.isfinite(estimate) & (estimate > 0)
    abs_rel = np.abs(estimate[both] - truth[both]) / truth[both]
    conf = None if confidence is None else np.asarray(confidence, np.float64)[both]
    density = float(both.sum() / has_truth.sum()) if has_truth.any() else float("nan")
    return DepthErrors(abs_rel, conf, density)


def sparsification_curve(
    errors: np.ndarray, order_key: np.ndarray, steps: int = SPARSIFICATION_STEPS
) -> np.ndarray:
    """(steps,) mean error left after removing the fraction k / steps of pixels with the lowest
    `order_key` (k = 0 .. steps - 1). errors, order_key: (N,) with N >= 1."""
    errors = np.asarray(errors, np.float64)
    if errors.size == 0:
        raise InputError("errors", "an empty array", "at least one pixel")
    kept_best_first = errors[np.argsort(-np.asarray(order_key, np.float64), kind="stable")]
    # mean of the first m entries for every m: one cumulative sum
    means = np.cumsum(kept_best_first) / np.arange(1, errors.size + 1)
    keep = np.maximum(1, np.round(errors.size * (1 - np.arange(steps) / steps)).astype(int))
    return means[keep - 1]


def ause(errors: np.ndarray, confidence: np.ndarray, steps: int = SPARSIFICATION_STEPS) -> float:
    """Area between the confidence's sparsification curve and the oracle's, over f in [0, 1)."""
    by_confidence = sparsification_curve(errors, confidence, steps)
    oracle = sparsification_curve(errors, -np.asarray(errors, np.float64), steps)
    return float(np.mean(by_confidence - oracle))
