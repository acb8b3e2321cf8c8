"""One region analysis of a set of views: ask the backend, parse, and fall back when that fails."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from area3d_msgs_py.errors import InputError
from area3d_semantics.backends import Backend, HeuristicBackend, NoneBackend
from area3d_semantics.parser import UnusableAnswer, parse_answer
from area3d_semantics.prompt import PROMPT_VERSION
from area3d_semantics.region import Region

LOG = logging.getLogger(__name__)

FALLBACKS = ("heuristic", "zeros")


@dataclass
class Analysis:
    """regions: 0-based image_index into the analysed views; fallback_used: None, "heuristic" or
    "zeros"; error: why the backend's answer was not used ("" when it was)."""

    regions: list[Region]
    num_images: int
    backend: str
    fallback_used: str | None = None
    error: str = ""
    answer: str = ""
    skipped: list[str] = field(default_factory=list)

    def regions_of(self, image_index: int) -> list[Region]:
        return [r for r in self.regions if r.image_index == image_index]

    def to_json(self, stamps_ns: list[int]) -> dict:
        """The /area3d/semantics/regions payload, images in query order with their capture stamps."""
        if len(stamps_ns) != self.num_images:
            raise InputError(
                "stamps_ns", len(stamps_ns), f"one stamp per analysed image ({self.num_images})"
            )
        return {
            "prompt_version": PROMPT_VERSION,
            "backend": self.backend,
            "fallback_used": self.fallback_used,
            "error": self.error,
            "images": [
                {"stamp_ns": int(stamp), "regions": [r.to_dict() for r in self.regions_of(i)]}
                for i, stamp in enumerate(stamps_ns)
            ],
        }


def analyze_views(
    backend: Backend,
    images: list[np.ndarray],
    depths: list[np.ndarray | None] | None = None,
    fallback: str = "heuristic",
) -> Analysis:
    """Regions for all views in one query. Backend errors and unusable answers never escape: they
    are logged and replaced by the heuristic analyzer's regions (fallback="heuristic") or by no
    regions (fallback="zeros")."""
    if fallback not in FALLBACKS:
        raise InputError("fallback", fallback, f"one of {', '.join(FALLBACKS)}")
    n = len(images)
    if isinstance(backend, NoneBackend):
        return Analysis(regions=[], num_images=n, backend=backend.name)
    try:
        answer = backend.analyze(images, depths)
        parsed = parse_answer(answer, n)
        return Analysis(parsed.regions, n, backend.name, answer=answer, skipped=parsed.skipped)
    except (InputError, TypeError):
        raise
    except Exception as exc:  # any backend failure (unreachable, timeout, garbage) falls back
        error = f"{exc.__class__.__name__}: {exc}"
    LOG.warning(
        "semantics: %s backend failed (%s); falling back to %s", backend.name, error, fallback
    )
    if fallback == "heuristic" and not isinstance(backend, HeuristicBackend):
        try:
            answer = HeuristicBackend().analyze(images, depths)
            parsed = parse_answer(answer, n)
            return Analysis(
                parsed.regions, n, backend.name, "heuristic", error, answer, parsed.skipped
            )
        except UnusableAnswer as exc:
            error += f"; heuristic: {exc}"
    return Analysis([], n, backend.name, "zeros", error)
