"""One captured frame in, metric depth and per-pixel confidence in [0, 1] out, for any backend.

Backends:
    rgbd              sensor depth + `rgbd_confidence`
    uniform           sensor depth, confidence 1 on every valid pixel (the "w/o feed-forward" ablation)
    stereo            depth matched from a rectified pair (left = the colour image) + stereo confidence
    vggt              VGGT depth + confidence over a sliding window of recent views, scaled to metres
    depth_anything_3  the same with Depth Anything 3

This is the pure core of the perception node: no transport, arrays in and out. It never alters the
depth it is given (a real camera's noise is in its depth already; the simulated camera adds its own,
`sim_bridge.camera`): invalid values become NaN, and depth beyond the sensor's range is cut.

Its depth follows REP 117: NaN = no estimate (unknown: the planner carves nothing through it),
+Inf = no return within range, measured (free space up to the sensor's range). Only a depth
camera measures that (`no_return`: which of its pixels without a return are taken as such); a
stereo match or a feed-forward model that fails on a pixel says nothing about the space behind it.
"""

from __future__ import annotations

import dataclasses
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field

import cv2
import numpy as np

from area3d_msgs_py.depth_sensor import RgbdSensorParams
from area3d_msgs_py.errors import InputError
from area3d_msgs_py.lens import Remap
from area3d_perception.feedforward import (
    DepthAnything3Backend,
    FeedForwardOutput,
    VggtBackend,
    align_depth_median,
    align_scale_to_poses,
    normalize_confidence,
)
from area3d_perception.sensor_model import rgbd_confidence
from area3d_perception.stereo import StereoMatcher, StereoParams

BACKENDS = ("rgbd", "vggt", "depth_anything_3", "uniform", "stereo")
# Which of a depth camera's pixels without a return are a return beyond its range (+Inf): those
# in regions of no return (farther than NO_RETURN_REGION_PX from any return: sky, open space
# beyond range; an isolated dropout of a dark, specular or grazing surface is not), all or none.
NO_RETURN_RULES = ("none", "regions", "all")
NO_RETURN_REGION_PX = 6
# A frame with returns in fewer of its pixels than this is the camera failing (all zeros, all
# saturated: a driver fault, the emitter off), not open space: none of it is declared a return
# beyond range, which would carve free space through the whole map in front of it.
MIN_RETURN_SHARE = 0.01
FEEDFORWARD_BACKENDS = ("vggt", "depth_anything_3")
# Views per feed-forward pass: the new frame plus up to 7 recent ones (our choice; VGGT is
# multi-view and its depth improves with context, while memory and time grow with the window).
FEEDFORWARD_WINDOW = 8
# Fewer valid metric pixels than this and the median alignment falls back to the poses.
MIN_ALIGNMENT_PIXELS = 100


@dataclass
class FrameResult:
    """depth: (H, W) float32 metres, NaN = no estimate, +Inf = no return within range (REP 117);
    confidence: (H, W) float32 in [0, 1], 0 where depth is not finite (what the planner and the
    semantics read); notes: human-readable warnings about this frame (bad input, fallbacks);
    weight: (H, W) float32 in [0, 1], what a reconstruction integrates the depth with (`process`
    sets it to the confidence unless the backend has a weight of its own: stereo)."""

    depth: np.ndarray
    confidence: np.ndarray
    notes: list[str] = field(default_factory=list)
    weight: np.ndarray | None = None


def sanitize_depth(depth: np.ndarray, field_name: str = "depth") -> tuple[np.ndarray, list[str]]:
    """Depth with every unusable value set to NaN, and a note per kind of bad value found.

    REP 117's values are kept silently: NaN (no return), +Inf (no return within range) and -Inf
    (nearer than the camera measures); finite values <= 0 are not a depth and are reported with
    their count. Returns (depth (H, W) float32, notes).
    """
    d = np.array(depth, dtype=np.float32, copy=True)
    notes = []
    with np.errstate(invalid="ignore"):
        nonpos = np.isfinite(d) & (d <= 0)
    n_nonpos = int(nonpos.sum())
    if n_nonpos:
        notes.append(f"{field_name}: {n_nonpos} values <= 0 set to missing (NaN)")
        d[nonpos] = np.nan
    return d, notes


def declare_no_return(depth: np.ndarray, rule: str) -> np.ndarray:
    """`depth` (changed in place and returned) with the pixels without a return (NaN) that `rule`
    (one of NO_RETURN_RULES) takes as a return beyond range set to +Inf."""
    missing = np.isnan(depth)
    if rule == "none" or not missing.any():
        return depth
    if rule == "regions":
        size = 2 * NO_RETURN_REGION_PX + 1
        returns = np.isfinite(depth).astype(np.uint8)  # surfaces measured
        missing &= cv2.dilate(returns, np.ones((size, size), np.uint8)) == 0
    depth[missing] = np.inf
    return depth


def check_frame(
    rgb: np.ndarray | None, depth: np.ndarray | None, info_size: tuple[int, int] | None
) -> None:
    """Reject a frame whose parts do not fit together (raises InputError naming the field).

    rgb: (H, W, 3) uint8 or None; depth: (H, W) float or None; info_size: (width, height) of the
    camera info, or None.
    """
    if depth is not None:
        depth = np.asarray(depth)
        if depth.ndim != 2:
            raise InputError("depth", f"shape {depth.shape}", "an (H, W) image")
    if rgb is not None:
        rgb = np.asarray(rgb)
        if rgb.ndim != 3 or rgb.shape[2] != 3:
            raise InputError("color", f"shape {rgb.shape}", "an (H, W, 3) image")
        if depth is not None and rgb.shape[:2] != depth.shape:
            raise InputError(
                "color",
                f"size {rgb.shape[1]}x{rgb.shape[0]}",
                f"the depth size {depth.shape[1]}x{depth.shape[0]}",
            )
    image = depth if depth is not None else rgb
    if image is None:
        raise InputError("depth/color", None, "at least one image")
    if info_size is not None and tuple(info_size) != (image.shape[1], image.shape[0]):
        raise InputError(
            "camera_info",
            f"size {info_size[0]}x{info_size[1]}",
            f"the image size {image.shape[1]}x{image.shape[0]}",
        )


class FrameEstimator:
    """Per-frame depth + confidence with one of `BACKENDS`.

    sensor: confidence model of the depth camera (rgbd backend) and its range (every backend).
    checkpoint/device: feed-forward weights (file for vggt, directory for depth_anything_3).
    window: views per feed-forward pass. confidence_normalization: see `normalize_confidence`.
    model_factory: builds the feed-forward model (defaults to the real backends; tests inject one).
    stereo: matcher settings of the stereo backend.
    no_return: which of a depth camera's pixels without a return are a return beyond its range
    (`declare_no_return`; the depth camera backends only).
    uniform_confidence: replace every backend's confidence by 1 on each valid pixel (the paper's
    "w/o feed-forward" ablation, on the depth that backend estimates).
    """

    def __init__(
        self,
        backend: str = "rgbd",
        sensor: RgbdSensorParams | None = None,
        checkpoint: str = "",
        device: str = "auto",
        window: int = FEEDFORWARD_WINDOW,
        confidence_normalization: str = "inverse",
        model_factory: Callable[[str, str], object] | None = None,
        stereo: StereoParams | None = None,
        uniform_confidence: bool = False,
        no_return: str = "regions",
    ) -> None:
        if backend not in BACKENDS:
            raise InputError("backend", backend, f"one of {', '.join(BACKENDS)}")
        if no_return not in NO_RETURN_RULES:
            raise InputError("no_return", no_return, f"one of {', '.join(NO_RETURN_RULES)}")
        self.no_return = no_return
        if int(window) != window or window < 1:
            raise InputError("window", window, "an integer >= 1")
        normalize_confidence(np.ones((1, 1)), confidence_normalization)  # validates the name
        self.backend = backend
        self.uniform_confidence = bool(uniform_confidence)
        self.sensor = sensor or RgbdSensorParams()
        self.window = int(window)
        self.confidence_normalization = confidence_normalization
        self.model = None
        self._history: deque[tuple[np.ndarray, np.ndarray]] = deque(maxlen=self.window - 1)
        self.matcher = None
        if backend == "stereo":
            self.matcher = StereoMatcher(
                dataclasses.replace(stereo or StereoParams(), max_range=self.sensor.max_range)
            )
        if backend in FEEDFORWARD_BACKENDS:
            factory = model_factory or _default_model_factory(backend)
            self.model = factory(checkpoint, device)

    def process(
        self,
        rgb: np.ndarray | None,
        depth: np.ndarray | None,
        K: np.ndarray,
        T_world_cam: np.ndarray,
        right: np.ndarray | None = None,
        baseline: float | None = None,
    ) -> FrameResult:
        """Depth and confidence of one frame.

        rgb: (H, W, 3) uint8 (needed by feed-forward and stereo backends; the left image of a
        stereo pair). depth: (H, W) float32 metres from the sensor, NaN = no return, +Inf = none
        within range (needed by rgbd/uniform; optional for feed-forward, which then scales by the
        poses; not used by stereo). K: (3, 3). T_world_cam: (4, 4) optical-frame pose. right: (H, W, 3) uint8 right
        image of the rectified pair and baseline: metres, both for the stereo backend only.
        """
        result = self._estimate(rgb, depth, K, T_world_cam, right, baseline)
        if self.uniform_confidence:  # the reconstruction's weight too (the ablation as measured)
            # every estimate the backend keeps weighs 1; one it refuses (confidence 0: a match
            # that failed the left-right check) stays refused
            kept = np.isfinite(result.depth) & (result.confidence > 0)
            result.confidence = kept.astype(np.float32)
            result.weight = None
        if result.weight is None:
            result.weight = result.confidence
        return result

    def _estimate(
        self,
        rgb: np.ndarray | None,
        depth: np.ndarray | None,
        K: np.ndarray,
        T_world_cam: np.ndarray,
        right: np.ndarray | None,
        baseline: float | None,
    ) -> FrameResult:
        check_frame(rgb, depth, None)
        if self.matcher is not None:
            stereo = self.matcher.match(rgb, right, float(K[0, 0]), baseline)
            return FrameResult(stereo.depth, stereo.confidence, [], stereo.weight)
        notes: list[str] = []
        metric = None
        if depth is not None:
            metric, notes = sanitize_depth(depth)
        if self.backend in FEEDFORWARD_BACKENDS:
            if metric is not None:  # the scale comes from the measured depth only
                metric[np.isinf(metric)] = np.nan
            if rgb is None:
                raise InputError("color", None, f"an rgb image for the {self.backend} backend")
            return self._feedforward(
                np.asarray(rgb), metric, np.asarray(T_world_cam, dtype=np.float64), notes
            )
        if metric is None:
            raise InputError("depth", None, f"a depth image for the {self.backend} backend")
        finite = np.isfinite(metric)
        metric[finite & (metric > self.sensor.max_range)] = np.nan
        metric[finite & (metric < self.sensor.min_range)] = -np.inf  # nearer than it measures
        returned = float(np.mean(np.isfinite(metric) | np.isneginf(metric)))
        if self.no_return != "none" and returned < MIN_RETURN_SHARE:
            notes.append(
                f"depth: a return in {100 * returned:.2g} % of the pixels (below "
                f"{100 * MIN_RETURN_SHARE:g} %): a blank or saturated frame, taken as the camera "
                "failing, not as open space: no pixel of it declared beyond range"
            )
        else:
            declare_no_return(metric, self.no_return)  # of the pixels without a return only
        metric[np.isneginf(metric)] = np.nan  # too near: no estimate
        if self.backend == "uniform":
            confidence = np.isfinite(metric).astype(np.float32)
        else:
            confidence = rgbd_confidence(metric, K, self.sensor)
        return FrameResult(metric, confidence, notes)

    def _feedforward(
        self, rgb: np.ndarray, metric: np.ndarray | None, T: np.ndarray, notes: list[str]
    ) -> FrameResult:
        views = [*self._history, (rgb, T)]
        out: FeedForwardOutput = self.model.predict_views([v[0] for v in views])
        pred = out.depth[-1].astype(np.float32)
        scale = None
        if metric is not None and int(np.isfinite(metric).sum()) >= MIN_ALIGNMENT_PIXELS:
            scale = align_depth_median(pred, metric)
        elif out.cam_centres is not None and len(views) >= 2:
            known = np.stack([v[1][:3, 3] for v in views])
            try:
                scale, _, _ = align_scale_to_poses(out.cam_centres, known)
            except InputError as exc:
                notes.append(f"pose alignment failed ({exc}); depth left in model units")
        else:
            notes.append("no metric depth and fewer than two views: depth left in model units")
        self._history.append((rgb, T))
        depth = pred * np.float32(scale if scale is not None else 1.0)
        with np.errstate(invalid="ignore"):
            depth[~(depth > 0) | (depth > self.sensor.max_range)] = np.nan
        confidence = normalize_confidence(out.confidence[-1], self.confidence_normalization)
        confidence[~np.isfinite(depth)] = 0.0
        return FrameResult(depth, confidence, notes)


def _default_model_factory(backend: str) -> Callable[[str, str], object]:
    return VggtBackend if backend == "vggt" else DepthAnything3Backend


def undistorted(
    rgb: np.ndarray, depth: np.ndarray | None, right: np.ndarray | None, undistortions: dict
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """A frame's images remapped into the pinhole camera k of their camera info, where it has
    distortion (`undistort`); an image of another size than its camera info's is left to
    `check_frame` to refuse by name."""
    left, right_remap = undistortions["left"], undistortions["right"]
    if left is not None and left.fits(rgb):
        rgb = left.color(rgb)
    if left is not None and left.fits(depth):  # registered to the colour image: the same camera
        depth = left.depth(depth)
    if right_remap is not None and right_remap.fits(right):
        right = right_remap.color(right)
    return rgb, depth, right


def nothing_outside(result: FrameResult, remap: Remap) -> FrameResult:
    """No estimate where the undistorted image's rays land outside the raw image: the rgbd
    backend takes a region without depth for one of no return (`no_return`), which the planner
    would carve free."""
    outside = remap.outside
    if result.depth.shape != outside.shape:
        return result
    weight = result.weight
    confidence = np.where(outside, np.float32(0.0), result.confidence)
    return dataclasses.replace(
        result,
        depth=np.where(outside, np.float32(np.nan), result.depth),
        confidence=confidence,
        weight=confidence
        if weight is None or weight is result.confidence
        else np.where(outside, np.float32(0.0), weight),
    )


def estimator_from_parameters(p: dict) -> FrameEstimator:
    """The estimator the perception node's parameters `p` describe (also what
    `area3d_bringup.inprocess` estimates with)."""
    sensor = RgbdSensorParams(
        **{f.name: p[f"sensor.{f.name}"] for f in dataclasses.fields(RgbdSensorParams)}
    )
    stereo = StereoParams(
        **{
            f.name: p[f"stereo.{f.name}"]
            for f in dataclasses.fields(StereoParams)
            if f.name != "max_range"
        }
    )
    return FrameEstimator(
        backend=p["backend"],
        sensor=sensor,
        checkpoint=p["checkpoint"],
        device=p["device"],
        window=p["window"],
        confidence_normalization=p["confidence_normalization"],
        stereo=stereo,
        uniform_confidence=p["uniform_confidence"],
        no_return=p["no_return"],
    )
