"""The answer parser against hand-written answers in the styles real VLMs produce."""

import json
import logging
import re
from pathlib import Path

import pytest

from area3d_msgs_py.errors import InputError
from area3d_semantics.answer_fields import parse_location
from area3d_semantics.parser import SKIPPED_LOGGED, UnusableAnswer, parse_answer
from area3d_semantics.prompt import PROMPT_VERSION, prompt_text
from area3d_semantics.region import COLUMNS, PRIORITIES, ROWS, SIZES, TYPES
from area3d_semantics.weights import SemanticParams

CORPUS = Path(__file__).parent / "corpus"
EXPECTED = json.loads((CORPUS / "expected.json").read_text())


def test_corpus_has_at_least_fifteen_answers_each_with_an_expectation():
    answers = sorted(p.name for p in CORPUS.glob("*.txt"))
    assert len(answers) >= 15
    assert set(answers) == set(EXPECTED)


@pytest.mark.parametrize("name", sorted(k for k, v in EXPECTED.items() if not v.get("unusable")))
def test_corpus_answer_parses_to_the_expected_regions(name):
    expected = EXPECTED[name]
    result = parse_answer((CORPUS / name).read_text(), expected["num_images"])
    got = [(r.image_index, r.column, r.row, r.type, r.priority, r.size) for r in result.regions]
    assert sorted(got) == sorted(tuple(e) for e in expected["regions"])
    assert len(result.skipped) == expected["skipped"]
    assert result.per_image == [
        sum(e[0] == i for e in expected["regions"]) for i in range(expected["num_images"])
    ]


@pytest.mark.parametrize("name", sorted(k for k, v in EXPECTED.items() if v.get("unusable")))
def test_unusable_corpus_answer_raises(name):
    with pytest.raises(UnusableAnswer):
        parse_answer((CORPUS / name).read_text(), EXPECTED[name]["num_images"])


def test_reasons_are_kept_verbatim():
    result = parse_answer((CORPUS / "01_internvl3_strict.txt").read_text(), 4)
    assert result.regions[0].reason.startswith("The mug's handle hides the back")


def test_refusal_is_reported_as_a_refusal():
    with pytest.raises(UnusableAnswer, match="refused"):
        parse_answer("I'm sorry, I cannot analyze images of this kind.", 1)


@pytest.mark.parametrize(
    ("text", "cells"),
    [
        ("center-left-middle", [("center-left", "middle")]),
        ("top-left", [("left", "top")]),
        ("Upper Right", [("right", "top")]),
        ("centre-right-bottom", [("center-right", "bottom")]),
        ("middle-left", [("left", "middle")]),
        ("middle-left-top", [("center-left", "top")]),
        ("left-center", [("left", "middle")]),
        ("center", [("center-left", "middle"), ("center-right", "middle")]),
        ("center-top", [("center-left", "top"), ("center-right", "top")]),
        ("bottom", [(c, "bottom") for c in COLUMNS]),
        ("right", [("right", r) for r in ROWS]),
        ("left-top and right-bottom", [("left", "top"), ("right", "bottom")]),
        ("left-top (behind the lamp)", [("left", "top")]),
        ("the whole image", []),
    ],
)
def test_location_phrases_name_the_expected_cells(text, cells):
    assert parse_location(text) == cells


def _listed(text: str, after: str) -> list[str]:
    """The comma-separated words of the prompt line that starts with `after`."""
    line = next(line for line in text.splitlines() if line.startswith(after))
    return [w.strip(" .") for w in line[len(after) :].split(",")]


def _headed(text: str, heading: str) -> list[str]:
    """The WORD of every "WORD:" in the section under `heading`, in order."""
    section = text.split(f"\n{heading}")[1].split("\n\n")[0]
    return re.findall(r"(?:^|\. |\n)([A-Za-z]+):", section)


def test_the_prompts_vocabulary_is_the_parsers_in_the_same_order():
    """Order matters: a column listed out of order puts every mask in the wrong place, and the
    types are listed by importance, as their weights rank them."""
    text = prompt_text(4)
    assert PROMPT_VERSION == "v1" and "4 images" in text and "1 to 4" in text
    assert _listed(text, "Columns, from left to right:") == list(COLUMNS)
    assert _listed(text, "Rows, from top to bottom:") == list(ROWS)
    assert _headed(text, "TYPES") == list(TYPES)
    assert _headed(text, "PRIORITY") == list(PRIORITIES)
    assert _headed(text, "SIZE") == list(SIZES)
    alpha = SemanticParams().alpha
    assert [alpha[t] for t in TYPES] == sorted((alpha[t] for t in TYPES), reverse=True)


def test_an_answer_in_the_prompts_format_parses_to_exactly_its_regions():
    """Every cell, type, priority and size the prompt offers, written in its line format, comes
    back from the parser as that region of that image."""
    text = prompt_text(2)
    form = next(line for line in text.splitlines() if line.startswith("REGION: <cell>"))
    cells = [f"{c}-{r}" for c in _listed(text, "Columns, from left to right:") for r in ROWS]
    types, priorities, sizes = (_headed(text, h) for h in ("TYPES", "PRIORITY", "SIZE"))
    wanted = []
    lines = []
    for image in (1, 2):  # 6 regions each (the prompt asks for 5 to 8): all 12 cells
        lines.append(f"IMAGE {image}")
        for n, cell in enumerate(cells[6 * (image - 1) : 6 * image], start=6 * (image - 1)):
            chosen = (cell, types[n % 5], priorities[n % 3], sizes[(n // 3) % 3])
            wanted.append((image - 1, *chosen))
            values = dict(zip(("<cell>", "<type>", "<priority>", "<size>"), chosen, strict=True))
            line = re.sub(r"<[a-z]+>", lambda m, v=values: v.get(m.group(0), m.group(0)), form)
            lines.append(line.split("| REASON:")[0] + "| REASON: a view from the side.")
    result = parse_answer("\n".join(lines), 2)
    got = [(r.image_index, r.location, r.type, r.priority, r.size) for r in result.regions]
    assert got == wanted


def test_the_prompts_own_example_parses():
    example = prompt_text(1).split("Example of the form (not of the content):")[1]
    result = parse_answer(example, 1)
    assert [(r.column, r.row, r.type) for r in result.regions] == [
        ("center-left", "middle", "OCCLUSION"),
        ("right", "top", "LIGHTING"),
    ]


def test_bad_arguments_are_rejected_at_the_boundary():
    with pytest.raises(InputError, match="num_images"):
        parse_answer("IMAGE 1", 0)
    with pytest.raises(InputError, match="text"):
        parse_answer(None, 1)


def test_an_image_number_that_is_no_whole_number_is_skipped_not_moved_to_another_image():
    """ "-3" was read as 3, "4.9" and 1.7 as 4 and 1, "1e308" as 1, and regions under "IMAGE -3"
    went to the image before: each now names no image, and its regions are skipped."""
    entries = [
        {"image": 2, "region": "left-top", "type": "OCCLUSION"},  # kept, as a control
        {"image": "Image 3", "region": "right-top", "type": "LIGHTING"},  # kept
        {"image": "-3", "region": "center-top", "type": "OCCLUSION"},
        {"image": "4.9", "region": "left-bottom", "type": "OCCLUSION"},
        {"image": 1.7, "region": "right-bottom", "type": "OCCLUSION"},
        {"image": "1e308", "region": "center-bottom", "type": "OCCLUSION"},
        {"image": 1e308, "region": "left-middle", "type": "OCCLUSION"},
    ]
    result = parse_answer(json.dumps(entries), 4)
    assert [(r.image_index, r.location) for r in result.regions] == [
        (1, "left-top"),
        (2, "right-top"),
    ]
    assert len(result.skipped) == 5 and all("out of range" in s for s in result.skipped)
    text = (
        "IMAGE 1\nREGION: left-top | TYPE: OCCLUSION\nIMAGE -3\nREGION: right-top | TYPE: LIGHTING"
    )
    result = parse_answer(text, 2)
    assert [(r.image_index, r.location) for r in result.regions] == [(0, "left-top")]
    assert result.skipped and "image 0 out of range" in result.skipped[0]


def test_an_answer_of_many_junk_lines_logs_a_few_and_counts_the_rest(caplog):
    lines = ["IMAGE 1", "REGION: left-top | TYPE: OCCLUSION"]
    lines += [f"IMAGE {n + 5}\nREGION: right-top | TYPE: LIGHTING" for n in range(500)]
    with caplog.at_level(logging.INFO, logger="area3d_semantics.parser"):
        result = parse_answer("\n".join(lines), 2)
    assert len(result.skipped) == 500 and len(result.regions) == 1
    logged = [r.getMessage() for r in caplog.records]
    assert len(logged) == SKIPPED_LOGGED + 1
    assert logged[-1] == f"VLM answer: {500 - SKIPPED_LOGGED} more lines skipped"
