"""The region vocabulary of the VLM protocol: a 4x3 image grid, five uncertainty types, three
priorities, three sizes, and the Region record that the parser produces."""

from __future__ import annotations

from dataclasses import asdict, dataclass

# Horizontal positions, left to right, and vertical positions, top to bottom (paper, supplement).
COLUMNS: tuple[str, ...] = ("left", "center-left", "center-right", "right")
ROWS: tuple[str, ...] = ("top", "middle", "bottom")

# Uncertainty categories, ranked as in the prompt (OCCLUSION and GEOMETRIC high, LIGHTING and
# BOUNDARY medium, TEXTURE low).
TYPES: tuple[str, ...] = ("OCCLUSION", "GEOMETRIC", "LIGHTING", "BOUNDARY", "TEXTURE")
PRIORITIES: tuple[str, ...] = ("HIGH", "MEDIUM", "LOW")
SIZES: tuple[str, ...] = ("small", "medium", "large")

# Priority a region gets when the answer leaves it out: the rank of its type in the prompt.
DEFAULT_PRIORITY_BY_TYPE: dict[str, str] = {
    "OCCLUSION": "HIGH",
    "GEOMETRIC": "HIGH",
    "LIGHTING": "MEDIUM",
    "BOUNDARY": "MEDIUM",
    "TEXTURE": "LOW",
}
DEFAULT_SIZE = "medium"


@dataclass(frozen=True)
class Region:
    """One uncertain grid cell of one image.

    image_index: 0-based position of the image in the query (the prompt numbers images from 1).
    column: one of COLUMNS; row: one of ROWS; type: one of TYPES; priority: one of PRIORITIES;
    size: one of SIZES; reason: the model's free-text justification.
    """

    image_index: int
    column: str
    row: str
    type: str
    priority: str
    size: str
    reason: str = ""

    @property
    def location(self) -> str:
        """Grid notation used by the prompt, column first: e.g. "center-left-middle"."""
        return f"{self.column}-{self.row}"

    def to_dict(self) -> dict:
        """JSON-ready dict with the location spelled out as well."""
        return {**asdict(self), "location": self.location}
