"""Turn a VLM's free-form answer into Region records.

The prompt asks for one strict line per region, but real models drift: markdown (bold, bullets,
tables, code fences), numbering, prose around the list, lower case, synonyms ("centre", "upper",
"top-left"), JSON, missing fields, duplicates, too many or too few regions. The parser accepts all
of these, skips (and logs) what it cannot place, and raises UnusableAnswer only when nothing usable
is left. It reads the answer's structure (lines, tables, JSON); what each field's words mean is
`answer_fields`.
"""

from __future__ import annotations

import json
import logging
import re
from dataclasses import dataclass, field

from area3d_msgs_py.errors import InputError
from area3d_semantics.answer_fields import (
    FIELD_ALIASES,
    ORDINALS,
    STRICT_TYPE_RE,
    parse_image_number,
    parse_location,
    parse_priority,
    parse_size,
    parse_type,
    whole_image_number,
)
from area3d_semantics.region import (
    DEFAULT_PRIORITY_BY_TYPE,
    DEFAULT_SIZE,
    PRIORITIES,
    Region,
)

__all__ = ["ParseResult", "Region", "UnusableAnswer", "parse_answer"]

LOG = logging.getLogger(__name__)

# The prompt asks for 5-8 regions per image; extra ones (in the model's order) are dropped.
MAX_REGIONS_PER_IMAGE = 8


class UnusableAnswer(ValueError):
    """The answer holds no region that can be placed (empty, refusal, garbage)."""

    def __init__(self, reason: str, text: str = "") -> None:
        self.reason = reason
        excerpt = " ".join(text.split())[:160]
        super().__init__(
            f"unusable VLM answer: {reason}" + (f" (answer: {excerpt!r})" if excerpt else "")
        )


@dataclass
class ParseResult:
    """regions: in answer order per image; skipped: one line per dropped piece, with the reason;
    per_image: number of regions for each image index 0..num_images-1."""

    regions: list[Region]
    skipped: list[str] = field(default_factory=list)
    per_image: list[int] = field(default_factory=list)

    def regions_of(self, image_index: int) -> list[Region]:
        return [r for r in self.regions if r.image_index == image_index]


SKIPPED_LOGGED = 20  # skipped pieces of one answer logged one by one; the rest counted
HEADER_RE = re.compile(
    r"^(?:for\s+)?(?:the\s+)?(?:image|view|img|picture|photo|frame)\s*(?:#|no\.?|number)?\s*"
    r"([-+]?\d+(?:[.,]\d+)?(?:e[-+]?\d+)?)\b"
    r"|^(" + "|".join(ORDINALS) + r")\s+(?:image|view|picture|photo)\b",
    re.I,
)
MD_NUMBER_HEADER_RE = re.compile(r"^#+\s*(\d+)\s*[:.)]?\s*$")
REFUSAL_RE = re.compile(
    r"\b(i'?m sorry|i am sorry|i cannot|i can'?t|i am unable|i'?m unable|unable to (?:help|assist|analy[sz]e)|as an ai)\b",
    re.I,
)
KEY_RE = re.compile(
    r"\b("
    + "|".join(sorted((re.escape(k) for k in FIELD_ALIASES), key=len, reverse=True))
    + r")\s*[:=]",
    re.I,
)
SEPARATORS = "|;,/([{-\u2013\u2014"


# --- text answers --------------------------------------------------------------------------------


def _clean_line(line: str) -> str:
    line = line.replace("**", "").replace("__", "").replace("`", "")
    line = re.sub(r"(?<!\w)\*(?!\s)|(?<!\s)\*(?!\w)", "", line)
    line = line.strip()
    line = re.sub(r"^(?:>\s*)+", "", line)
    line = re.sub(r"^(?:[-*\u2022+]\s+|\(?\d{1,2}[.)]\s+|#\d+[.:)]?\s+)+", "", line)
    return line.strip()


def _header_image(line: str) -> tuple[int, str] | None:
    """(image number, rest of the line) when the line opens an image's section."""
    md = MD_NUMBER_HEADER_RE.match(line.strip())
    if md:
        return int(md.group(1)), ""
    bare = re.sub(r"^#+\s*", "", line).strip().lstrip("[").strip()
    match = HEADER_RE.match(bare)
    if not match:
        return None
    # "IMAGE -3" or "IMAGE 4.9" opens a section of no image (0: skipped, out of range)
    number = (
        whole_image_number(match.group(1)) if match.group(1) else ORDINALS[match.group(2).lower()]
    )
    rest = bare[match.end() :].lstrip("]):.-\u2013\u2014 \t")
    return number, rest


def _key_values(line: str) -> list[tuple[str, str]]:
    """(field, value) pairs written as "KEY: value" in one line."""
    keys = []
    for match in KEY_RE.finditer(line):
        before = line[: match.start()].rstrip()
        written = match.group(1)
        if before and before[-1] not in SEPARATORS and not written.isupper():
            continue
        if keys and keys[-1][1] == "reason" and (not before or before[-1] != "|"):
            continue  # words like "area:" inside a reason stay in the reason
        keys.append((match, FIELD_ALIASES[written.lower()]))
    pairs = []
    for n, (match, name) in enumerate(keys):
        end = keys[n + 1][0].start() if n + 1 < len(keys) else len(line)
        value = line[match.end() : end].strip().strip("|;,").strip()
        pairs.append((name, value))
    return pairs


def _free_text_record(line: str) -> dict | None:
    """A region written without keys: "left-top (OCCLUSION, HIGH, small): the sofa hides ..."."""
    if not STRICT_TYPE_RE.search(line):
        return None
    head_match = re.search(r":|\s[-\u2013\u2014]\s", line)
    head = line[: head_match.start()] if head_match else line
    tail = line[head_match.end() :].strip() if head_match else ""
    if not parse_location(
        re.sub(r"\b(OCCLUSION|GEOMETRIC|LIGHTING|BOUNDARY|TEXTURE)\b", " ", head, flags=re.I)
    ):
        return None
    strict = STRICT_TYPE_RE.search(head) or STRICT_TYPE_RE.search(line)
    priority = re.search(r"\b(HIGH|MEDIUM|LOW)\b", head, re.I) or re.search(
        r"\b(HIGH|MEDIUM|LOW)\b", line, re.I
    )
    # The size word is looked for after taking the priority word out ("MEDIUM, small").
    head_rest = (
        head[: priority.start()] + head[priority.end() :]
        if priority and priority.string is head
        else head
    )
    size = re.search(r"\b(small|medium|large)\b", head_rest, re.I)
    return {
        "region": re.sub(r"\b(OCCLUSION|GEOMETRIC|LIGHTING|BOUNDARY|TEXTURE|HIGH|MEDIUM|LOW|small|medium|large)\b", " ", head, flags=re.I),
        "type": strict.group(1),
        "priority": priority.group(1) if priority else "",
        "size": size.group(1) if size else "",
        "reason": tail,
    }  # fmt: skip


def _table_cells(line: str) -> list[str]:
    return [c.strip() for c in line.strip().strip("|").split("|")]


def _text_records(text: str) -> tuple[list[tuple[int | None, dict, str]], bool]:
    """Records (image number or None, fields, source line) and whether any header was seen."""
    records: list[tuple[int | None, dict, str]] = []
    image: int | None = None
    current: dict = {}
    current_image: int | None = None
    source = ""
    table_header: list[str | None] | None = None
    saw_header = False

    def flush() -> None:
        nonlocal current, source
        if current:
            records.append((current_image, current, source))
        current, source = {}, ""

    for raw in text.splitlines():
        if raw.strip().startswith("```"):
            continue
        line = _clean_line(raw)
        if not line:
            continue
        if line.startswith("|") and line.count("|") >= 2:
            cells = _table_cells(line)
            if all(re.fullmatch(r":?-{2,}:?", c) for c in cells if c):
                continue
            names = [FIELD_ALIASES.get(c.lower().strip(" *:"), None) for c in cells]
            if "region" in names and ("type" in names or "priority" in names):
                flush()
                table_header = names
                continue
            if table_header:
                flush()
                row = {n: c for n, c in zip(table_header, cells, strict=False) if n}
                row_image = parse_image_number(row.pop("image")) if row.get("image") else image
                if row.get("region") or row.get("type"):
                    records.append((row_image, row, line))
                continue
        header = _header_image(line)
        if header is not None:
            flush()
            image, line = header
            saw_header = True
            table_header = None
            if not line:
                continue
        pairs = _key_values(line)
        if not pairs:
            record = _free_text_record(line)
            if record is not None:
                flush()
                current, current_image, source = record, image, line
                flush()
            elif current and "reason" in current and not _header_image(line):
                pass  # a wrapped reason line; the reason is kept as first written
            continue
        for name, value in pairs:
            if name == "image":
                number = parse_image_number(value)
                if number is not None:
                    flush()
                    image = number
                    saw_header = True
                continue
            if name in current and (name == "region" or "region" in current):
                flush()
            if not current:
                current_image, source = image, line
            else:
                source = f"{source} {line}" if line not in source else source
            current[name] = value
    flush()
    return records, saw_header


# --- JSON answers --------------------------------------------------------------------------------


def _json_candidates(text: str) -> list[str]:
    fenced = re.findall(r"```(?:json|JSON)?\s*\n(.*?)```", text, re.S)
    candidates = fenced + [text.strip()]
    for open_, close in (("[", "]"), ("{", "}")):
        start, end = text.find(open_), text.rfind(close)
        if 0 <= start < end:
            candidates.append(text[start : end + 1])
    return candidates


def _json_records(obj, image: int | None, out: list) -> None:
    if isinstance(obj, dict):
        keys = {str(k).strip().lower(): k for k in obj}
        fields = {FIELD_ALIASES[k]: obj[orig] for k, orig in keys.items() if k in FIELD_ALIASES}
        if "image" in fields and not isinstance(fields["image"], list | dict):
            number = parse_image_number(fields.pop("image"))
            image = number if number is not None else image
        if (
            "region" in fields
            and not isinstance(fields["region"], dict)
            and not (
                isinstance(fields["region"], list)
                and fields["region"]
                and isinstance(fields["region"][0], dict)
            )
        ):
            record = {
                k: (" and ".join(map(str, v)) if isinstance(v, list) else str(v))
                for k, v in fields.items()
                if k != "image"
            }
            out.append((image, record, json.dumps(obj)[:200]))
            return
        for key, value in obj.items():
            header = _header_image(str(key)) or (
                (int(key), "") if re.fullmatch(r"\s*\d+\s*", str(key)) else None
            )
            _json_records(value, header[0] if header else image, out)
    elif isinstance(obj, list):
        nested = obj and all(isinstance(v, list) for v in obj)
        for n, value in enumerate(obj, start=1):
            _json_records(value, n if nested else image, out)


def _try_json(text: str) -> tuple[list, bool] | None:
    for candidate in _json_candidates(text):
        try:
            obj = json.loads(candidate)
        except (json.JSONDecodeError, ValueError):
            continue
        records: list = []
        _json_records(obj, None, records)
        if records:
            return records, any(r[0] is not None for r in records)
    return None


# --- assembly ------------------------------------------------------------------------------------


def _record_to_regions(fields: dict) -> tuple[list[tuple[str, str]], str, str, str, str] | str:
    """(cells, type, priority, size, reason), or the reason the record is skipped."""
    region_text = str(fields.get("region", "")).strip()
    cells = parse_location(region_text) if region_text else []
    type_ = parse_type(str(fields.get("type", ""))) if fields.get("type") else None
    if not cells:
        return f"no grid location in {region_text!r}" if region_text else "no location"
    if type_ is None:
        return (
            f"no uncertainty type in {fields.get('type', '')!r}"
            if fields.get("type")
            else "no type"
        )
    priority = parse_priority(str(fields.get("priority", ""))) or DEFAULT_PRIORITY_BY_TYPE[type_]
    size = parse_size(str(fields.get("size", ""))) or DEFAULT_SIZE
    reason = " ".join(str(fields.get("reason", "")).split())
    return cells, type_, priority, size, reason


def parse_answer(
    text: str, num_images: int, max_per_image: int = MAX_REGIONS_PER_IMAGE
) -> ParseResult:
    """Regions of a VLM answer to the region-analysis prompt.

    text: the raw answer. num_images: how many images the query carried (images are numbered
    from 1 in the answer, image_index is 0-based). Raises UnusableAnswer when no region survives.
    """
    if not isinstance(text, str):
        raise InputError("text", type(text).__name__, "the answer as a str")
    if not isinstance(num_images, int) or num_images < 1:
        raise InputError("num_images", num_images, "an int >= 1")
    if not text.strip():
        raise UnusableAnswer("empty answer")

    parsed = _try_json(text)
    records, saw_header = parsed if parsed is not None else _text_records(text)
    labelled_one = any(img == 1 for img, _, _ in records)

    skipped: list[str] = []
    regions: list[Region] = []
    index_of: dict[tuple[int, str, str, str], int] = {}
    records_per_image = [0] * num_images
    for image, fields, source in records:
        if image is None:
            if num_images == 1 or (saw_header and not labelled_one):
                image = 1
            else:
                skipped.append(f"no image header before region: {source[:120]}")
                continue
        if not 1 <= image <= num_images:
            skipped.append(f"image {image} out of range 1..{num_images}: {source[:120]}")
            continue
        converted = _record_to_regions(fields)
        if isinstance(converted, str):
            skipped.append(f"{converted}: {source[:120]}")
            continue
        cells, type_, priority, size, reason = converted
        idx = image - 1
        new_cells = [c for c in cells if (idx, c[0], c[1], type_) not in index_of]
        for column, row in cells:
            key = (idx, column, row, type_)
            if key in index_of:
                old = regions[index_of[key]]
                if PRIORITIES.index(priority) < PRIORITIES.index(old.priority):
                    regions[index_of[key]] = Region(idx, column, row, type_, priority, size, reason)
        if not new_cells:
            continue
        if records_per_image[idx] >= max_per_image:
            skipped.append(f"more than {max_per_image} regions for image {image}: {source[:120]}")
            continue
        records_per_image[idx] += 1
        for column, row in new_cells:
            index_of[(idx, column, row, type_)] = len(regions)
            regions.append(Region(idx, column, row, type_, priority, size, reason))

    for line in skipped[:SKIPPED_LOGGED]:
        LOG.info("VLM answer: skipped %s", line)
    if len(skipped) > SKIPPED_LOGGED:  # an answer of junk lines is not as many log lines
        LOG.info("VLM answer: %d more lines skipped", len(skipped) - SKIPPED_LOGGED)
    if not regions:
        if REFUSAL_RE.search(text):
            raise UnusableAnswer("the model refused", text)
        raise UnusableAnswer("no region with a grid location and a type", text)
    per_image = [sum(r.image_index == i for r in regions) for i in range(num_images)]
    return ParseResult(regions=regions, skipped=skipped, per_image=per_image)
