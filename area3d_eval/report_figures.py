"""The report's figures: per scene its metric-vs-views curves, per run its chosen views, the
uncertainty slices before and after (captioned with the hard regions left, `hard_region_text`) and
the final mesh rendered around the region, and the time per stage of every run (PNG files, drawn by
`plots`). `report.write_report` draws them all with `draw_figures` and links them from the page."""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from area3d_eval import plots
from area3d_eval.open3d_loader import import_open3d
from area3d_eval.render import MeshRenderer
from area3d_eval.rundir import (
    EVAL_DIR,
    GRID_FINAL_FILE,
    GRID_INITIAL_FILE,
    MESH_FILE,
    iter_frames,
    read_grid,
)
from area3d_msgs_py.backproject import depth_to_world
from area3d_msgs_py.camera_pose import look_at
from area3d_planner.hard_regions import grid_voxel_size, points_hard_regions

if TYPE_CHECKING:  # the records are the report's; it imports this module
    from area3d_eval.report import RunRecord

CURVE_METRICS = ("completion", "fscore", "chamfer", "psnr_roi", "ssim_roi")
MESH_AZIMUTHS = (45, 165, 285)  # degrees: the final mesh seen from three sides
MESH_RENDER_SIZE = (320, 240)
PREVIEW_POINTS = 4000  # scene points drawn behind the chosen views when no GT sample was saved


def draw_figures(
    records: list[RunRecord], fig_dir: Path
) -> tuple[dict[str, dict[str, Path]], Path | None]:
    """Draw every figure; returns ({scene name: {metric: png}}, timing png)."""
    curves: dict[str, dict[str, dict[str, list]]] = defaultdict(lambda: defaultdict(dict))
    by_scene: dict[str, dict[str, list]] = defaultdict(lambda: defaultdict(list))
    for r in records:
        by_scene[r.scene][r.episode.policy].append(r.metrics.get("curve", []))
    for scene, policies in by_scene.items():
        for metric in CURVE_METRICS:
            curves[scene][metric] = plots.plot_metric_curves(
                policies,
                metric,
                fig_dir / f"curve_{_slug(scene)}_{metric}.png",
                title=f"{scene}: {metric}",
            )
    for i, r in enumerate(records):
        stem = f"run{i:02d}_{_slug(r.scene)}_{_slug(r.episode.policy)}_s{r.episode.seed}"
        points = _scene_points(r)
        roi = _roi(r)
        r.figures["views"] = plots.plot_views(
            points,
            r.episode.poses(),
            r.episode.kinds(),
            fig_dir / f"{stem}_views.png",
            title=r.label,
            roi=roi,
        )
        slices = plots.plot_grid_slices(
            read_grid(r.path / GRID_INITIAL_FILE),
            read_grid(r.path / GRID_FINAL_FILE),
            fig_dir / f"{stem}_uncertainty.png",
            title=r.label,
        )
        if slices is not None:
            r.figures["uncertainty"] = slices
        r.hard_regions = hard_region_text(read_grid(r.path / GRID_FINAL_FILE))
        mesh = _mesh_figure(r, fig_dir / f"{stem}_mesh.png")
        if mesh is not None:
            r.figures["mesh"] = mesh
    timings = {r.label: r.episode.timings_s for r in records if r.episode.timings_s}
    timing_png = plots.plot_timings(timings, fig_dir / "timings.png") if timings else None
    return curves, timing_png


def hard_region_text(grid: dict[str, np.ndarray] | None) -> str:
    """What the camera could not resolve, in a sentence: the hard regions of a saved grid (its
    `hard` field grouped as the planner groups them, `area3d_planner.hard_regions`), the hard
    voxels they hold and where the largest is; "" for a grid without a `hard` field."""
    if grid is None or "hard" not in grid:
        return ""
    xyz = np.stack([np.asarray(grid[axis], np.float64) for axis in "xyz"], axis=1)
    hard = np.asarray(grid["hard"]) > 0
    voxel = grid_voxel_size(xyz)
    if not hard.any() or voxel is None:
        return "Hard regions in the final grid: none (every observed surface was resolved)."
    regions = points_hard_regions(xyz[hard], np.asarray(grid["uncertainty"])[hard], voxel)
    largest = regions[0]
    centre = ", ".join(f"{c:.2f}" for c in largest["centroid"])
    count, size = int(hard.sum()), int(largest["voxel_count"])
    return (
        f"Hard regions in the final grid: {len(regions)} ({_count(count, 'hard voxel')} of "
        f"{voxel * 100:.3g} cm; the largest, {_count(size, 'voxel')}, around ({centre}) m)."
    )


def _count(n: int, noun: str) -> str:
    return f"{n} {noun}" if n == 1 else f"{n} {noun}s"


def _scene_points(r: RunRecord) -> np.ndarray:
    sample = r.path / EVAL_DIR / "gt_sample.npy"
    if sample.is_file():
        return np.load(sample)
    points = []
    for frame in iter_frames(r.path):
        world = depth_to_world(frame.depth, frame.K, frame.T_world_cam)[::4, ::4].reshape(-1, 3)
        points.append(world[np.all(np.isfinite(world), axis=1)])
    if not points:
        return np.zeros((0, 3))
    pts = np.concatenate(points)
    return pts[:: max(1, len(pts) // PREVIEW_POINTS)]


def _mesh_figure(r: RunRecord, out_path: Path) -> Path | None:
    """The run's final mesh (eval/reconstruction.ply) rendered from MESH_AZIMUTHS around its
    region, from 0.8 region diagonals away and above (white where no surface is); None without a
    mesh or a region."""
    ply, roi = r.path / EVAL_DIR / MESH_FILE, _roi(r)
    if not ply.is_file() or roi is None:
        return None
    mesh = import_open3d().io.read_triangle_mesh(str(ply))
    if len(mesh.triangles) == 0:
        return None
    renderer = MeshRenderer(mesh)
    lo, hi = roi
    centre, reach = 0.5 * (lo + hi), 0.8 * float(np.linalg.norm(hi - lo))
    w, h = MESH_RENDER_SIZE
    K = np.array([[w / 2, 0, w / 2], [0, w / 2, h / 2], [0, 0, 1]])  # 90 degrees wide
    images, titles = [], []
    for azimuth in MESH_AZIMUTHS:
        a = np.radians(azimuth)
        eye = centre + reach * np.array([np.cos(a), np.sin(a), 0.7]) / np.linalg.norm([1, 0.7])
        rgb, depth = renderer.render(K, look_at(eye, centre), w, h)
        images.append(np.where(np.isfinite(depth)[..., None], rgb, 255).astype(np.uint8))
        titles.append(f"from azimuth {azimuth} deg")
    return plots.plot_images(images, titles, out_path, title=f"{r.label}: reconstruction")


def _roi(r: RunRecord) -> tuple[np.ndarray, np.ndarray] | None:
    """The region of interest the run's planner was given (its parameters in the episode's
    config, {node: parameters}), None when the run does not say."""
    cfg = r.episode.config.get("planner", r.episode.config)
    if "roi_min" in cfg and "roi_max" in cfg:
        return np.asarray(cfg["roi_min"], dtype=np.float64), np.asarray(
            cfg["roi_max"], dtype=np.float64
        )
    return None


def _slug(text: str) -> str:
    return "".join(c if c.isalnum() else "_" for c in text)
