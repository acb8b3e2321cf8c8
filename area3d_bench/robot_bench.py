"""`area3d bench robot`: a whole object mission beside a robot stack (`robot.py`), once with a
triggered camera (one frame per view: the reference) and once per streaming setting, every row
from the same code in one run; prints what the mission manager and the nodes saw side by side.

Per run: the answers (succeeded / asked), NextBestView round trips (p50, p95, max: what the
mission manager waited, the planner's wait for the request's frame included), the answers whose
message says they planned from an older map or repeat a view; the driver's frames published and
its late frame slots (the renderer could not keep the camera's clock); perception's frames
paired, missed (whole frames absent from the stream), its pairing rate, keyframes integrated and
frames skipped; the planner's frames fused and dropped; the final grid's coverage (the share of
the ground-truth surface inside the region within one voxel of an occupied voxel); each node's
resident memory at the first request and at the end. Targets (issue: a streaming camera on a
moving robot): NextBestView p95 < 0.5 s on an object, pairing rate >= 0.8, coverage >= the
triggered camera's, memory flat.
"""

from __future__ import annotations

import json
import math
import os
import platform
import subprocess
import tempfile
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from area3d_bench.robot import MissionOptions, MissionResult, occupied_in_region, run_mission
from area3d_bringup.launch_description import scene_parameters
from area3d_eval.metrics import ReferenceSurface, distance_metrics
from sim_bridge.scenes import load_scene

# name -> the driver's settings; "triggered" is the reference every other row is compared with
RUNS = {
    "triggered": {"stream_hz": 0.0},
    "stream": {},
    "stream-lossy": {"loss": 1 / 3},
    "stream-default-dds": {"driver_profile": "default"},
}
DEFAULT_RUNS = "triggered,stream,stream-default-dds"
NBV_P95_TARGET_S = 0.5  # object level (room: 1 s)
PAIRING_TARGET = 0.8
SURFACE_POINTS = 20_000


@dataclass
class RunFigures:
    name: str
    seed: int
    answers_ok: int
    answers: int
    nbv_s: list[float]
    stale_answers: int
    repeat_answers: int
    driver_published: int
    retriggers: int
    driver_late: int
    parts_lost_by_driver: int
    perception_paired: int
    perception_missed: int
    pairing_rate: float | None
    integrated: int
    skipped: int
    parts_unpaired: int
    planner_fused: int
    planner_dropped_backlog: int
    coverage: float
    rss_mb: dict[str, tuple[float, float]]
    budget: dict


def coverage(result: MissionResult, scene_name: str) -> float:
    """The share of the ground-truth surface inside the region that lies within one voxel
    (its half diagonal) of an occupied voxel's centre in the mission's final grid."""
    region = scene_parameters(scene_name)["planner"]
    lo, hi = np.array(region["roi_min"]), np.array(region["roi_max"])
    reference = ReferenceSurface(load_scene(scene_name).ground_truth_mesh(), SURFACE_POINTS)
    gt = reference.points[np.all((reference.points >= lo) & (reference.points <= hi), axis=1)]
    occupied = occupied_in_region(result.grid, lo, hi)
    if len(gt) == 0 or len(occupied) == 0:
        return 0.0
    xs = np.unique(np.round(occupied[:, 0], 6))
    voxel = float(np.min(np.diff(xs))) if len(xs) > 1 else 0.01
    # the evaluation's recall: the share of ground-truth points within tau of the occupied centres
    return distance_metrics(occupied, gt, 0.5 * math.sqrt(3) * voxel + 1e-9)["recall"]


def figures(name: str, seed: int, result: MissionResult, scene_name: str) -> RunFigures:
    planner, perception = result.planner_status, result.statuses.get("perception", {})
    messages = [answer.message for answer, _ in result.answers]
    return RunFigures(
        name=name,
        seed=seed,
        answers_ok=sum(answer.success for answer, _ in result.answers),
        answers=len(result.answers),
        nbv_s=[seconds for _, seconds in result.answers],
        stale_answers=sum("not fused within" in m for m in messages),
        repeat_answers=sum("handed out before" in m for m in messages),
        driver_published=int(result.driver.get("frames_published", 0)),
        retriggers=result.retriggers,
        driver_late=int(result.driver.get("frames_late", 0)),
        parts_lost_by_driver=int(result.driver.get("parts_lost", 0)),
        perception_paired=int(perception.get("frames_paired", 0)),
        perception_missed=int(perception.get("frames_missed", 0)),
        pairing_rate=perception.get("pairing_rate"),
        integrated=int(perception.get("frames_integrated", 0)),
        skipped=int(perception.get("frames_skipped", 0)),
        parts_unpaired=int(perception.get("parts_dropped_unpaired", 0)),
        planner_fused=int(planner.get("frames_fused", 0)),
        planner_dropped_backlog=int(planner.get("frames_dropped_backlog", 0)),
        coverage=coverage(result, scene_name),
        rss_mb={k: v for k, v in result.rss_mb.items() if k != "semantics"},
        budget=planner.get("budget", {}),
    )


def _spread(values: list[float], fmt: str) -> str:
    """mean, and min-max over seeds when there are several."""
    values = [v for v in values if v is not None and np.isfinite(v)]
    if not values:
        return "-"
    text = format(float(np.mean(values)), fmt)
    if len(values) > 1:
        text += f" ({format(min(values), fmt)}-{format(max(values), fmt)})"
    return text


def _machine() -> str:
    try:
        commit = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"],
            capture_output=True, text=True, cwd=Path(__file__).parent, check=False,
        ).stdout.strip()  # fmt: skip
    except OSError:
        commit = ""
    return f"{platform.machine()}, {os.cpu_count()} cores, commit {commit or 'unknown'}"


def print_table(rows: list[RunFigures], title: str) -> None:
    from rich.console import Console
    from rich.table import Table

    names = list(dict.fromkeys(r.name for r in rows))
    by_name = {name: [r for r in rows if r.name == name] for name in names}
    reference = by_name.get("triggered")
    table = Table(title=title)
    table.add_column("figure", justify="left")
    for name in names:
        table.add_column(name, justify="right")
    table.add_column("target", justify="right")

    def row(label: str, values, fmt: str, target: str = "") -> None:
        table.add_row(
            label, *(_spread([values(r) for r in by_name[n]], fmt) for n in names), target
        )

    def pct(values: list[float], q: float) -> float:
        return float(np.percentile(values, q)) if values else float("nan")

    row("answers succeeded", lambda r: r.answers_ok, ".0f")
    row("NextBestView p50, s", lambda r: pct(r.nbv_s, 50), ".3f")
    row("NextBestView p95, s", lambda r: pct(r.nbv_s, 95), ".3f", f"< {NBV_P95_TARGET_S:g}")
    row("NextBestView max, s", lambda r: max(r.nbv_s, default=float("nan")), ".3f")
    if reference:
        ref95 = np.mean([pct(r.nbv_s, 95) for r in reference])
        row("  p95 / triggered's", lambda r: pct(r.nbv_s, 95) / ref95, ".2f")
    row("answers from an older map", lambda r: r.stale_answers, ".1f", "0")
    row("answers repeating a view", lambda r: r.repeat_answers, ".1f")
    row("driver: frames published", lambda r: r.driver_published, ".0f")
    row("driver: late frame slots", lambda r: r.driver_late, ".0f", "0")
    row("triggered frames lost, captured again", lambda r: r.retriggers, ".0f", "0")
    row("driver: parts it dropped on purpose", lambda r: r.parts_lost_by_driver, ".0f")
    row("perception: frames paired", lambda r: r.perception_paired, ".0f")
    row("perception: frames missed (stamp gaps)", lambda r: r.perception_missed, ".0f")
    row("perception: parts unpaired", lambda r: r.parts_unpaired, ".0f")
    row("perception: pairing rate", lambda r: r.pairing_rate, ".2f", f">= {PAIRING_TARGET:g}")
    row("perception: keyframes integrated", lambda r: r.integrated, ".0f")
    row("perception: frames skipped", lambda r: r.skipped, ".0f")
    row("planner: frames fused", lambda r: r.planner_fused, ".0f")
    row("planner: frames dropped, backlog", lambda r: r.planner_dropped_backlog, ".0f", "0")
    row("coverage of the region's surface", lambda r: r.coverage, ".3f", ">= triggered")
    if reference:
        ref_cov = np.mean([r.coverage for r in reference])
        row("  coverage / triggered's", lambda r: r.coverage / ref_cov, ".3f", ">= 1")
    for node in ("perception", "planner"):
        row(
            f"{node} RSS at 1st request, MB", lambda r, n=node: r.rss_mb.get(n, (np.nan,))[0], ".0f"
        )
        row(
            f"{node} RSS at the end, MB",
            lambda r, n=node: r.rss_mb.get(n, (np.nan, np.nan))[1],
            ".0f",
            "flat",
        )
    Console().print(table)


def run_bench(
    runs: str = DEFAULT_RUNS,
    seeds: int = 1,
    planned: int = 10,
    stream_hz: float = 30.0,
    render_scale: float = 1.0,
    scene: str = "single_object",
    json_out: Path | None = None,
) -> list[RunFigures]:
    """Run each named mission (`RUNS`) for `seeds` seeds; print the table; returns the rows."""
    names = [name.strip() for name in runs.split(",") if name.strip()]
    unknown = [name for name in names if name not in RUNS]
    if unknown or not names:
        raise ValueError(f"runs: got {runs!r}, expected a comma list of {', '.join(RUNS)}")
    rows: list[RunFigures] = []
    for seed in range(seeds):
        for name in names:
            settings = {
                "scene": scene,
                "planned": planned,
                "stream_hz": stream_hz,
                "tf": True,
                "render_scale": render_scale,
                "seed": seed,
            }
            options = MissionOptions(**(settings | RUNS[name]))
            with tempfile.TemporaryDirectory(prefix="area3d-robot-") as workdir:
                result = run_mission(options, Path(workdir))
            rows.append(figures(name, seed, result, scene))
    width, height = round(848 * render_scale), round(480 * render_scale)
    title = (
        f"robot: {scene}, {planned} views asked one at a time after the initial ones; streams "
        f"{width}x{height} at {stream_hz:g} Hz on a TF chain; {seeds} seed(s); {_machine()}"
    )
    print_table(rows, title)
    if json_out is not None:
        json_out.write_text(
            json.dumps({"title": title, "rows": [asdict(r) for r in rows]}, indent=1)
        )
    return rows
