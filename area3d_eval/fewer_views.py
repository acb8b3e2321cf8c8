"""How many views each policy needs to reach a reference policy's final completion, per scene:
the paper's "fewer views" claim as a figure. A row's curve is the mean over its seeds of the
completion evaluated after each checkpoint (`evaluate.default_checkpoints`: every 4th view, 60 %
of the budget and the last), so the answer is the first checkpoint reached, not the exact view:
"9 of 15" means reached after 9 views and not after 8."""

from __future__ import annotations

import html
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

REFERENCE_POLICY = "uniform"


def mean_curve(curves: Sequence[Sequence[Mapping[str, Any]]], key: str = "completion") -> dict:
    """{number of views: mean of `key` over the runs} at the checkpoints every run evaluated with a
    finite value (a run whose checkpoints differ from the others' leaves out the ones it lacks)."""
    per_run = []
    for curve in curves:
        values = {}
        for point in curve:
            value = point.get(key)
            if value is not None and np.isfinite(float(value)):
                values[int(point["num_views"])] = float(value)
        per_run.append(values)
    if not per_run:
        return {}
    common = set.intersection(*(set(values) for values in per_run))
    return {n: float(np.mean([values[n] for values in per_run])) for n in sorted(common)}


def views_to_reach(
    rows: Mapping[tuple[str, str], Sequence[Sequence[Mapping[str, Any]]]],
    reference: str = REFERENCE_POLICY,
) -> list[dict[str, Any]]:
    """rows: {(scene, row label): the curves of its runs}. For every scene with a `reference` row,
    one entry per row of that scene (the reference included: it may plateau before its last view):
    {"scene", "label", "target" (the reference's final mean completion), "views" (the first
    checkpoint whose mean completion reaches the target, None if none does), "last_views",
    "last" (the row's own final mean completion)}. Sorted by scene, then label."""
    means = {name: mean_curve(curves) for name, curves in rows.items()}
    out = []
    for (scene, label), curve in sorted(means.items()):
        ref = means.get((scene, reference))
        if not ref or not curve:
            continue
        target = ref[max(ref)]
        reached = [n for n, value in curve.items() if value >= target]
        out.append(
            {
                "scene": scene,
                "label": label,
                "target": target,
                "views": min(reached) if reached else None,
                "last_views": max(curve),
                "last": curve[max(curve)],
            }
        )
    return out


def cell(entry: Mapping[str, Any]) -> str:
    """ "9 of 15 (60 %)", or "not reached (0.943 < 0.951)"."""
    if entry["views"] is None:
        return f"not reached ({entry['last']:.3f} < {entry['target']:.3f})"
    share = 100.0 * entry["views"] / entry["last_views"]
    return f"{entry['views']} of {entry['last_views']} ({share:.0f} %)"


def grid(entries: Sequence[Mapping[str, Any]]) -> tuple[list[str], list[str], list[list[str]]]:
    """(scenes, row labels, cells[label][scene]) of the entries, "–" where a row lacks a scene."""
    scenes = sorted({e["scene"] for e in entries})
    labels = sorted({e["label"] for e in entries})
    found = {(e["scene"], e["label"]): e for e in entries}
    cells = [
        [cell(found[(s, label)]) if (s, label) in found else "–" for s in scenes]
        for label in labels
    ]
    return scenes, labels, cells


INTRO = (
    "The first checkpoint at which a row's mean completion reaches `{reference}`'s final mean"
    " completion on the same scene, of the views it took (checkpoints: every 4th view, 60 % of the"
    " budget and the last)."
)


def markdown_lines(entries: Sequence[Mapping[str, Any]], reference: str = REFERENCE_POLICY):
    if not entries:
        return []
    scenes, labels, cells = grid(entries)
    intro = INTRO.format(reference=reference)
    lines = [f"## Views to reach `{reference}`'s final completion", "", intro, ""]
    lines += ["| Policy | " + " | ".join(scenes) + " |", "|" + "---|" * (len(scenes) + 1)]
    lines += [
        f"| {label} | " + " | ".join(row) + " |" for label, row in zip(labels, cells, strict=True)
    ]
    return [*lines, ""]


def html_parts(entries: Sequence[Mapping[str, Any]], reference: str = REFERENCE_POLICY):
    if not entries:
        return []
    e = html.escape
    scenes, labels, cells = grid(entries)
    code = f"<code>{e(reference)}</code>"
    intro = e(INTRO.format(reference=reference)).replace(f"`{e(reference)}`", code)
    head = "".join(f"<th>{e(s)}</th>" for s in scenes)
    parts = [f"<h2>Views to reach {code}'s final completion</h2><p>{intro}</p>"]
    parts.append(f"<table><tr><th>Policy</th>{head}</tr>")
    for label, row in zip(labels, cells, strict=True):
        tds = "".join(f"<td>{e(c)}</td>" for c in row)
        parts.append(f"<tr><td class='policy'>{e(label)}</td>{tds}</tr>")
    parts.append("</table>")
    return parts
