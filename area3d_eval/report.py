"""The evaluation report: a policy x scene table as in the paper, metric-vs-views curves, the chosen
views, uncertainty slices and time per stage, as Markdown and as one HTML page (figures as PNG files
beside them, linked relatively). This module reads the runs, aggregates their metrics into the table
and assembles the pages; the figures are drawn by `report_figures`."""

from __future__ import annotations

import html
import math
import os
import re
from collections import defaultdict
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from area3d_eval import fewer_views
from area3d_eval.report_figures import draw_figures
from area3d_eval.rundir import EVAL_DIR, MESH_FILE, Episode, read_episode, read_metrics, scene_name

# (key in metrics.json, column title, higher is better, scale for display, format). PSNR and SSIM
# are the region's (pixels where the ground truth sees the ROI): the whole-image figures also score
# the black background outside the region, which a reconstruction matches for free.
TABLE_METRICS: tuple[tuple[str, str, bool, float, str], ...] = (
    ("completion", "Comp. ratio", True, 1.0, "{:.3f}"),
    ("chamfer", "Chamfer [mm]", False, 1000.0, "{:.2f}"),
    ("fscore", "F-score", True, 1.0, "{:.3f}"),
    ("psnr_roi", "PSNR region [dB]", True, 1.0, "{:.2f}"),
    ("ssim_roi", "SSIM region", True, 1.0, "{:.3f}"),
)
# Secondary, in a table of their own: the two halves of the Chamfer distance, PSNR / SSIM over
# whole held-out images and the region PSNR split into coverage and appearance.
WHOLE_IMAGE_METRICS: tuple[tuple[str, str, bool, float, str], ...] = (
    ("accuracy", "Accuracy [mm]", False, 1000.0, "{:.2f}"),
    ("completeness", "Completeness [mm]", False, 1000.0, "{:.2f}"),
    ("psnr", "PSNR whole image [dB]", True, 1.0, "{:.2f}"),
    ("ssim", "SSIM whole image", True, 1.0, "{:.3f}"),
    ("roi_unreconstructed", "Region not reconstructed [%]", False, 100.0, "{:.1f}"),
    ("psnr_roi_reconstructed", "PSNR region, reconstructed pixels [dB]", True, 1.0, "{:.2f}"),
)

HOW_TO_READ = """\
Each run is one episode: a policy chose camera views of a scene under a view budget, starting from
the scene's initial views. The captured RGB-D frames are fused into a TSDF mesh and compared with the
scene's ground-truth surface. *Completion ratio* is the share of ground-truth surface points within
tau of the reconstruction (tau = 1 cm for objects, 5 cm for rooms); *Chamfer* is the mean of the two
average nearest-surface distances (lower is better), shown apart in the second table: *accuracy*
from the reconstruction to the ground truth, *completeness* from the ground truth to it;
*F-score* combines precision and recall at tau. *PSNR region* and *SSIM region* compare the mesh
rendered at held-out views with the simulator's images, only over the pixels where the ground truth
sees the region to reconstruct (a pixel the reconstruction leaves empty counts as black there). The
whole-image PSNR / SSIM in the second table also count the black background outside the region,
which every reconstruction matches for free: they are shown for reference only. Beside them, what
splits the region PSNR: the share of region pixels the reconstruction leaves empty (coverage) and the
PSNR over the pixels it has (appearance: colour, and geometry off its place). Cells show the mean over a row's runs (its seeds; a seed run twice counts twice) and, when there are several, ± one standard deviation;
the best value of each column is bold. The curves show how each metric grows with the number of
views: a policy whose curve rises earlier reaches the same quality with fewer views. The view plots
show where each run put its camera (grey = initial views, colour = order of the planned views); the
uncertainty slices show the planner's grid before and after the episode (bright = uncertain)."""


@dataclass
class RunRecord:
    """One run directory with its episode and metrics."""

    path: Path
    episode: Episode
    metrics: dict[str, Any]
    label: str = ""
    scene: str = ""  # the scene's name in titles and tables (`_scene_names`)
    figures: dict[str, Path] = field(default_factory=dict)
    hard_regions: str = ""  # the final grid's hard regions, in a sentence (`hard_region_text`)


def _value(v: Any) -> float:
    return float("nan") if v is None else float(v)


def load_runs(run_dirs: Sequence[Path], evaluate_missing: bool = True) -> list[RunRecord]:
    """Read every run; runs without metrics.json are evaluated first (needs the scene from
    sim_bridge) when `evaluate_missing`, else skipped."""
    records = []
    for run_dir in run_dirs:
        run_dir = Path(run_dir)
        metrics = read_metrics(run_dir)
        if metrics is None:
            if not evaluate_missing:
                continue
            from area3d_eval.evaluate import evaluate_run

            evaluate_run(run_dir)
            metrics = read_metrics(run_dir)
        episode = read_episode(run_dir)
        records.append(RunRecord(run_dir, episode, metrics))
    names = _scene_names([r.episode for r in records])
    seen: dict[str, int] = defaultdict(int)
    for r in records:
        r.scene = names[r.episode.scene]
        base = f"{r.scene} / {r.episode.policy} / seed {r.episode.seed}"
        seen[base] += 1
        r.label = base if seen[base] == 1 else f"{base} ({r.path.name})"
    return records


def _scene_names(episodes: Sequence[Episode]) -> dict[str, str]:
    """{episode.json "scene": its name in titles and tables}: the bundled name or the MJCF file's
    stem (`rundir.scene_name`); two scene files of one stem in different folders are told apart by
    their folder's name ("scene (clutter7_a)"), never by a path."""
    scenes = sorted({e.scene for e in episodes})
    stems = defaultdict(list)
    for scene in scenes:
        stems[scene_name(scene)].append(scene)
    names = {}
    for stem, same in stems.items():
        for scene in same:
            names[scene] = stem if len(same) == 1 else f"{stem} ({Path(scene).parent.name})"
    return names


def aggregate(
    run_dirs: Sequence[Path] | Sequence[RunRecord], evaluate_missing: bool = False
) -> list[dict[str, Any]]:
    """Table rows, one per (scene, policy): {"scene" (episode.json's: a name or an MJCF path),
    "scene_name" (for titles and tables), "policy", "runs", METRIC: mean, METRIC_std: std} over the
    final metrics of its runs (NaN / inf values are left out of the mean; all-undefined gives
    NaN). Sorted by scene then policy."""
    records = [r if isinstance(r, RunRecord) else None for r in run_dirs]
    if any(r is None for r in records):
        records = load_runs([Path(p) for p in run_dirs], evaluate_missing)
    labels = _row_labels(records)
    groups: dict[tuple[str, str], list[RunRecord]] = defaultdict(list)
    for r in records:
        groups[(r.episode.scene, labels[id(r)])].append(r)
    names = _scene_names([r.episode for r in records])
    rows = []
    for (scene, label), runs in sorted(groups.items()):
        row: dict[str, Any] = {
            "scene": scene,
            "scene_name": names[scene],
            "policy": runs[0].episode.policy,
            "label": label,
            "runs": len(runs),
        }
        for key, *_ in TABLE_METRICS + WHOLE_IMAGE_METRICS:
            values = np.array([_value(r.metrics.get("final", {}).get(key)) for r in runs])
            values = values[np.isfinite(values)]
            row[key] = float(values.mean()) if values.size else float("nan")
            row[f"{key}_std"] = float(values.std()) if values.size > 1 else 0.0
        rows.append(row)
    return rows


def view_curves(records: Sequence[RunRecord]) -> dict[tuple[str, str], list[list[dict]]]:
    """{(scene's name, row label): the metric-vs-views curve of each of its runs}, the rows of
    `aggregate`."""
    labels = _row_labels(records)
    curves: dict[tuple[str, str], list[list[dict]]] = defaultdict(list)
    for r in records:
        curves[(r.scene, labels[id(r)])].append(r.metrics.get("curve") or [])
    return dict(curves)


def _row_labels(records: Sequence[RunRecord]) -> dict[int, str]:
    """{id(record): its row's name}: the policy, with the view budget, mode and depth source
    added where runs of one policy differ in them (runs of 25 and of 10 views are not seeds of
    one row, and their mean would be no one's)."""

    def settings(e: Episode) -> dict[str, str]:
        return {
            "budget": f"{e.budget} views",
            "mode": e.mode,
            "depth": f"{e.depth_source} depth",
        }

    differ: dict[str, list[str]] = {}
    for policy in {r.episode.policy for r in records}:
        seen = [settings(r.episode) for r in records if r.episode.policy == policy]
        differ[policy] = [k for k in seen[0] if len({s[k] for s in seen}) > 1]
    labels = {}
    for r in records:
        keys, mine = differ[r.episode.policy], settings(r.episode)
        extra = ", ".join(mine[k] for k in keys)
        labels[id(r)] = f"{r.episode.policy} ({extra})" if extra else r.episode.policy
    return labels


def _cell(row: dict[str, Any] | None, key: str, scale: float, fmt: str) -> str:
    if row is None or not math.isfinite(row.get(key, float("nan"))):
        return "–"
    text = fmt.format(row[key] * scale)
    if row["runs"] > 1:
        text += " ± " + fmt.format(row[f"{key}_std"] * scale)
    return text


def _table(
    rows: list[dict[str, Any]],
    metrics: tuple[tuple[str, str, bool, float, str], ...] = TABLE_METRICS,
) -> tuple[list[str], list[str], list[list[str]], list[list[bool]]]:
    """(scene names, policies, cells[policy][scene x metric], bold[policy][...]) of the
    paper-style table."""
    scenes = sorted({r["scene"] for r in rows})
    names = {r["scene"]: r["scene_name"] for r in rows}
    policies = sorted({r["label"] for r in rows})
    index = {(r["scene"], r["label"]): r for r in rows}
    cells, bold = [], []
    best: dict[tuple[str, str], float] = {}
    for scene in scenes:
        for key, _, higher, *_ in metrics:
            values = [
                index[(scene, p)][key]
                for p in policies
                if (scene, p) in index and math.isfinite(index[(scene, p)][key])
            ]
            if values:
                best[(scene, key)] = max(values) if higher else min(values)
    for policy in policies:
        row_cells, row_bold = [], []
        for scene in scenes:
            r = index.get((scene, policy))
            for key, _, _, scale, fmt in metrics:
                row_cells.append(_cell(r, key, scale, fmt))
                row_bold.append(
                    r is not None
                    and len(policies) > 1
                    and (scene, key) in best
                    and r[key] == best[(scene, key)]
                )
        cells.append(row_cells)
        bold.append(row_bold)
    return [names[s] for s in scenes], policies, cells, bold


def stopped_text(episode: Episode) -> str:
    """A run that ended before its budget, in a sentence."""
    return (
        f"Stopped early after {len(episode.views)} of {episode.budget} views: "
        f"{episode.stopped_early}."
    )


def semantics_text(episode: Episode) -> str:
    """Where the run's semantic regions came from, in a sentence ("" when it says nothing)."""
    s = episode.semantics
    if not s or not s.get("backend"):
        return ""
    if s["backend"] == "none":
        return "No semantic guidance (semantics backend `none`)."
    if s.get("fallback_used"):
        return (
            f"Semantic regions from the `{s['fallback_used']}` fallback, not from the "
            f"`{s['backend']}` backend: {s.get('error') or 'no reason given'}."
        )
    return f"Semantic regions from the `{s['backend']}` backend."


def _mesh_path(r: RunRecord, out_dir: Path) -> str:
    """The run's mesh file, relative to the report (the runs need not lie below it)."""
    return Path(os.path.relpath(r.path / EVAL_DIR / MESH_FILE, out_dir)).as_posix()


def _rel(path: Path, out_dir: Path) -> str:
    return Path(path).resolve().relative_to(out_dir.resolve()).as_posix()


def write_report(
    run_dirs: Sequence[Path],
    out_dir: Path,
    evaluate_missing: bool = True,
    title: str = "AREA3D evaluation report",
) -> tuple[Path, Path]:
    """Write out_dir/report.md and out_dir/report.html (figures in out_dir/figures/).

    Runs without metrics.json are evaluated first when `evaluate_missing` (see `load_runs`).
    Returns (md_path, html_path).
    """
    out_dir = Path(out_dir)
    fig_dir = out_dir / "figures"
    fig_dir.mkdir(parents=True, exist_ok=True)
    records = load_runs([Path(p) for p in run_dirs], evaluate_missing)
    rows = aggregate(records)
    scenes, policies, cells, bold = _table(rows)
    fewer = fewer_views.views_to_reach(view_curves(records))
    whole = _table(rows, WHOLE_IMAGE_METRICS)[2:]
    curves, timing_png = draw_figures(records, fig_dir) if records else ({}, None)
    md_path = out_dir / "report.md"
    html_path = out_dir / "report.html"
    parts = (title, records, scenes, policies, (cells, bold), whole, fewer, curves, timing_png)
    md_path.write_text(_markdown(*parts, out_dir))
    html_path.write_text(_html(*parts, out_dir))
    return md_path, html_path


def _markdown_table(scenes, policies, cells, bold, metrics) -> list[str]:
    arrows = {name: ("↑" if higher else "↓") for _, name, higher, *_ in metrics}
    header = ["Policy"] + [
        f"{scene}: {name} {arrows[name]}" for scene in scenes for _, name, *_ in metrics
    ]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for policy, row_cells, row_bold in zip(policies, cells, bold, strict=True):
        shown = [f"**{c}**" if b else c for c, b in zip(row_cells, row_bold, strict=True)]
        lines.append("| " + " | ".join([policy, *shown]) + " |")
    return lines


def _markdown(
    title, records, scenes, policies, headline, whole, fewer, curves, timing_png, out_dir
) -> str:
    lines = [f"# {title}", "", "## How to read this report", "", HOW_TO_READ, "", "## Results", ""]
    if not records:
        lines += ["No evaluated runs.", ""]
        return "\n".join(lines)
    lines += _markdown_table(scenes, policies, *headline, TABLE_METRICS)
    lines += [
        "",
        "Accuracy and completeness (the Chamfer distance's halves), whole-image PSNR / SSIM"
        " (secondary: they also score the black background) and the region PSNR split into"
        " coverage and appearance:",
        "",
    ]
    lines += _markdown_table(scenes, policies, *whole, WHOLE_IMAGE_METRICS)
    lines += [
        "",
        f"Runs: {len(records)}. Thresholds tau: "
        + ", ".join(sorted({f"{r.scene} {r.metrics.get('tau')} m" for r in records}))
        + ".",
        "",
    ]
    lines += fewer_views.markdown_lines(fewer)
    lines += ["## Metrics against the number of views", ""]
    for scene in scenes:
        lines += [f"### {scene}", ""]
        lines += [
            f"![{scene} {metric}]({_rel(png, out_dir)})"
            for metric, png in curves.get(scene, {}).items()
        ]
        lines.append("")
    lines += ["## Chosen views", ""]
    for r in records:
        lines += [f"### {r.label}", "", f"![views]({_rel(r.figures['views'], out_dir)})", ""]
        if r.episode.stopped_early:
            lines += [stopped_text(r.episode), ""]
        if said := semantics_text(r.episode):
            lines += [said, ""]
    lines += ["## Reconstruction", ""]
    meshed = [r for r in records if "mesh" in r.figures]
    for r in meshed:
        lines += [f"### {r.label}", "", f"![mesh]({_rel(r.figures['mesh'], out_dir)})", ""]
        lines += [f"The mesh: `{_mesh_path(r, out_dir)}`.", ""]
    if not meshed:
        lines += [f"No run was evaluated into a mesh ({EVAL_DIR}/{MESH_FILE}).", ""]
    lines += ["## Uncertainty before and after", ""]
    with_grids = [r for r in records if "uncertainty" in r.figures]
    for r in with_grids:
        lines += [
            f"### {r.label}",
            "",
            f"![uncertainty]({_rel(r.figures['uncertainty'], out_dir)})",
            "",
        ]
        if r.hard_regions:
            lines += [r.hard_regions, ""]
    if not with_grids:
        lines += ["No run saved its uncertainty grid (grid_initial.npz / grid_final.npz).", ""]
    lines += ["## Time per stage", ""]
    lines += (
        [f"![timings]({_rel(timing_png, out_dir)})", ""]
        if timing_png
        else ["No timings recorded.", ""]
    )
    return "\n".join(lines)


CSS = """
body { font-family: system-ui, sans-serif; margin: 2em auto; max-width: 1200px; color: #222; }
table { border-collapse: collapse; font-size: 0.85em; margin: 1em 0; }
th, td { border: 1px solid #ccc; padding: 0.3em 0.6em; text-align: center; }
th { background: #f2f2f2; }
td.policy { text-align: left; font-weight: 600; }
img { max-width: 100%; margin: 0.5em 0; border: 1px solid #eee; }
.figs { display: flex; flex-wrap: wrap; gap: 1em; }
.figs img { max-width: 48%; }
p.howto { background: #f8f8f8; padding: 1em; border-left: 4px solid #888; }
"""


def _html_table(scenes, policies, cells, bold, metrics) -> list[str]:
    e = html.escape
    parts = ["<table><tr><th rowspan='2'>Policy</th>"]
    parts += [f"<th colspan='{len(metrics)}'>{e(s)}</th>" for s in scenes]
    parts.append("</tr><tr>")
    parts += [
        f"<th>{e(name)} {'&uarr;' if higher else '&darr;'}</th>"
        for _ in scenes
        for _, name, higher, *_ in metrics
    ]
    parts.append("</tr>")
    for policy, row_cells, row_bold in zip(policies, cells, bold, strict=True):
        tds = "".join(
            f"<td>{'<b>' + e(c) + '</b>' if b else e(c)}</td>"
            for c, b in zip(row_cells, row_bold, strict=True)
        )
        parts.append(f"<tr><td class='policy'>{e(policy)}</td>{tds}</tr>")
    parts.append("</table>")
    return parts


def _inline(text: str) -> str:
    """Text the Markdown report writes with `code` and *emphasis*, as HTML (escaped first)."""
    out = html.escape(text)
    out = re.sub(r"`([^`]+)`", r"<code>\1</code>", out)
    return re.sub(r"(?<![\w*])\*([^*\s][^*]*?)\*(?![\w*])", r"<em>\1</em>", out)


def _html(
    title, records, scenes, policies, headline, whole, fewer, curves, timing_png, out_dir
) -> str:
    e = html.escape
    parts = [
        f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{e(title)}</title><style>{CSS}</style></head><body>"
    ]
    parts.append(
        f"<h1>{e(title)}</h1><h2>How to read this report</h2><p class='howto'>{_inline(HOW_TO_READ)}</p><h2>Results</h2>"
    )
    if not records:
        parts.append("<p>No evaluated runs.</p></body></html>")
        return "".join(parts)
    parts += _html_table(scenes, policies, *headline, TABLE_METRICS)
    parts.append(
        "<p>Accuracy and completeness (the Chamfer distance's halves), whole-image PSNR / SSIM"
        " (secondary: they also score the black background) and the region PSNR split into"
        " coverage and appearance:</p>"
    )
    parts += _html_table(scenes, policies, *whole, WHOLE_IMAGE_METRICS)
    parts += fewer_views.html_parts(fewer)
    parts.append("<h2>Metrics against the number of views</h2>")
    for scene in scenes:
        imgs = "".join(
            f"<img src='{e(_rel(png, out_dir))}' alt='{e(scene)} {e(metric)}'>"
            for metric, png in curves.get(scene, {}).items()
        )
        parts.append(f"<h3>{e(scene)}</h3><div class='figs'>{imgs}</div>")
    parts.append("<h2>Chosen views</h2>")
    for r in records:
        parts.append(
            f"<h3>{e(r.label)}</h3><img src='{e(_rel(r.figures['views'], out_dir))}' alt='views'>"
        )
        if r.episode.stopped_early:
            parts.append(f"<p>{_inline(stopped_text(r.episode))}</p>")
        if said := semantics_text(r.episode):
            parts.append(f"<p>{_inline(said)}</p>")
    parts.append("<h2>Reconstruction</h2>")
    meshed = [r for r in records if "mesh" in r.figures]
    for r in meshed:
        parts.append(
            f"<h3>{e(r.label)}</h3><img src='{e(_rel(r.figures['mesh'], out_dir))}' alt='mesh'>"
            f"<p>The mesh: <code>{e(_mesh_path(r, out_dir))}</code></p>"
        )
    if not meshed:
        parts.append(f"<p>No run was evaluated into a mesh ({EVAL_DIR}/{MESH_FILE}).</p>")
    parts.append("<h2>Uncertainty before and after</h2>")
    with_grids = [r for r in records if "uncertainty" in r.figures]
    for r in with_grids:
        parts.append(
            f"<h3>{e(r.label)}</h3><img src='{e(_rel(r.figures['uncertainty'], out_dir))}' alt='uncertainty'>"
        )
        if r.hard_regions:
            parts.append(f"<p>{_inline(r.hard_regions)}</p>")
    if not with_grids:
        parts.append(
            "<p>No run saved its uncertainty grid (grid_initial.npz / grid_final.npz).</p>"
        )
    parts.append("<h2>Time per stage</h2>")
    parts.append(
        f"<img src='{e(_rel(timing_png, out_dir))}' alt='timings'>"
        if timing_png
        else "<p>No timings recorded.</p>"
    )
    parts.append("</body></html>")
    return "".join(parts)
