"""Benchmark of the evaluation path on a synthetic object-level episode: 4 initial + 25 planned
views at 640 x 480 (the paper's object-level budget), 16 held-out views."""

from __future__ import annotations

import tempfile
import time
from pathlib import Path
from typing import Any

from area3d_eval.evaluate import EVAL_HEIGHT, EVAL_WIDTH, evaluate_run
from area3d_eval.metrics import NUM_SURFACE_POINTS
from area3d_eval.synthetic import SyntheticRenderer, SyntheticScene, make_run

# Targets on a 2-core CPU: a whole object-level evaluation in a few seconds.
TARGETS_S = {
    "evaluate_run_s": 5.0,  # all checkpoints of 29 frames: TSDF, surface metrics, held-out images
    "tsdf_per_frame_s": 0.03,
    "surface_metrics_per_checkpoint_s": 0.25,
    "render_per_eval_view_s": 0.03,  # ray casting + PSNR/SSIM of one 320 x 240 view
}


def run_bench_eval(
    budget: int = 25,  # planned views after |O_0| = 4 (paper, object level)
    width: int = 640,
    height: int = 480,
    num_eval_views: int = 16,
    eval_width: int = EVAL_WIDTH,
    eval_height: int = EVAL_HEIGHT,
    num_surface_points: int = NUM_SURFACE_POINTS,
    run_dir: Path | None = None,
) -> dict[str, Any]:
    """Time evaluate_run on a synthetic run; returns the figures (seconds and final metrics)."""
    scene = SyntheticScene(num_eval_views=num_eval_views)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(run_dir) if run_dir is not None else Path(tmp) / "run"
        t = time.perf_counter()
        make_run(path, scene, policy="random", seed=0, budget=budget, width=width, height=height)
        make_s = time.perf_counter() - t
        t = time.perf_counter()
        result = evaluate_run(
            path,
            scene,
            renderer_factory=SyntheticRenderer,
            eval_width=eval_width,
            eval_height=eval_height,
            num_surface_points=num_surface_points,
        )
        total = time.perf_counter() - t
    timings = result["timings_s"]
    checkpoints = len(result["curve"])
    frames = result["num_views"]
    return {
        "frames": frames,
        "checkpoints": checkpoints,
        "eval_views": num_eval_views,
        "make_run_s": make_s,
        "evaluate_run_s": total,
        "tsdf_per_frame_s": timings["tsdf"] / frames,
        "mesh_extraction_s": timings["mesh"],
        "surface_metrics_per_checkpoint_s": timings["surface"] / checkpoints,
        "render_per_eval_view_s": timings["render"] / max(checkpoints * num_eval_views, 1),
        "reference_images_s": timings["reference"],
        "final_completion": result["final"]["completion"],
        "final_fscore": result["final"]["fscore"],
        "final_psnr_roi": result["final"].get("psnr_roi"),
    }


def run_bench(**options: Any) -> dict[str, Any]:
    """`area3d bench eval`: run the evaluation benchmark and print figures beside their targets."""
    from rich.console import Console
    from rich.table import Table

    figures = run_bench_eval(**options)
    table = Table(
        title=f"area3d_eval: {figures['frames']} frames, {figures['checkpoints']} checkpoints, {figures['eval_views']} held-out views"
    )
    table.add_column("figure")
    table.add_column("value", justify="right")
    table.add_column("target", justify="right")
    table.add_column("value / target", justify="right")
    for key, value in figures.items():
        target = TARGETS_S.get(key)
        shown = f"{value:.4f}" if isinstance(value, float) else str(value)
        ratio = f"{value / target:.2f}" if target and isinstance(value, float) else ""
        table.add_row(key, shown, "" if target is None else f"<= {target}", ratio)
    Console().print(table)
    return figures


if __name__ == "__main__":
    run_bench()
