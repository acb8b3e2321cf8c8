"""`area3d bench episode`: every policy on every scene (bundled and generated hold-out) with several
seeds, in this process or spread over worker processes and machines (`episode_cluster.py`)."""

from __future__ import annotations

import os
import time
from collections import defaultdict
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from rich.console import Console, Group
from rich.live import Live
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from area3d_bench.episode_task import (
    ATTEMPTS_DIR,
    EpisodeResult,
    EpisodeTask,
    HoldoutScene,
    episode_summary,
    materialize,
    with_policy,
    write_holdout,
)

SPEED_TARGET_S = (
    60.0  # a full object-level episode end to end on 2 CPU cores (the paper: ~135 s on a GPU)
)
ROOM_SPEED_TARGET_S = 120.0  # a room-level episode (40 views)
HOLDOUT_SEED = 0  # the benchmark's generated hold-out scenes (tests use other seeds)


@dataclass
class RunSet:
    """The benchmark's episodes run once, with one engine."""

    workers: int | None  # None: in this process
    engine: str
    out_dir: Path
    wall_s: float = 0.0
    load: list[float] = field(default_factory=list)  # 1-min load average, start ... end
    results: dict[str, EpisodeResult] = field(default_factory=dict)  # run name -> result
    failures: list[str] = field(default_factory=list)
    lost_attempts: int = 0  # unfinished attempts in out_dir/attempts (dead workers, failures)

    def cpu_s(self) -> float:
        """CPU seconds the episodes took, wherever they ran (see `EpisodeResult.cpu_s`)."""
        return sum(r.cpu_s for r in self.results.values())

    def run_dirs(self) -> list[Path]:
        return [self.out_dir / name for name in self.results]

    def summaries(self) -> dict[str, dict]:
        return {name: episode_summary(r) for name, r in self.results.items()}


def _tasks(
    scenes: list[str],
    policies: list[str],
    seeds: int,
    budget: int | None,
    out_dir: Path,
    in_process: bool,
    overrides: dict[str, dict] | None,
    depth_source: str,
    holdouts: dict[str, HoldoutScene],
) -> list[EpisodeTask]:
    return [
        EpisodeTask(
            scene=scene,
            policy=policy,
            seed=seed,
            budget=budget,
            out_dir=str(out_dir),
            run_name=f"{Path(scene).stem}_{policy}_s{seed}",
            in_process=in_process,
            overrides=with_policy(overrides, policy),
            depth_source=depth_source,
            holdout=holdouts.get(scene),
        )
        for scene in scenes
        for policy in policies
        for seed in range(seeds)
    ]


def _live_table(tasks: list[EpisodeTask], results: dict[str, EpisodeResult]) -> Table:
    """Completion and F-score per scene and policy over the episodes finished so far."""
    total: dict[tuple[str, str], int] = defaultdict(int)
    done: dict[tuple[str, str], list[dict]] = defaultdict(list)
    for task in tasks:
        total[(task.scene, task.policy)] += 1
    for result in results.values():
        final = result.metrics()["final"]
        seconds = result.episode().get("timings_s", {}).get("episode_total", np.nan)
        done[(result.task.scene, result.task.policy)].append({**final, "seconds": seconds})
    table = Table(title="episodes as they finish (mean ± std over the seeds done)")
    for column in ("scene", "policy", "done", "Comp. ratio", "F-score", "episode [s]"):
        table.add_column(column)
    for key, n in total.items():
        rows = done.get(key, [])
        cells = [Path(key[0]).stem, key[1], f"{len(rows)}/{n}"]
        for metric, fmt in (("completion", "{:.3f}"), ("fscore", "{:.3f}"), ("seconds", "{:.1f}")):
            values = np.array([r.get(metric, np.nan) for r in rows], dtype=float)
            values = values[np.isfinite(values)]
            cells.append(
                f"{fmt.format(values.mean())} ± {fmt.format(values.std())}" if values.size else "…"
            )
        table.add_row(*cells)
    return table


def _run_set(
    engine: Any, workers: int | None, tasks: list[EpisodeTask], out_dir: Path, console: Console
) -> RunSet:
    """Run every task with `engine`, filling the table and the progress bar as results come in."""
    run = RunSet(workers, engine.description, out_dir)
    columns = (
        TextColumn("{task.description}"),
        BarColumn(),
        TextColumn("{task.completed}/{task.total}"),
        TimeElapsedColumn(),
    )
    progress = Progress(*columns, console=console)
    overall = progress.add_task(f"episodes, {engine.slots} at once", total=len(tasks))
    run.load.append(os.getloadavg()[0])
    t0 = time.monotonic()
    view = Group(progress, _live_table(tasks, run.results))
    with Live(view, console=console, refresh_per_second=4, transient=True) as live:
        for result in engine.run(tasks, progress):
            task = result.task
            if result.error is not None:
                run.failures.append(
                    f"{Path(task.scene).stem}/{task.policy}/s{task.seed}: {result.error}"
                )
            else:
                materialize(result, out_dir / task.run_name)
                run.results[task.run_name] = result
            run.load.append(os.getloadavg()[0])
            progress.advance(overall)
            live.update(Group(progress, _live_table(tasks, run.results)))
    run.wall_s = time.monotonic() - t0
    run.load.append(os.getloadavg()[0])
    attempts = out_dir / ATTEMPTS_DIR
    run.lost_attempts = len(list(attempts.iterdir())) if attempts.is_dir() else 0
    if attempts.is_dir() and not run.lost_attempts:
        attempts.rmdir()
    return run


def _print_table(run: RunSet, console: Console) -> list[dict]:
    from area3d_eval.report import TABLE_METRICS, aggregate, load_runs

    records = load_runs(run.run_dirs(), evaluate_missing=False)
    rows = aggregate(records)
    episode_seconds: dict[tuple[str, str], list[float]] = defaultdict(list)
    for record in records:  # the runs of the table's rows: those with metrics
        episode = record.episode
        episode_seconds[(episode.scene, episode.policy)].append(
            episode.timings_s.get("episode_total", np.nan)
        )
    table = Table(title="area3d bench episode (mean ± std over seeds)")
    for column in (
        "scene",
        "policy",
        "runs",
        *[label for _, label, *_ in TABLE_METRICS],
        "episode [s]",
    ):
        table.add_column(column)
    for row in rows:
        cells = [Path(row["scene"]).stem, row["policy"], str(row["runs"])]
        for key, _, _, scale, fmt in TABLE_METRICS:
            cells.append(
                f"{fmt.format(row[key] * scale)} ± {fmt.format(row[key + '_std'] * scale)}"
            )
        seconds = episode_seconds.get((row["scene"], row["policy"]), [])
        cells.append(f"{np.mean(seconds):.1f} (max {np.max(seconds):.1f})" if seconds else "–")
        table.add_row(*cells)
    console.print(table, width=max(console.width, 160))
    _print_fewer_views(records, console)
    return rows


def _print_fewer_views(records: list, console: Console) -> None:
    """Per scene, the views each policy took to reach `uniform`'s final completion (the paper's
    "fewer views" figure; `area3d_eval.fewer_views`). Printed only where uniform ran."""
    from area3d_eval import fewer_views
    from area3d_eval.report import view_curves

    entries = fewer_views.views_to_reach(view_curves(records))
    if not entries:
        return
    reference = fewer_views.REFERENCE_POLICY
    table = Table(title=f"views to reach {reference}'s final completion (mean over seeds)")
    scenes, labels, cells = fewer_views.grid(entries)
    for column in ("scene", *labels):
        table.add_column(column)
    for i, scene in enumerate(scenes):
        table.add_row(Path(scene).stem, *[row[i] for row in cells])
    console.print(table, width=max(console.width, 160))


def _print_wall_times(runs: list[RunSet], shape: str, console: Console) -> None:
    """Wall time per engine, beside each other: the speed-up over the fewest workers and its
    target (as many times faster as there are times more workers). A list such as 2,1 runs the
    larger count first, so that a load that drifts meanwhile can be told from the speed-up.
    "cores used" is the episodes' CPU time over the wall time: what the workers got of the
    machine (on a machine shared with other work, less than the workers could use)."""
    table = Table(title=f"benchmark wall time, {shape}, on {os.cpu_count()} cores")
    for column in (
        "workers",
        "episodes",
        "wall [s]",
        "CPU [s]",
        "cores used",
        "load 1 min: start/max/end",
        "speed-up",
        "target",
        "ratio",
    ):
        table.add_column(column)
    base = min(runs, key=lambda run: run.workers or 0)
    for run in runs:
        cells = [
            "– (this process)" if run.workers is None else str(run.workers),
            str(len(run.results)),
            f"{run.wall_s:.1f}",
            f"{run.cpu_s():.1f}",
            f"{run.cpu_s() / run.wall_s:.2f}" if run.wall_s > 0 else "–",
            f"{run.load[0]:.1f}/{max(run.load):.1f}/{run.load[-1]:.1f}",
        ]
        if run is base or not base.workers or not run.workers:
            cells += ["1.00x" if run is base else "–", "–", "–"]
        else:
            speedup = base.wall_s / run.wall_s
            target = run.workers / base.workers
            cells += [f"{speedup:.2f}x", f"{target:.2f}x", f"{speedup / target:.2f}"]
        table.add_row(*cells)
    console.print(table, width=max(console.width, 140))
    for run in runs:
        console.print(f"{run.workers or 'no'} worker(s): {run.engine}")
    if len(runs) > 1:
        first = base.summaries()
        for run in (run for run in runs if run is not base):
            other = run.summaries()
            common = sorted(set(first) & set(other))
            differ = [name for name in common if first[name] != other[name]]
            who = f"{base.workers} and {run.workers} workers"
            if differ:
                console.print(f"[red]views or metrics differ[/] with {who}: {', '.join(differ)}")
            else:
                console.print(
                    f"same views and metrics with {who}: {len(common)} of {len(first)} episodes"
                )
    for run in runs:
        if run.lost_attempts:
            console.print(
                f"{run.lost_attempts} unfinished attempt(s) kept in {run.out_dir / ATTEMPTS_DIR}: "
                "of workers that died mid-episode (their episodes were run again) or of the "
                "failed episodes below"
            )


def _check_request(seeds: int, policies: list[str], scenes: list[str], budget) -> None:
    """Refuse, before any episode runs, what every episode would fail on: no seed, a policy or
    a scene that does not exist (each episode failed with it, and the run ended 'done')."""
    from area3d_bringup.presets import RUN_PRESETS
    from sim_bridge.scenes import list_scenes

    if not isinstance(seeds, int) or seeds < 1:
        raise ValueError(f"seeds: got {seeds}, expected an int >= 1")
    unknown = [p for p in policies if p not in RUN_PRESETS]
    if unknown or not policies:
        raise ValueError(
            f"policies: got {unknown or policies}, expected names among {sorted(RUN_PRESETS)}"
        )
    bundled = set(list_scenes())
    missing = [s for s in scenes if s not in bundled and not Path(s).expanduser().is_file()]
    if missing:
        raise ValueError(
            f"scenes: got {missing}, expected bundled scene names ({', '.join(sorted(bundled))}) "
            "or paths of MJCF files"
        )
    if budget is not None and budget < 1:
        raise ValueError(f"budget: got {budget}, expected the total number of views (>= |O_0|)")


def run_episode_bench(
    seeds: int,
    policies: list[str],
    scenes: list[str],
    budget: int | None,
    out: Path,
    console: Console,
    in_process: bool = False,
    holdout: bool = False,
    holdout_kinds: Sequence[str] | None = None,
    overrides: dict[str, dict] | None = None,
    depth_source: str = "sensor",
    workers: Sequence[int] | None = None,
    cluster: str | None = None,
) -> dict:
    """Run the benchmark and print its table. workers: run it on a local cluster of that many
    worker processes, once per count given (the wall times are printed beside each other);
    cluster: a Dask scheduler's address to run it on instead. Neither: in this process.
    holdout_kinds: the hold-out kinds `holdout` generates (default: every kind).
    Returns {"rows", "failures", "report", "runs": [{"workers", "engine", "wall_s", "cpu_s", "load",
    "lost_attempts", "out_dir", "episodes": {run name: its views and metrics}, "ran_on": {run
    name: host:pid}}]}."""
    from area3d_bench.episode_cluster import open_engine
    from area3d_eval.report import write_report
    from sim_bridge.holdout_scenes import HOLDOUT_WRITERS
    from sim_bridge.scenes import list_scenes

    scenes = list(scenes) or list_scenes()
    _check_request(seeds, policies, scenes, budget)
    kinds = list(holdout_kinds) if holdout_kinds else list(HOLDOUT_WRITERS)
    unknown = [kind for kind in kinds if kind not in HOLDOUT_WRITERS]
    if unknown:
        raise ValueError(
            f"holdout_kinds: got {unknown}, expected kinds among {list(HOLDOUT_WRITERS)}"
        )
    counts: list[int | None] = list(workers) if workers else [None]
    if cluster is not None and len(counts) > 1:
        raise ValueError(
            f"workers: got {list(workers or [])} with a cluster, expected none (a cluster has "
            "its own workers)"
        )
    root = out / time.strftime("%Y%m%d-%H%M%S")
    holdouts: dict[str, HoldoutScene] = {}
    if holdout:  # scenes nobody tuned on, generated now, with no metadata but their MJCF
        for kind in kinds:
            folder = root / "holdout" / f"{kind}_s{HOLDOUT_SEED}"
            path, spec = write_holdout(kind, HOLDOUT_SEED, folder)
            scenes.append(str(path))
            holdouts[str(path)] = spec
    runs: list[RunSet] = []
    for count in counts:
        out_dir = root if len(counts) == 1 else root / f"workers{count}"
        tasks = _tasks(
            scenes,
            policies,
            seeds,
            budget,
            out_dir,
            in_process,
            overrides,
            depth_source,
            holdouts,
        )
        engine = open_engine(None if cluster else count, cluster)
        try:
            for warning in getattr(engine, "warnings", []):
                console.print(f"[yellow]warning:[/] {warning}")
            runs.append(_run_set(engine, count, tasks, out_dir, console))
        finally:
            engine.close()
    last = runs[-1]
    md, html = write_report(last.run_dirs(), root / "report")
    rows = _print_table(last, console)
    console.print(
        f"speed target: episode < {SPEED_TARGET_S:.0f} s end to end at object level, "
        f"{ROOM_SPEED_TARGET_S:.0f} s at room level"
    )
    shape = (
        f"{len(scenes)} scenes x {len(policies)} policies x {seeds} seeds, "
        f"{'in process' if in_process else 'over the graph'}"
    )
    _print_wall_times(runs, shape, console)
    failures = [f for run in runs for f in run.failures]
    for failure in failures:
        console.print(f"[red]failed[/] {failure}")
    console.print(f"report: {html}")
    return {
        "rows": rows,
        "failures": failures,
        "report": str(html),
        "runs": [
            {
                "workers": run.workers,
                "engine": run.engine,
                "wall_s": run.wall_s,
                "cpu_s": run.cpu_s(),
                "load": run.load,
                "lost_attempts": run.lost_attempts,
                "out_dir": run.out_dir,
                "episodes": run.summaries(),
                "ran_on": {name: r.worker for name, r in run.results.items()},
            }
            for run in runs
        ],
    }
