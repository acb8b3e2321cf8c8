"""`area3d bench episode`: every policy on every scene (bundled and generated hold-out) with several seeds."""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import numpy as np
from rich.console import Console
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

SPEED_TARGET_S = (
    60.0  # a full object-level episode end to end on 2 CPU cores (the paper: ~135 s on a GPU)
)
ROOM_SPEED_TARGET_S = 120.0  # a room-level episode (40 views)


def _with_policy(overrides: dict[str, dict] | None, policy: str) -> dict[str, dict]:
    """The bench's overrides for one policy: an ablation's own settings win over the command
    line's (no_ff keeps its uniform confidence whatever the backend)."""
    from area3d_bringup.launch_description import merge
    from area3d_bringup.presets import RUN_PRESETS

    return merge(overrides, RUN_PRESETS.get(policy, {}))


def run_episode_bench(
    seeds: int,
    policies: list[str],
    scenes: list[str],
    budget: int | None,
    out: Path,
    console: Console,
    in_process: bool = False,
    holdout: bool = False,
    overrides: dict[str, dict] | None = None,
    depth_source: str = "sensor",
) -> dict:
    from area3d_bringup.episode_config import EpisodeConfig, EpisodeError
    from area3d_bringup.runner import run_episode
    from area3d_eval import rundir
    from area3d_eval.report import aggregate, write_report
    from sim_bridge.scenes import list_scenes

    scenes = list(scenes) or list_scenes()
    # Its own loopback domain, so that the benchmark's graphs never meet another graph on this machine.
    domain_id = 1 + (os.getpid() + 17) % 200
    stamp = time.strftime("%Y%m%d-%H%M%S")
    if holdout:  # scenes nobody tuned on, generated now, with no metadata but their MJCF
        from sim_bridge.holdout_scenes import write_holdout_scenes

        scenes += [str(p) for p in write_holdout_scenes(out / stamp / "holdout", seeds=(0,))]
    run_dirs: list[Path] = []
    failures: list[str] = []
    episode_seconds: dict[tuple[str, str], list[float]] = {}
    columns = (
        TextColumn("{task.description}"),
        BarColumn(),
        TextColumn("{task.completed}/{task.total}"),
        TimeElapsedColumn(),
    )
    with Progress(*columns, console=console) as progress:
        overall = progress.add_task("episodes", total=len(scenes) * len(policies) * seeds)
        for scene in scenes:
            for policy in policies:
                for seed in range(seeds):
                    config = EpisodeConfig(
                        scene=scene,
                        policy=policy,
                        budget=budget,
                        seed=seed,
                        out_dir=out / stamp,
                        record=False,
                        run_name=f"{Path(scene).stem}_{policy}_s{seed}",
                        domain_id=domain_id,
                        overrides=_with_policy(overrides, policy),
                        depth_source=depth_source,
                    )
                    try:
                        if in_process:  # the same cores in one process: no transport, same views
                            from area3d_bringup.inprocess import run_inprocess_episode

                            t0 = time.monotonic()
                            run_dir = run_inprocess_episode(
                                scene,
                                policy,
                                seed,
                                out / stamp,
                                budget,
                                overrides=config.overrides,
                                run_name=config.run_name,
                                depth_source=depth_source,
                            )
                            episode = json.loads((run_dir / rundir.EPISODE_FILE).read_text())
                            episode["timings_s"]["episode_total"] = time.monotonic() - t0
                            rundir.write_episode(run_dir, episode)
                        else:
                            run_dir = run_episode(config, progress=progress)
                        run_dirs.append(run_dir)
                        episode = rundir.read_episode(run_dir)
                        episode_seconds.setdefault((episode.scene, policy), []).append(
                            episode.timings_s.get("episode_total", np.nan)
                        )
                    except (EpisodeError, ValueError) as err:
                        failures.append(f"{scene}/{policy}/s{seed}: {err}")
                    progress.advance(overall)
    md, html = write_report(run_dirs, out / stamp / "report")
    rows = aggregate(run_dirs)
    from area3d_eval.report import TABLE_METRICS

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
    console.print(
        f"speed target: episode < {SPEED_TARGET_S:.0f} s end to end at object level, "
        f"{ROOM_SPEED_TARGET_S:.0f} s at room level"
    )
    for failure in failures:
        console.print(f"[red]failed[/] {failure}")
    console.print(f"report: {html}")
    return {"rows": rows, "failures": failures, "report": str(html)}
