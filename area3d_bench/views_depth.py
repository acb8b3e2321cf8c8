"""`area3d bench views-depth RUN_ROOT`: what an estimated-depth episode lost to its views and what
to its depth.

An episode run with `--depth-source estimated` keeps, in every frame, the camera's depth beside
perception's. Its views are rebuilt here from the camera's depth (`evaluate_run` with
`depth_source="sensor"`, nothing written), so for each policy and scene the table shows, as means
over the seeds found: completion and region PSNR as the episode ran; the same with the camera's
depth at the same views; and the share of the region's pixels in its planned views whose estimated
depth is within 1 cm + 1 % of the camera's. Two policies that differ as run but not with the
camera's depth chose equally good views; the depth measured at them made the difference.

RUN_ROOT is any folder of run directories, e.g. an `area3d bench episode --depth-source
estimated` output. The figures are also written to RUN_ROOT/views_depth.json.
"""

from __future__ import annotations

import json
from collections.abc import Iterable
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
from rich.console import Console
from rich.table import Table

from area3d_eval.depth_metrics import depth_right
from area3d_eval.rundir import (
    EPISODE_FILE,
    METRICS_FILE,
    frame_files,
    read_episode,
    read_frame,
    write_json,
)
from area3d_msgs_py.backproject import roi_pixels

OUT_FILE = "views_depth.json"


def find_runs(root: Path) -> list[Path]:
    """Run directories under `root` (itself included) recorded with estimated depth and frames,
    sorted."""
    root = Path(root)
    found = []
    for episode in sorted(root.rglob(EPISODE_FILE)):
        run = episode.parent
        if frame_files(run) and read_episode(run).depth_source == "estimated":
            found.append(run)
    return found


def right_share(
    estimated: np.ndarray,
    depth: np.ndarray,
    K: np.ndarray,
    T_world_cam: np.ndarray,
    roi_min: np.ndarray,
    roi_max: np.ndarray,
) -> tuple[int, int]:
    """(right, counted): of the pixels whose camera depth lands in the region of interest
    (counted), those whose estimated depth is right (`depth_right`: within 1 cm + 1 % of the
    camera's; no estimate is not right)."""
    inside = roi_pixels(depth, K, T_world_cam, roi_min, roi_max)
    right = depth_right(estimated[inside], depth[inside])
    return int(right.sum()), int(inside.sum())


def _as_run(run_dir: Path, scene, evaluation: dict, checkpoints: list[int]) -> dict:
    """The run's final figures with its estimated depth: its metrics.json when that was evaluated
    from the estimated depth with evaluate_run's defaults (no `evaluation` given), else
    evaluated now with `evaluation`."""
    metrics = run_dir / METRICS_FILE
    if metrics.is_file() and not evaluation:
        data = json.loads(metrics.read_text())
        if data.get("final") and data.get("depth_source") == "estimated":
            return data["final"]
    from area3d_eval.evaluate import evaluate_run

    result = evaluate_run(
        run_dir, scene, checkpoints, write=False, depth_source="estimated", **evaluation
    )
    return result["final"]


def run_figures(run_dir: Path, **evaluation) -> dict:
    """One run's figures: scene, policy, seed; completion and region PSNR as run and with the
    camera's depth at its views; the planned views' right share (None without planned views).
    `evaluation`: keyword arguments of `evaluate_run` (its image size, surface points) for both
    evaluations; the run's own metrics.json is read as it is when it exists."""
    from area3d_eval.evaluate import evaluate_run
    from sim_bridge.scenes import load_scene

    run_dir = Path(run_dir)
    episode = read_episode(run_dir)
    scene = load_scene(episode.scene)
    files = frame_files(run_dir)
    checkpoints = [len(files)]  # the final figures only
    run = _as_run(run_dir, scene, evaluation, checkpoints)
    camera = evaluate_run(
        run_dir, scene, checkpoints, write=False, depth_source="sensor", **evaluation
    )["final"]
    right = counted = 0
    for path in files[episode.num_initial :]:
        frame = read_frame(path)
        if frame.estimated_depth is None:
            continue
        r, n = right_share(
            frame.estimated_depth,
            frame.depth,
            frame.K,
            frame.T_world_cam,
            scene.roi_min,
            scene.roi_max,
        )
        right, counted = right + r, counted + n
    return {
        "run": run_dir.name,
        "scene": episode.scene_name,
        "policy": episode.policy,
        "seed": episode.seed,
        "completion": run["completion"],
        "psnr": run.get("psnr_roi"),
        "camera_completion": camera["completion"],
        "camera_psnr": camera.get("psnr_roi"),
        "planned_right": right / counted if counted else None,
    }


FIELDS = ("completion", "camera_completion", "psnr", "camera_psnr", "planned_right")


def summarise(rows: Iterable[dict], fields: Iterable[str] = FIELDS) -> dict[tuple[str, str], dict]:
    """{(scene, policy): {field: mean over its seeds (None where no seed has it), "seeds": n}}
    for each of `fields`."""
    groups: dict[tuple[str, str], list[dict]] = {}
    for row in rows:
        groups.setdefault((row["scene"], row["policy"]), []).append(row)
    out = {}
    for key, group in groups.items():
        cell: dict = {"seeds": len(group)}
        for field in fields:
            values = [r[field] for r in group if r[field] is not None]
            cell[field] = float(np.mean(values)) if values else None
        out[key] = cell
    return out


def _fmt(value, digits: int) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def policy_means(
    summary: dict[tuple[str, str], dict], fields: Iterable[str] = FIELDS
) -> dict[str, dict]:
    """{policy: {field: mean over its scenes (None unless every scene has it), "scenes": n}} for
    each of `fields`."""
    out = {}
    for policy in sorted({p for _, p in summary}):
        cells = [c for (_, p), c in summary.items() if p == policy]
        mean: dict = {"scenes": len(cells)}
        for field in fields:
            values = [c[field] for c in cells]
            mean[field] = None if None in values else float(np.mean(values))
        out[policy] = mean
    return out


COLUMNS = (
    ("completion", "completion as run", 3),
    ("camera_completion", "completion, camera depth", 3),
    ("psnr", "PSNR as run", 2),
    ("camera_psnr", "PSNR, camera depth", 2),
    ("planned_right", "planned views right", 3),
)


def print_table(summary: dict[tuple[str, str], dict], console: Console | None = None) -> None:
    """Per scene and policy, then each policy's mean over the scenes."""
    table = Table(
        title="the same views with the camera's depth (means over seeds)",
        caption="planned views right: share of the region's pixels in the planned views whose "
        "estimated depth is within 1 cm + 1 % of the camera's (no estimate counts as not right; "
        "over the seeds that have planned views)",
    )
    table.add_column("scene", no_wrap=True)
    table.add_column("policy", no_wrap=True)
    table.add_column("seeds")
    for _, name, _ in COLUMNS:
        table.add_column(name)
    for (scene, policy), c in sorted(summary.items()):
        cells = [_fmt(c[field], digits) for field, _, digits in COLUMNS]
        table.add_row(scene, policy, str(c["seeds"]), *cells)
    for policy, c in policy_means(summary).items():
        cells = [_fmt(c[field], digits) for field, _, digits in COLUMNS]
        table.add_row(f"mean ({c['scenes']} scenes)", policy, "", *cells)
    (console or Console(width=160)).print(table)


def _figures_or_error(run: Path, evaluation: dict) -> dict:
    """`run_figures`, or {"run", "error"} naming what went wrong: one bad run (a frame cut
    short, a scene file moved) does not cost the others' figures."""
    try:
        return run_figures(run, **evaluation)
    except Exception as err:  # reported in the table's place, with the run named
        return {"run": str(run), "error": f"{type(err).__name__}: {err}"}


def figures_of_runs(root: Path, figures_or_error, argument, workers: int) -> tuple[list, list]:
    """(rows, errors): `figures_or_error(run, argument)` of every estimated-depth run under
    `root` (`find_runs`), in `workers` processes when more than 1; rows holding "error" apart.
    A missing folder or one without such runs is refused, naming it."""
    root = Path(root)
    if not root.is_dir():
        raise ValueError(f"run root: got {str(root)!r}, expected an existing folder")
    runs = find_runs(root)
    if not runs:
        raise ValueError(
            f"run root: got {str(root)!r}, expected run directories recorded with "
            "--depth-source estimated (episode.json and frames/)"
        )
    if workers > 1:
        with ProcessPoolExecutor(workers) as pool:
            rows = list(pool.map(figures_or_error, runs, [argument] * len(runs)))
    else:
        rows = [figures_or_error(run, argument) for run in runs]
    return [r for r in rows if "error" not in r], [r for r in rows if "error" in r]


def run_bench(root: Path, workers: int = 1, **evaluation) -> dict:
    """Figures of every estimated-depth run under `root`, printed and written to
    root/views_depth.json; returns {"runs": [...], "summary": [...], "policy_means": {...},
    "errors": [...]}. `evaluation`: keyword arguments of `evaluate_run` (see `run_figures`)."""
    root = Path(root)
    rows, errors = figures_of_runs(root, _figures_or_error, evaluation, workers)
    summary = summarise(rows)
    console = Console(width=160)
    if summary:
        print_table(summary, console)
    for row in errors:
        console.print(f"not evaluated: {row['run']}: {row['error']}", soft_wrap=True)
    result = {
        "runs": rows,
        "summary": [{"scene": s, "policy": p, **c} for (s, p), c in sorted(summary.items())],
        "policy_means": policy_means(summary),
        "errors": errors,
    }
    write_json(root / OUT_FILE, result)
    return result
