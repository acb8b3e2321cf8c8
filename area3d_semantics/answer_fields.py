"""The words a VLM answers with, field by field: which key names a field (`FIELD_ALIASES`), and
what a region's location, type, priority, size and image number read as, however the model
words them ("centre", "upper", "top-left", "occluded", "critical", "12%", "second image").
"""

from __future__ import annotations

import itertools
import re

from area3d_semantics.region import COLUMNS, PRIORITIES, ROWS

FIELD_ALIASES: dict[str, str] = {
    "region": "region", "location": "region", "cell": "region", "grid cell": "region",
    "grid location": "region", "grid position": "region", "grid": "region", "position": "region",
    "area": "region", "where": "region", "loc": "region",
    "type": "type", "category": "type", "uncertainty type": "type", "uncertainty": "type",
    "kind": "type", "class": "type", "issue": "type",
    "priority": "priority", "importance": "priority", "prio": "priority", "level": "priority",
    "size": "size", "extent": "size", "coverage": "size", "region size": "size",
    "reason": "reason", "reasoning": "reason", "explanation": "reason", "why": "reason",
    "rationale": "reason", "justification": "reason", "description": "reason", "notes": "reason",
    "image": "image", "image index": "image", "image id": "image", "image number": "image",
    "image_index": "image", "image_id": "image", "view": "image", "img": "image",
}  # fmt: skip

TYPE_PATTERNS: list[tuple[str, str]] = [
    (r"occlu\w*|hidden|blocked|self.occlu\w*", "OCCLUSION"),
    (r"geometr\w*|thin\b|fine.structure\w*|reflect\w*|transparen\w*|curv\w*", "GEOMETRIC"),
    (r"light\w*|illumin\w*|shadow\w*|over.?expos\w*|under.?expos\w*|exposure|highlight\w*|glare|specular|blur\w*", "LIGHTING"),
    (r"boundar\w*|border\w*|truncat\w*|cut.off|partial\w*|edge\w*", "BOUNDARY"),
    (r"textur\w*|featureless|repetitive|uniform", "TEXTURE"),
]  # fmt: skip
TYPE_RE = re.compile("|".join(f"(?P<t{i}>{p})" for i, (p, _) in enumerate(TYPE_PATTERNS)), re.I)
STRICT_TYPE_RE = re.compile(r"\b(OCCLUSION|GEOMETRIC|LIGHTING|BOUNDARY|TEXTURE)\b", re.I)

PRIORITY_WORDS = {
    "high": "HIGH", "critical": "HIGH", "must": "HIGH", "urgent": "HIGH", "highest": "HIGH",
    "medium": "MEDIUM", "med": "MEDIUM", "moderate": "MEDIUM", "mid": "MEDIUM", "should": "MEDIUM",
    "normal": "MEDIUM", "low": "LOW", "minor": "LOW", "nice": "LOW", "optional": "LOW", "lowest": "LOW",
}  # fmt: skip
SIZE_WORDS = {
    "small": "small", "tiny": "small", "little": "small", "sm": "small", "s": "small",
    "medium": "medium", "med": "medium", "moderate": "medium", "mid": "medium", "m": "medium",
    "large": "large", "big": "large", "huge": "large", "major": "large", "l": "large",
}  # fmt: skip
ORDINALS = {
    "first": 1, "second": 2, "third": 3, "fourth": 4, "fifth": 5, "sixth": 6, "seventh": 7,
    "eighth": 8, "ninth": 9, "tenth": 10,
}  # fmt: skip


# --- location ------------------------------------------------------------------------------------


def _location_tokens(text: str) -> list[str]:
    text = text.lower().replace("centre", "center").replace("central", "center")
    words = re.findall(r"[a-z]+|[&/+,;]", text)
    synonyms = {
        "upper": "top",
        "lower": "bottom",
        "mid": "middle",
        "centered": "center",
        "centred": "center",
    }
    vocab = {"left", "right", "center", "middle", "top", "bottom", "and", "&", "/", "+", ",", ";"}
    return [t for t in (synonyms.get(w, w) for w in words) if t in vocab]


def _parse_location_part(tokens: list[str]) -> tuple[list[tuple[str, str]], bool] | None:
    """Cells named by one location phrase, and whether both column and row were explicit."""
    n_row_words = sum(t in ("top", "bottom", "middle") for t in tokens)
    cols: list[str] = []
    rows: list[str] = []
    center_alone = False
    i = 0
    while i < len(tokens):
        t = tokens[i]
        nxt = tokens[i + 1] if i + 1 < len(tokens) else ""
        if t == "center" and nxt in ("left", "right"):
            cols.append(f"center-{nxt}")
            i += 2
        elif t in ("left", "right") and nxt == "center":
            # Column-row order: "left-center" is the left column, middle row, unless another row
            # word follows ("left-center-top" is the center-left column).
            if n_row_words >= 1:
                cols.append(f"center-{t}")
            else:
                cols.append(t)
                rows.append("middle")
            i += 2
        elif t == "middle" and nxt in ("left", "right") and n_row_words >= 2:
            # "middle-left" next to another row word is a column ("middle-left-top").
            cols.append(f"center-{nxt}")
            i += 2
        elif t == "center":
            cols += ["center-left", "center-right"]
            center_alone = True
            i += 1
        elif t in ("left", "right"):
            cols.append(t)
            i += 1
        elif t in ("top", "bottom", "middle"):
            rows.append(t)
            i += 1
        else:
            i += 1
    if not cols and not rows:
        return None
    explicit = bool(cols) and bool(rows)
    if not cols:
        cols = ["center-left", "center-right"] if rows == ["middle"] else list(COLUMNS)
    if not rows:
        rows = ["middle"] if center_alone else list(ROWS)
    cells = list(dict.fromkeys(itertools.product(dict.fromkeys(cols), dict.fromkeys(rows))))
    return cells, explicit


def parse_location(text: str) -> list[tuple[str, str]]:
    """Grid cells (column, row) named by a location phrase; [] when it names none.

    Column-row ("center-left-middle") and row-column ("top-left") orders both work; "center" alone
    means both center columns; a phrase with only a row spans all columns and one with only a
    column spans all rows; "a and b", "a / b" name several cells.
    """
    text = re.sub(r"\([^)]*\)", " ", text) if re.sub(r"\([^)]*\)", " ", text).strip() else text
    tokens = _location_tokens(text)
    parts = [
        list(g)
        for sep, g in itertools.groupby(tokens, key=lambda t: t in {"and", "&", "/", "+", ",", ";"})
        if not sep
    ]
    parsed_parts = [_parse_location_part(p) for p in parts]
    if len(parts) > 1 and all(p is not None and p[1] for p in parsed_parts):
        return list(dict.fromkeys(c for p in parsed_parts for c in p[0]))  # type: ignore[union-attr]
    whole = _parse_location_part([t for t in tokens if t not in {"and", "&", "/", "+", ",", ";"}])
    return whole[0] if whole else []


# --- field values --------------------------------------------------------------------------------


def parse_type(text: str) -> str | None:
    match = TYPE_RE.search(text)
    if not match:
        return None
    return TYPE_PATTERNS[int(match.lastgroup[1:])][1]


def parse_priority(text: str) -> str | None:
    for word in re.findall(r"[a-z]+|\d", text.lower()):
        if word in PRIORITY_WORDS:
            return PRIORITY_WORDS[word]
        if word in ("1", "2", "3"):
            return PRIORITIES[int(word) - 1]
    return None


def parse_size(text: str) -> str | None:
    for word in re.findall(r"[a-z]+", text.lower()):
        if word in SIZE_WORDS:
            return SIZE_WORDS[word]
    percent = re.search(r"(\d+(?:\.\d+)?)\s*%", text)
    if percent:
        value = float(percent.group(1))
        return "small" if value < 10 else "medium" if value <= 25 else "large"
    return None


# a number that opens an image's name: "2", "Image 2", "#2 (left)", or one that is not a whole
# number >= 0 ("-3", "4.9", "1e308"), which names no image
IMAGE_NUMBER_RE = re.compile(
    r"(?:(?:image|view|img|picture|photo|frame)\s*)?(?:#|no\.?|number)?\s*"
    r"([-+]?\d+(?:[.,]\d+)?(?:e[-+]?\d+)?)",
    re.I,
)


def whole_image_number(text: str) -> int:
    """A number as an image's: the int of plain digits, else 0 (out of range: the region is
    skipped, not moved to another image as "-3" -> 3 or "4.9" -> 4 did)."""
    return int(text) if text.isdigit() else 0


def parse_image_number(value) -> int | None:
    """The image a region names (from 1): an int, a whole float, text that opens with a number
    or an ordinal ("second"); 0 for a number that is no whole number >= 0 (skipped as out of
    range); None when it names none."""
    if isinstance(value, bool):
        return None
    if isinstance(value, int):
        return value
    if isinstance(value, float):
        return int(value) if value.is_integer() and 0 <= value < 2**31 else 0
    match = IMAGE_NUMBER_RE.match(str(value).strip())
    if match:
        return whole_image_number(match.group(1))
    if re.search(r"\d", str(value)):
        return 0
    word = str(value).strip().lower().split(" ")[0]
    return ORDINALS.get(word)
