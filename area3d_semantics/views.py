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
    (and depth when require_depth, and perception's confidence when require_confidence:
    perception publishes it for the frames it integrates, so a streaming camera's views are its
    keyframes, not every frame). Keeps at most max_views complete views and max_pending
    incomplete ones, dropping the oldest of each (a 30 Hz stream whose frames never become
    views cannot push out the views)."""

    def __init__(
        self,
        require_depth: bool = True,
        max_views: int = 128,
        require_confidence: bool = False,
        max_pending: int = 64,
    ) -> None:
        self.require_depth = require_depth
        self.require_confidence = require_confidence
        self.max_views = max_views
        self.max_pending = max_pending
        self._views: dict[int, View] = {}
        self._complete: list[int] = []  # stamps in the order they became complete
        self._pending: dict[int, None] = {}  # stamps of incomplete views, in arrival order

    def _view(self, stamp_ns: int) -> View:
        if stamp_ns not in self._views:
            self._views[stamp_ns] = View(stamp_ns)
            self._pending[stamp_ns] = None
            while len(self._pending) > self.max_pending:
                oldest = next(iter(self._pending))
                del self._pending[oldest], self._views[oldest]
        return self._views[stamp_ns]

    def _update(self, view: View) -> None:
        ready = (
            view.rgb is not None
            and (view.depth is not None or not self.require_depth)
            and (view.confidence is not None or not self.require_confidence)
        )
        if ready and view.stamp_ns not in self._complete:
            self._pending.pop(view.stamp_ns, None)
            self._complete.append(view.stamp_ns)
            while len(self._complete) > self.max_views:
                del self._views[self._complete.pop(0)]

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
        self._update(view)
        return view

    def get(self, stamp_ns: int) -> View | None:
        return self._views.get(stamp_ns)

    @property
    def complete(self) -> list[int]:
        """Stamps of complete views, in the order they became complete."""
        return list(self._complete)
