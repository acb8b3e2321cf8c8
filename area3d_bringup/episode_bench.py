"""`area3d bench episode`: every policy on every object-level scene with several seeds."""

from __future__ import annotations

import time
from pathlib import Path

from rich.console import Console
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

SPEED_TARGET_S = 60.0  # a full object-level episode end to end on 2 CPU cores (the paper: ~135 s on a GPU)


def run_episode_bench(
    seeds: int, policies: list[str], scenes: list[str], budget: int | None, out: Path, console: Console
) -> dict:
    from area3d_bringup.runner import EpisodeConfig, EpisodeError, run_episode
    from area3d_eval.report import aggregate, evaluate_runs, write_report
    from sim_bridge.scenes import list_scenes, load_scene

    scenes = scenes or [name for name in list_scenes() if load_scene(name).level == "object"]
    stamp = time.strftime("%Y%m%d-%H%M%S")
    run_dirs: list[Path] = []
    failures: list[str] = []
    columns = (TextColumn("{task.description}"), BarColumn(), TextColumn("{task.completed}/{task.total}"),
               TimeElapsedColumn())
    with Progress(*columns, console=console) as progress:
        overall = progress.add_task("episodes", total=len(scenes) * len(policies) * seeds)
        for scene in scenes:
            for policy in policies:
                for seed in range(seeds):
                    config = EpisodeConfig(scene=scene, policy=policy, budget=budget, seed=seed,
                                           out_dir=out / stamp, record=False,
                                           run_name=f"{scene}_{policy}_s{seed}")
                    try:
                        run_dirs.append(run_episode(config, progress=progress))
                    except EpisodeError as err:
                        failures.append(f"{scene}/{policy}/s{seed}: {err}")
                    progress.advance(overall)
    evaluate_runs(run_dirs, console=console)
    rows = aggregate(run_dirs)
    table = Table(title="area3d bench episode (mean ± std over seeds)")
    for column in ("scene", "policy", "completion", "chamfer_mm", "f_score", "psnr", "ssim", "episode_s"):
        table.add_column(column)
    for row in rows:
        table.add_row(*[str(row.get(c, "")) for c in ("scene", "policy", "completion", "chamfer_mm", "f_score",
                                                      "psnr", "ssim", "episode_s")])
    console.print(table)
    console.print(f"speed target: object-level episode < {SPEED_TARGET_S:.0f} s end to end")
    for failure in failures:
        console.print(f"[red]failed[/] {failure}")
    md, html = write_report(run_dirs, out / stamp / "report")
    console.print(f"report: {html}")
    return {"rows": rows, "failures": failures, "report": str(html)}
