"""Offline region analyzer: finds the prompt's five kinds of hard regions from image evidence alone
and scores the 12 grid cells, so the system runs (and is testable) with no VLM at all.

Evidence per pixel, then per cell:
- OCCLUSION: depth discontinuities (relative jump between neighbours, or depth next to no return)
  inside the image: the near side hides what lies behind it. Needs a depth image.
- BOUNDARY: depth discontinuities or strong image edges in a thin band along the image border:
  an object cut by the frame.
- GEOMETRIC: dense strong edges (thin or intricate structure) and, with depth, strong curvature
  (Laplacian of inverse depth, which is zero on any plane).
- LIGHTING: saturated (specular / overexposed) or very dark pixels.
- TEXTURE: low local intensity variance.
Pixels with no depth return are left out of GEOMETRIC, LIGHTING and TEXTURE (nothing to rebuild).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from area3d_msgs_py.errors import InputError
from area3d_semantics.region import COLUMNS, PRIORITIES, ROWS, TYPES


def _full_evidence() -> dict[str, float]:
    # Share of a cell's pixels (of its border band for BOUNDARY) at which the evidence counts as
    # certain: a depth edge is thin, so 4% of a cell is already a long occluding contour.
    return {"OCCLUSION": 0.04, "GEOMETRIC": 0.3, "LIGHTING": 0.25, "BOUNDARY": 0.3, "TEXTURE": 0.6}


def _rank() -> dict[str, float]:
    # Order of importance given in the prompt; ties between cells are broken by this.
    return {"OCCLUSION": 1.0, "GEOMETRIC": 0.9, "LIGHTING": 0.8, "BOUNDARY": 0.7, "TEXTURE": 0.5}


@dataclass(frozen=True)
class HeuristicParams:
    depth_jump: float = (
        0.08  # relative depth step between neighbouring pixels that is an occluding edge
    )
    border_band: float = 0.03  # width of the border band, fraction of min(H, W)
    edge_gradient: float = 0.25  # Sobel magnitude (grey in [0, 1]) of a strong edge
    edge_window: int = 15  # px, window of the edge-density filter
    edge_density: float = (
        0.25  # share of strong-edge pixels in the window that marks busy structure
    )
    curvature: float = (
        0.05  # |Laplacian(1/d)| * d over 3x3 px, above this a surface is strongly curved
    )
    texture_window: int = 7  # px, window of the local standard deviation
    texture_std: float = 0.012  # local grey std (in [0, 1]) below which a patch is textureless
    saturated_level: int = 250  # any RGB channel at or above this is saturated
    dark_level: float = 0.06  # grey below this is "very dark"
    full_evidence: dict[str, float] = field(default_factory=_full_evidence)
    rank: dict[str, float] = field(default_factory=_rank)
    min_evidence: float = 0.15  # a cell/type pair below this is not reported ...
    fill_evidence: float = 0.03  # ... unless it is needed to reach min_regions and is above this
    min_regions: int = 5  # the prompt asks for 5-8 regions per image
    max_regions: int = 8


def _depth_discontinuities(depth: np.ndarray, jump: float) -> np.ndarray:
    """(H, W) bool: pixels on either side of a relative depth jump or a depth/no-return edge."""
    finite = np.isfinite(depth) & (depth > 0)
    d = np.where(finite, depth, 0.0).astype(np.float32)
    out = np.zeros(depth.shape, dtype=bool)
    for a, b, fa, fb, sa, sb in (
        (d[:, :-1], d[:, 1:], finite[:, :-1], finite[:, 1:], np.s_[:, :-1], np.s_[:, 1:]),
        (d[:-1, :], d[1:, :], finite[:-1, :], finite[1:, :], np.s_[:-1, :], np.s_[1:, :]),
    ):
        both = fa & fb
        with np.errstate(divide="ignore", invalid="ignore"):
            rel = np.abs(a - b) / np.minimum(a, b)
        edge = (both & (rel > jump)) | (fa != fb)
        out[sa] |= edge
        out[sb] |= edge
    return out


def border_band(height: int, width: int, fraction: float) -> np.ndarray:
    """(H, W) bool: pixels within fraction * min(H, W) (at least 1 px) of the image border."""
    px = max(1, round(fraction * min(height, width)))
    band = np.zeros((height, width), dtype=bool)
    band[:px], band[-px:], band[:, :px], band[:, -px:] = True, True, True, True
    return band


def evidence_maps(
    image: np.ndarray, depth: np.ndarray | None = None, params: HeuristicParams | None = None
) -> dict[str, np.ndarray]:
    """Per-pixel evidence, one (H, W) bool map per type.

    image: (H, W, 3) uint8 RGB. depth: (H, W) float metres, NaN = no return, or None.
    """
    p = params or HeuristicParams()
    h, w = image.shape[:2]
    grey = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY).astype(np.float32) / 255.0
    band = border_band(h, w, p.border_band)

    gx = cv2.Sobel(grey, cv2.CV_32F, 1, 0, ksize=3) / 4.0
    gy = cv2.Sobel(grey, cv2.CV_32F, 0, 1, ksize=3) / 4.0
    edges = np.hypot(gx, gy) > p.edge_gradient
    density = cv2.boxFilter(edges.astype(np.float32), -1, (p.edge_window, p.edge_window))
    geometric = density > p.edge_density

    mean = cv2.boxFilter(grey, -1, (p.texture_window, p.texture_window))
    mean_sq = cv2.boxFilter(grey * grey, -1, (p.texture_window, p.texture_window))
    std = np.sqrt(np.maximum(mean_sq - mean * mean, 0.0))
    lighting = (image.max(axis=2) >= p.saturated_level) | (grey < p.dark_level)
    texture = (std < p.texture_std) & ~lighting

    if depth is not None:
        valid = np.isfinite(depth) & (depth > 0)
        disc = (
            cv2.dilate(
                _depth_discontinuities(depth, p.depth_jump).astype(np.uint8),
                np.ones((3, 3), np.uint8),
            )
            > 0
        )
        inv = np.where(valid, 1.0 / np.where(valid, depth, 1.0), 0.0).astype(np.float32)
        curved = (
            np.abs(cv2.Laplacian(inv, cv2.CV_32F, ksize=3)) * np.where(valid, depth, 0.0)
            > p.curvature
        )
        geometric = (geometric | (curved & ~disc)) & valid & ~disc
        lighting &= valid
        texture &= valid & ~disc
        occlusion = disc & ~band
        boundary = band & (disc | edges)
    else:
        occlusion = np.zeros((h, w), dtype=bool)
        boundary = band & edges
    return {
        "OCCLUSION": occlusion,
        "GEOMETRIC": geometric,
        "LIGHTING": lighting,
        "BOUNDARY": boundary,
        "TEXTURE": texture,
    }


def _cell_sums(mask: np.ndarray) -> np.ndarray:
    """(3, 4) sums of an (H, W) map over the grid cells (rows x columns)."""
    h, w = mask.shape
    r_edges = np.linspace(0, h, len(ROWS) + 1).round().astype(int)[:-1]
    c_edges = np.linspace(0, w, len(COLUMNS) + 1).round().astype(int)[:-1]
    rows = np.add.reduceat(mask.astype(np.float64), r_edges, axis=0)
    return np.add.reduceat(rows, c_edges, axis=1)


def cell_evidence(
    image: np.ndarray, depth: np.ndarray | None = None, params: HeuristicParams | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Evidence strength and covered share of the image per type and cell.

    Returns (strength (5, 3, 4) in [0, 1], share (5, 3, 4)): TYPES x ROWS x COLUMNS; strength is
    the flagged share of the cell (of its border band for BOUNDARY) over full_evidence; share is
    the flagged pixels of the cell and its 8 neighbours over the whole image (for SIZE).
    """
    p = params or HeuristicParams()
    maps = evidence_maps(image, depth, p)
    h, w = image.shape[:2]
    pixels = _cell_sums(np.ones((h, w), dtype=bool))
    band = border_band(h, w, p.border_band)
    band_pixels = np.maximum(_cell_sums(band), 1.0)
    strength = np.zeros((len(TYPES), len(ROWS), len(COLUMNS)))
    share = np.zeros_like(strength)
    for t, name in enumerate(TYPES):
        counts = _cell_sums(maps[name])
        frac = counts / (band_pixels if name == "BOUNDARY" else pixels)
        strength[t] = np.minimum(frac / p.full_evidence[name], 1.0)
        padded = np.pad(counts, 1)
        neigh = sum(
            padded[i : i + len(ROWS), j : j + len(COLUMNS)] for i in range(3) for j in range(3)
        )
        share[t] = neigh / (h * w)
    return strength, share


REASONS = {
    "OCCLUSION": "Depth jumps across this cell: the near surface hides what lies behind it, which only another viewpoint can reveal.",
    "GEOMETRIC": "Dense edges or strong curvature mark fine or curved structure whose shape this single view cannot pin down.",
    "LIGHTING": "Much of this cell is saturated or very dark, so its surfaces carry little usable detail from this view.",
    "BOUNDARY": "Geometry runs into the image border here: the part outside the frame has not been observed.",
    "TEXTURE": "This cell is nearly textureless, which leaves its depth poorly constrained.",
}


def analyze_image(
    image: np.ndarray, depth: np.ndarray | None = None, params: HeuristicParams | None = None
) -> list[tuple[str, str, str, str, str, str]]:
    """Regions of one image, most important first: (column, row, TYPE, PRIORITY, size, reason)."""
    p = params or HeuristicParams()
    if (
        not isinstance(image, np.ndarray)
        or image.ndim != 3
        or image.shape[2] != 3
        or image.dtype != np.uint8
    ):
        raise InputError(
            "image", getattr(image, "shape", type(image).__name__), "an (H, W, 3) uint8 RGB array"
        )
    if depth is not None and np.shape(depth) != image.shape[:2]:
        raise InputError(
            "depth", np.shape(depth), f"an (H, W) array matching the image {image.shape[:2]}"
        )
    strength, share = cell_evidence(image, depth, p)
    rank = np.array([p.rank[t] for t in TYPES])[:, None, None]
    score = strength * rank
    order = np.argsort(-score, axis=None, kind="stable")
    regions = []
    for flat in order:
        t, r, c = np.unravel_index(flat, score.shape)
        e = strength[t, r, c]
        enough = e >= p.min_evidence or (len(regions) < p.min_regions and e >= p.fill_evidence)
        if not enough or len(regions) >= p.max_regions:
            break
        priority = PRIORITIES[0] if e >= 0.6 else PRIORITIES[1] if e >= 0.3 else PRIORITIES[2]
        covered = share[t, r, c]
        size = "small" if covered < 0.10 else "medium" if covered <= 0.25 else "large"
        regions.append((COLUMNS[c], ROWS[r], TYPES[t], priority, size, REASONS[TYPES[t]]))
    return regions


def format_answer(per_image: list[list[tuple[str, str, str, str, str, str]]]) -> str:
    """Write regions in exactly the answer format the prompt asks of a VLM."""
    lines = []
    for n, regions in enumerate(per_image, start=1):
        lines.append(f"IMAGE {n}")
        for column, row, type_, priority, size, reason in regions:
            lines.append(
                f"REGION: {column}-{row} | TYPE: {type_} | PRIORITY: {priority} | SIZE: {size} | REASON: {reason}"
            )
    return "\n".join(lines) + "\n"
