"""Figures of the report (PNG, matplotlib Agg): metric-vs-views curves, the chosen views around the
scene, uncertainty-grid slices before and after, time per stage."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.ticker import MaxNLocator  # noqa: E402

from area3d_msgs_py.camera import PAPER_HFOV_DEG  # noqa: E402

DPI = 110
FRUSTUM_DEPTH_FRACTION = 0.08  # frustum pyramid depth as a share of the scene's extent
FRUSTUM_HALF_ANGLE = np.radians(PAPER_HFOV_DEG / 2)

METRIC_LABELS = {
    "completion": "completion ratio (higher is better)",
    "chamfer": "Chamfer distance [m] (lower is better)",
    "fscore": "F-score (higher is better)",
    "psnr_roi": "PSNR on the region [dB] (higher is better)",
    "ssim_roi": "SSIM on the region (higher is better)",
    "psnr": "PSNR, whole image [dB] (secondary)",
    "ssim": "SSIM, whole image (secondary)",
    "roi_unreconstructed": "share of region pixels left empty (lower is better)",
    "psnr_roi_reconstructed": "PSNR on the reconstructed region pixels [dB]",
    "accuracy": "accuracy [m] (lower is better)",
    "completeness": "completeness [m] (lower is better)",
}


def _finite(values: Sequence[float | None]) -> np.ndarray:
    return np.array([np.nan if v is None else float(v) for v in values], dtype=np.float64)


def plot_metric_curves(
    curves: Mapping[str, Sequence[Sequence[Mapping[str, float]]]],
    metric: str,
    out_path: Path,
    title: str = "",
) -> Path:
    """One line per policy of `metric` against the number of views.

    curves: {policy: [curve of one run (list of {"num_views": n, metric: value}), ...]}; several runs
    of a policy (seeds) are drawn as their mean with a band of +- one standard deviation.
    """
    fig, ax = plt.subplots(figsize=(6, 4), dpi=DPI)
    for policy in sorted(curves):
        runs = curves[policy]
        views = sorted({int(row["num_views"]) for run in runs for row in run})
        table = np.full((len(runs), len(views)), np.nan)
        for r, run in enumerate(runs):
            for row in run:
                table[r, views.index(int(row["num_views"]))] = _finite([row.get(metric)])[0]
        table[~np.isfinite(table)] = np.nan
        with np.errstate(all="ignore"):
            mean = (
                np.nanmean(table, axis=0)
                if np.isfinite(table).any()
                else np.full(len(views), np.nan)
            )
            std = np.nanstd(table, axis=0) if len(runs) > 1 else np.zeros(len(views))
        (line,) = ax.plot(views, mean, marker="o", markersize=3, label=f"{policy} (n={len(runs)})")
        if len(runs) > 1:
            ax.fill_between(views, mean - std, mean + std, color=line.get_color(), alpha=0.2)
    ax.set_xlabel("number of views")
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))  # a count of views: no 4.5 tick
    ax.set_ylabel(METRIC_LABELS.get(metric, metric))
    ax.set_title(title or metric)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    return _save(fig, out_path)


def _frustum_lines(T: np.ndarray, depth: float) -> np.ndarray:
    """(8, 2, 3) segments of a pyramid: apex at the camera, base `depth` metres ahead (optical z)."""
    half = depth * np.tan(FRUSTUM_HALF_ANGLE)
    corners = np.array(
        [
            [-half, -half * 0.75, depth],
            [half, -half * 0.75, depth],
            [half, half * 0.75, depth],
            [-half, half * 0.75, depth],
        ]
    )
    corners = corners @ T[:3, :3].T + T[:3, 3]
    apex = T[:3, 3]
    sides = [(apex, c) for c in corners]
    base = [(corners[i], corners[(i + 1) % 4]) for i in range(4)]
    return np.array(sides + base)


def plot_views(
    points: np.ndarray,
    poses: np.ndarray,
    kinds: Sequence[str],
    out_path: Path,
    title: str = "",
    roi: tuple[np.ndarray, np.ndarray] | None = None,
) -> Path:
    """Top view (x-y) and side view (x-z) of the scene: `points` (N, 3) as a light scatter, each
    camera pose (M, 4, 4) as a small frustum; initial views grey, planned ones coloured by order."""
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    everything = np.concatenate([points, poses[:, :3, 3]]) if len(poses) else points
    extent = float(np.ptp(everything, axis=0).max()) if len(everything) else 1.0
    depth = max(extent, 1e-3) * FRUSTUM_DEPTH_FRACTION
    planned = [i for i, k in enumerate(kinds) if k != "initial"]
    cmap = plt.get_cmap("viridis")
    fig, axes = plt.subplots(1, 2, figsize=(11, 5), dpi=DPI)
    for ax, (a, b), name in zip(
        axes, [(0, 1), (0, 2)], ["top view (x-y)", "side view (x-z)"], strict=True
    ):
        if len(points):
            ax.scatter(points[:, a], points[:, b], s=1, c="0.75", alpha=0.5, linewidths=0)
        if roi is not None:
            lo, hi = np.asarray(roi[0]), np.asarray(roi[1])
            ax.add_patch(
                plt.Rectangle(
                    (lo[a], lo[b]),
                    hi[a] - lo[a],
                    hi[b] - lo[b],
                    fill=False,
                    ls="--",
                    color="0.4",
                    lw=0.8,
                )
            )
        for i, T in enumerate(poses):
            if kinds[i] == "initial":
                colour = "0.5"
            else:
                colour = cmap(planned.index(i) / max(len(planned) - 1, 1))
            for seg in _frustum_lines(T, depth):
                ax.plot(seg[:, a], seg[:, b], color=colour, lw=0.8)
            ax.plot(T[a, 3], T[b, 3], "o", color=colour, markersize=2.5)
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_xlabel("xyz"[a] + " [m]")
        ax.set_ylabel("xyz"[b] + " [m]")
        ax.set_title(name)
        ax.grid(True, alpha=0.3)
    if planned:
        sm = plt.cm.ScalarMappable(cmap=cmap, norm=plt.Normalize(1, len(planned)))
        fig.colorbar(sm, ax=axes, shrink=0.8, label="planned view order (grey = initial)")
    fig.suptitle(title or "chosen views")
    return _save(fig, out_path)


def _grid_volume(grid: Mapping[str, np.ndarray], field: str) -> tuple[np.ndarray, list[np.ndarray]]:
    """A flat grid (x, y, z, field arrays) as a dense (nx, ny, nz) volume (NaN where absent)."""
    axes = [np.unique(np.round(np.asarray(grid[k], dtype=np.float64), 6)) for k in ("x", "y", "z")]
    idx = [
        np.searchsorted(ax, np.round(np.asarray(grid[k], dtype=np.float64), 6))
        for ax, k in zip(axes, ("x", "y", "z"), strict=True)
    ]
    vol = np.full([len(a) for a in axes], np.nan)
    vol[idx[0], idx[1], idx[2]] = np.asarray(grid[field], dtype=np.float64)
    return vol, axes


def hard_voxels_xy(
    grid: Mapping[str, np.ndarray], z: float | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """(x, y) of a flat grid's hard voxels (its `hard` field > 0; none in grids without it),
    those at height `z` only when given (to 1 um)."""
    if "hard" not in grid:
        return np.zeros(0), np.zeros(0)
    hard = np.asarray(grid["hard"]) > 0
    if z is not None:
        hard &= np.abs(np.asarray(grid["z"], np.float64) - z) < 1e-6
    return np.asarray(grid["x"], np.float64)[hard], np.asarray(grid["y"], np.float64)[hard]


def column_mean(vol: np.ndarray) -> np.ndarray:
    """(nx, ny) mean along z of a dense (nx, ny, nz) grid volume, its absent voxels (NaN: left out
    of the published grid as empty) counted as 0; NaN for a column without any voxel."""
    present = np.isfinite(vol)
    mean = np.where(present, vol, 0.0).mean(axis=2)
    mean[~present.any(axis=2)] = np.nan
    return mean


def plot_grid_slices(
    before: Mapping[str, np.ndarray] | None,
    after: Mapping[str, np.ndarray] | None,
    out_path: Path,
    field: str = "uncertainty",
    title: str = "",
) -> Path | None:
    """Rows before / after, columns: horizontal slice at the grid's middle height and the mean
    along z of each column (the voxels the grid leaves out, empty ones at no more than gamma,
    counted as 0), colour = `field` (one colour scale for all panels; white: a voxel left out, or
    a column of none); the hard voxels (a grid's `hard` field: what no view is expected to
    resolve) marked in cyan, those of the slice on the slice, every one on the projection. None if
    no grid. The mean, not the maximum: every column through an object holds its never-seen
    inside at full uncertainty, so its maximum stays there however well the surface is known."""
    grids = [
        (name, g)
        for name, g in (("before", before), ("after", after))
        if g is not None and field in g and len(g[field])
    ]
    if not grids:
        return None
    volumes = [(name, *_grid_volume(g, field)) for name, g in grids]
    finite = np.concatenate([v[np.isfinite(v)] for _, v, _ in volumes])
    vmin, vmax = (float(finite.min()), float(finite.max())) if finite.size else (0.0, 1.0)
    fig, axes = plt.subplots(
        len(volumes), 2, figsize=(10, 4.2 * len(volumes)), dpi=DPI, squeeze=False
    )
    image = None
    hard_grids = [g for _, g in grids]
    for row, (name, vol, (xs, ys, zs)) in enumerate(volumes):
        mid = len(zs) // 2
        proj = column_mean(vol)
        hx = 0.5 * (xs[1] - xs[0]) if len(xs) > 1 else 0.5
        hy = 0.5 * (ys[1] - ys[0]) if len(ys) > 1 else 0.5
        extent = (xs[0] - hx, xs[-1] + hx, ys[0] - hy, ys[-1] + hy)  # voxel edges, not centres
        for col, (panel, label) in enumerate(
            [(vol[:, :, mid], f"slice z = {zs[mid]:.3f} m"), (proj, "mean over z")]
        ):
            ax = axes[row, col]
            image = ax.imshow(
                panel.T,
                origin="lower",
                extent=extent,
                vmin=vmin,
                vmax=vmax,
                cmap="inferno",
                aspect="equal",
            )
            total = hard_voxels_xy(hard_grids[row])[0].size
            hard = f"\n{total} hard voxels (cyan)" if col == 1 and total else ""  # no legend box
            ax.set_title(f"{name}: {label}{hard}")
            ax.set_xlabel("x [m]")
            ax.set_ylabel("y [m]")
            x, y = hard_voxels_xy(hard_grids[row], zs[mid] if col == 0 else None)
            if x.size:
                ax.scatter(x, y, s=4, c="cyan", marker="s", linewidths=0, label="hard")
    fig.colorbar(image, ax=axes, shrink=0.8, label=field)
    fig.suptitle(title or f"{field} grid (white: empty, not in the published grid)")
    return _save(fig, out_path)


def plot_timings(
    timings: Mapping[str, Mapping[str, float]], out_path: Path, title: str = "time per stage"
) -> Path:
    """Grouped horizontal bars: for each label (a run or a policy) the seconds spent per stage."""
    labels = list(timings)
    stages = sorted({s for t in timings.values() for s in t})
    fig, ax = plt.subplots(
        figsize=(7, 0.5 + 0.35 * max(len(labels) * max(len(stages), 1), 4)), dpi=DPI
    )
    height = 0.8 / max(len(stages), 1)
    y = np.arange(len(labels))
    for k, stage in enumerate(stages):
        values = [float(timings[label].get(stage, 0.0)) for label in labels]
        ax.barh(y + k * height, values, height=height, label=stage)
    ax.set_yticks(y + 0.4 - height / 2)
    ax.set_yticklabels(labels, fontsize=8)
    ax.invert_yaxis()
    ax.set_xlabel("seconds")
    ax.set_title(title)
    ax.grid(True, axis="x", alpha=0.3)
    # beside the axes: inside, it covered the longest bar (the episode's total)
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    fig.tight_layout()
    return _save(fig, out_path)


def _save(fig: plt.Figure, out_path: Path) -> Path:
    out_path = Path(out_path)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out_path)
    plt.close(fig)
    return out_path


def plot_images(
    images: Sequence[np.ndarray], titles: Sequence[str], out_path: Path, title: str = ""
) -> Path:
    """RGB images (H, W, 3) uint8 side by side, each with its title (the reconstructed mesh seen
    from around the region)."""
    fig, axes = plt.subplots(1, len(images), figsize=(4.2 * len(images), 3.6), dpi=DPI)
    for ax, image, name in zip(np.atleast_1d(axes), images, titles, strict=True):
        ax.imshow(image)
        ax.set_title(name, fontsize=9)
        ax.axis("off")
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    return _save(fig, out_path)
