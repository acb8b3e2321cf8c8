"""The captured views the semantics node knows about, paired by capture stamp."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from area3d_msgs_py.errors import InputError


@dataclass
class View:
    """One captured frame: rgb (H, W, 3) uint8, depth (H, W) float32 metres NaN = no return,
    confidence (h, w) float32 in [0, 1] from perception; any may still be missing."""

    stamp_ns: int
    frame_id: str = ""
    rgb: np.ndarray | None = None
    depth: np.ndarray | None = None
    confidence: np.ndarray | None = None


class ViewCollector:
    """Pairs color, depth and confidence images by stamp; a view is complete once it has color
    (and depth when require_depth). Keeps at most max_views views, dropping the oldest."""

    def __init__(self, require_depth: bool = True, max_views: int = 128) -> None:
        self.require_depth = require_depth
        self.max_views = max_views
        self._views: dict[int, View] = {}
        self._complete: list[int] = []  # stamps in the order they became complete

    def _view(self, stamp_ns: int) -> View:
        if stamp_ns not in self._views:
            self._views[stamp_ns] = View(stamp_ns)
            if len(self._views) > self.max_views:
                oldest = min(self._views)
                del self._views[oldest]
                if oldest in self._complete:
                    self._complete.remove(oldest)
        return self._views[stamp_ns]

    def _update(self, view: View) -> None:
        ready = view.rgb is not None and (view.depth is not None or not self.require_depth)
        if ready and view.stamp_ns not in self._complete:
            self._complete.append(view.stamp_ns)

    @staticmethod
    def _check_size(
        field: str, image: np.ndarray, other: np.ndarray | None, other_name: str
    ) -> None:
        """Color and depth of one frame are registered: same width and height."""
        if other is not None and image.shape[:2] != other.shape[:2]:
            raise InputError(
                field,
                f"{image.shape[1]}x{image.shape[0]}",
                f"the {other_name} size {other.shape[1]}x{other.shape[0]} of the same stamp",
            )

    def add_color(self, stamp_ns: int, rgb: np.ndarray, frame_id: str = "") -> View:
        existing = self._views.get(stamp_ns)
        self._check_size("color", rgb, existing and existing.depth, "depth")
        view = self._view(stamp_ns)
        view.rgb, view.frame_id = rgb, frame_id or view.frame_id
        self._update(view)
        return view

    def add_depth(self, stamp_ns: int, depth: np.ndarray) -> View:
        existing = self._views.get(stamp_ns)
        self._check_size("depth", depth, existing and existing.rgb, "color")
        view = self._view(stamp_ns)
        view.depth = depth
        self._update(view)
        return view

    def add_confidence(self, stamp_ns: int, confidence: np.ndarray) -> View:
        view = self._view(stamp_ns)
        view.confidence = confidence
        return view

    def get(self, stamp_ns: int) -> View | None:
        return self._views.get(stamp_ns)

    @property
    def complete(self) -> list[int]:
        """Stamps of complete views, in the order they became complete."""
        return list(self._complete)
