"""`area3d bench map-truth RUN_ROOT`: what the planner's map holds where the scene has a surface.

A robot that plans its motion through the planner's free space needs that space not to cross a
real surface. Each run recorded with `--depth-source estimated` keeps the depth and confidence
perception sent the planner; they are fused again, in order, into a planner of the run's own
parameters (`NextBestViewServer.add_frame`, the path every frame takes). The region's
ground-truth surface, sampled as the evaluation samples it, then falls into voxels that the map
holds free (carved through a real surface: the error a motion planner pays for), unknown, or
occupied. Per scene and policy the shares are means over the seeds found, then means over the
scenes per policy. Also written to RUN_ROOT/map_truth.json.
"""

from __future__ import annotations

from dataclasses import fields
from pathlib import Path

import numpy as np
from rich.console import Console
from rich.table import Table

from area3d_bench.views_depth import figures_of_runs, policy_means, summarise
from area3d_eval.rundir import frame_files, read_episode, read_frame, write_json

OUT_FILE = "map_truth.json"
FIELDS = ("free", "unknown", "occupied")


def surface_voxels(spec, points: np.ndarray, roi_min, roi_max) -> np.ndarray:
    """Sorted unique ids of the voxels of `spec` that hold a point of `points` (P, 3) inside the
    box roi_min..roi_max."""
    points = np.asarray(points, np.float64)
    inside = np.all((points >= np.asarray(roi_min)) & (points <= np.asarray(roi_max)), axis=1)
    ids, in_grid = spec.flat_index(points[inside])
    return np.unique(ids[in_grid])


def map_shares(occupancy: np.ndarray, voxels: np.ndarray) -> dict[str, float]:
    """Shares of `voxels` that `occupancy` (-1 unknown, 0 free, 1 occupied) holds free, unknown
    and occupied."""
    if voxels.size == 0:
        raise ValueError("surface voxels: got none, expected a surface inside the region")
    held = occupancy[voxels]
    return {
        "free": float(np.mean(held == 0)),
        "unknown": float(np.mean(held == -1)),
        "occupied": float(np.mean(held == 1)),
    }


def replayed_planner(run_dir: Path):
    """A `NextBestViewServer` with the run's planner parameters that fused, in order, the depth
    and confidence every frame of the run sent it."""
    from area3d_planner.config import PlannerConfig
    from area3d_planner.server import NextBestViewServer

    episode = read_episode(run_dir)
    names = {f.name for f in fields(PlannerConfig)}
    given = episode.config.get("planner", {}) if isinstance(episode.config, dict) else {}
    server = NextBestViewServer(PlannerConfig(**{k: v for k, v in given.items() if k in names}))
    for i, path in enumerate(frame_files(run_dir)):
        frame = read_frame(path)
        if frame.estimated_depth is None or frame.confidence is None:
            raise ValueError(f"frame {path.name}: got no estimated depth, expected perception's")
        # stamps by order: a run's frames are fused once each, whatever stamps they carry
        server.add_frame(i + 1, frame.estimated_depth, frame.confidence, frame.K, frame.T_world_cam)
    return server


def run_figures(run_dir: Path, num_surface_points: int | None = None) -> dict:
    """One run's shares of the region's surface voxels the replayed map holds free, unknown and
    occupied, with its scene, policy and seed."""
    from area3d_eval.metrics import NUM_SURFACE_POINTS, SURFACE_SEED, sample_surface
    from area3d_eval.render import mesh_arrays
    from sim_bridge.scenes import load_scene

    run_dir = Path(run_dir)
    episode = read_episode(run_dir)
    scene = load_scene(episode.scene)
    server = replayed_planner(run_dir)
    vertices, triangles, _ = mesh_arrays(scene.ground_truth_mesh())
    points = sample_surface(
        vertices, triangles, num_surface_points or NUM_SURFACE_POINTS, SURFACE_SEED
    )
    voxels = surface_voxels(server.grid.spec, points, scene.roi_min, scene.roi_max)
    return {
        "run": run_dir.name,
        "scene": episode.scene_name,
        "policy": episode.policy,
        "seed": episode.seed,
        "surface_voxels": int(voxels.size),
        **map_shares(server.grid.occupancy(), voxels),
    }


def _figures_or_error(run: Path, num_surface_points: int | None) -> dict:
    """`run_figures`, or {"run", "error"}: one bad run does not cost the others' figures."""
    try:
        return run_figures(run, num_surface_points)
    except Exception as err:  # reported in the table's place, with the run named
        return {"run": str(run), "error": f"{type(err).__name__}: {err}"}


def print_table(summary: dict, console: Console | None = None) -> None:
    """Per scene and policy, then each policy's mean over the scenes."""
    table = Table(
        title="the planner's map where the region has a surface (means over seeds)",
        caption="share of the region's ground-truth surface voxels the map holds free (carved "
        "through a real surface), unknown, occupied",
    )
    for name in ("scene", "policy", "seeds", *FIELDS):
        table.add_column(name, no_wrap=True)
    for (scene, policy), c in sorted(summary.items()):
        table.add_row(scene, policy, str(c["seeds"]), *(f"{c[f]:.3f}" for f in FIELDS))
    for policy, c in policy_means(summary, FIELDS).items():
        table.add_row(f"mean ({c['scenes']} scenes)", policy, "", *(f"{c[f]:.3f}" for f in FIELDS))
    (console or Console(width=120)).print(table)


def run_bench(root: Path, workers: int = 1, num_surface_points: int | None = None) -> dict:
    """Figures of every estimated-depth run under `root`, printed and written to
    root/map_truth.json; returns {"runs", "summary", "policy_means", "errors"}."""
    root = Path(root)
    rows, errors = figures_of_runs(root, _figures_or_error, num_surface_points, workers)
    summary = summarise(rows, FIELDS)
    console = Console(width=120)
    if summary:
        print_table(summary, console)
    for row in errors:
        console.print(f"not replayed: {row['run']}: {row['error']}", soft_wrap=True)
    result = {
        "runs": rows,
        "summary": [{"scene": s, "policy": p, **c} for (s, p), c in sorted(summary.items())],
        "policy_means": policy_means(summary, FIELDS),
        "errors": errors,
    }
    write_json(root / OUT_FILE, result)
    return result
