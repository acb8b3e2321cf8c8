"""Reconstruction metrics: surface distances and F-score against the ground-truth mesh, and
PSNR / SSIM of images rendered at held-out views (scikit-image's, with masks and the border crop
the evaluation needs).

Surface metrics (both surfaces sampled uniformly by area, fixed seed, distances in metres):

- accuracy     = mean over reconstruction points of the distance to the nearest GT point
- completeness = mean over GT points of the distance to the reconstruction's surface (exact
                 point-to-triangle distance: a nearest-sample distance would grow, and completion
                 fall, when the same surface is sampled more thinly because the mesh grew elsewhere)
- chamfer      = (accuracy + completeness) / 2
- precision    = share of reconstruction points within tau of the GT
- recall       = completion ratio = share of GT points within tau of the reconstruction
- fscore       = 2 precision recall / (precision + recall)

An empty reconstruction has completion = recall = precision = fscore = 0, completeness and chamfer
= inf and accuracy = NaN (there is no point to measure); JSON files store both as null.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from scipy.spatial import cKDTree
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

from area3d_eval.mesh_order import position_classes, row_order, smallest_first
from area3d_eval.render import MeshRenderer, mesh_arrays, render_mesh
from area3d_msgs_py.errors import InputError

NUM_SURFACE_POINTS = 50_000  # points sampled on each surface; ~0.2 mm spacing on a 10 cm object
SURFACE_SEED = 0  # fixed so every policy is measured on the same GT sample
SSIM_SIGMA = 1.5  # Gaussian window of Wang et al. 2004 (the SSIM the paper cites)
SSIM_RADIUS = 5  # 11 x 11 window, as in Wang et al. 2004
SSIM_K1 = 0.01  # Wang et al. 2004
SSIM_K2 = 0.03  # Wang et al. 2004
DATA_RANGE = 255.0  # 8-bit images

__all__ = [
    "ReferenceSurface",
    "psnr",
    "render_mesh",
    "sample_surface",
    "ssim",
    "ssim_map",
    "surface_metrics",
]


def sample_surface(
    vertices: np.ndarray, triangles: np.ndarray, num_points: int, seed: int = SURFACE_SEED
) -> np.ndarray:
    """(num_points, 3) float64 points uniform by area on the triangle mesh; (0, 3) if it has no area.

    vertices (V, 3) metres; triangles (F, 3) vertex indices. The sample depends on the surface, not
    on how its triangles are listed: Open3D's multi-threaded mesh extraction lists the same
    triangles in a different order from run to run, so the triangles are put in a canonical order
    first (each starting at its lexicographically smallest corner, orientation kept, then sorted).
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    triangles = np.asarray(triangles, dtype=np.int64)
    if len(triangles) == 0 or num_points <= 0:
        return np.zeros((0, 3))
    # the corners' positions ranked (equal positions, equal rank): comparing ranks compares the
    # corners lexicographically, on integers and without sorting 3 corners per triangle
    classes = position_classes(vertices)
    rows = np.arange(len(triangles))[:, None]
    turn = smallest_first(classes[triangles])  # the smallest corner first (the first of equals)
    triangles = triangles[rows, turn]
    ranked = classes[triangles]
    corners = vertices[triangles[row_order(ranked, int(classes.max()) + 1)]]
    finite = np.isfinite(corners).all(axis=(1, 2))
    if not finite.all():
        bad = corners[~finite][0]
        raise InputError("vertices", bad.tolist(), "finite corners of every triangle (metres)")
    a, b, c = corners[:, 0], corners[:, 1], corners[:, 2]
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    total = area.sum()
    if not total > 0:
        return np.zeros((0, 3))
    rng = np.random.default_rng(seed)
    face = rng.choice(len(corners), size=num_points, p=area / total)
    r1, r2 = rng.random(num_points), rng.random(num_points)
    flip = r1 + r2 > 1.0  # reflect into the triangle: uniform barycentric sampling
    r1, r2 = np.where(flip, 1.0 - r1, r1), np.where(flip, 1.0 - r2, r2)
    return a[face] + r1[:, None] * (b[face] - a[face]) + r2[:, None] * (c[face] - a[face])


def distance_metrics(
    recon_points: np.ndarray,
    gt_points: np.ndarray,
    tau: float,
    gt_tree: cKDTree | None = None,
    gt_to_recon: np.ndarray | None = None,
) -> dict[str, float]:
    """The surface metrics of the module docstring from two point samples (N, 3), (M, 3) metres.

    gt_to_recon: (M,) distance of each GT point to the reconstruction's surface, when known exactly;
    otherwise the distance to the nearest reconstruction point is used."""
    if not tau > 0:
        raise InputError("tau", tau, "a distance threshold > 0 metres")
    gt_points = np.asarray(gt_points, dtype=np.float64)
    recon_points = np.asarray(recon_points, dtype=np.float64)
    if len(gt_points) == 0:
        raise InputError("gt_points", "0 points", "a non-empty ground-truth sample")
    if len(recon_points) == 0:
        return {
            "accuracy": float("nan"),
            "completeness": float("inf"),
            "chamfer": float("inf"),
            "precision": 0.0,
            "recall": 0.0,
            "completion": 0.0,
            "fscore": 0.0,
            "num_recon_points": 0,
        }
    gt_tree = gt_tree if gt_tree is not None else cKDTree(gt_points)
    d_recon, _ = gt_tree.query(recon_points, workers=-1)
    if gt_to_recon is None:
        d_gt, _ = cKDTree(recon_points).query(gt_points, workers=-1)
    else:
        d_gt = np.asarray(gt_to_recon, dtype=np.float64)
    accuracy, completeness = float(d_recon.mean()), float(d_gt.mean())
    precision, recall = float(np.mean(d_recon < tau)), float(np.mean(d_gt < tau))
    fscore = 2 * precision * recall / (precision + recall) if precision + recall > 0 else 0.0
    return {
        "accuracy": accuracy,
        "completeness": completeness,
        "chamfer": 0.5 * (accuracy + completeness),
        "precision": precision,
        "recall": recall,
        "completion": recall,
        "fscore": float(fscore),
        "num_recon_points": int(len(recon_points)),
    }


class ReferenceSurface:
    """The ground-truth surface sampled once (and its KD-tree), to compare many reconstructions."""

    def __init__(
        self, gt_mesh: Any, num_points: int = NUM_SURFACE_POINTS, seed: int = SURFACE_SEED
    ) -> None:
        vertices, triangles, _ = mesh_arrays(gt_mesh)
        self.points = sample_surface(vertices, triangles, num_points, seed)
        if len(self.points) == 0:
            raise InputError(
                "gt_mesh", f"{len(triangles)} triangles", "a ground-truth mesh with surface area"
            )
        self.num_points = num_points
        self.seed = seed
        self.tree = cKDTree(self.points)

    def compare(
        self, recon_mesh: Any, tau: float, surface: MeshRenderer | None = None
    ) -> dict[str, float]:
        """Surface metrics of `recon_mesh` (open3d or trimesh) at threshold tau (metres).

        surface: the `MeshRenderer` of the same mesh when the caller renders it too (its
        ray-casting scene answers the distances; built once for both)."""
        vertices, triangles, _ = mesh_arrays(recon_mesh)
        recon = sample_surface(vertices, triangles, self.num_points, self.seed + 1)
        if len(recon) == 0:
            return distance_metrics(recon, self.points, tau, self.tree)
        surface = MeshRenderer(recon_mesh) if surface is None else surface
        gt_to_recon = surface.distances(self.points)
        return distance_metrics(recon, self.points, tau, self.tree, gt_to_recon)


def surface_metrics(
    recon_mesh: Any,
    gt_mesh: Any,
    tau: float,
    num_points: int = NUM_SURFACE_POINTS,
    seed: int = SURFACE_SEED,
) -> dict[str, float]:
    """Accuracy, completeness, Chamfer, precision, recall = completion, F-score at tau (metres)."""
    return ReferenceSurface(gt_mesh, num_points, seed).compare(recon_mesh, tau)


def _check_pair(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    a, b = np.asarray(a), np.asarray(b)
    if a.ndim not in (2, 3):
        raise InputError("a", a.shape, "an (H, W) or (H, W, C) image")
    if b.shape != a.shape:
        raise InputError("b", b.shape, f"the shape of a, {a.shape}")
    return a, b


def psnr(
    a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None, data_range: float = DATA_RANGE
) -> float:
    """Peak signal-to-noise ratio in dB over all pixels (or those where `mask` (H, W) is True),
    scikit-image's `peak_signal_noise_ratio`.

    a, b: (H, W) or (H, W, C) images on a 0..data_range scale (uint8 by default). Identical images
    give inf; an empty mask gives NaN.
    """
    a, b = _check_pair(a, b)
    if mask is not None:
        mask = np.asarray(mask, dtype=bool)
        if mask.shape != a.shape[:2]:
            raise InputError("mask", mask.shape, f"(H, W) = {a.shape[:2]}")
        if not mask.any():
            return float("nan")
        a, b = a[mask], b[mask]
    with np.errstate(divide="ignore"):  # identical images: 10 log10(peak^2 / 0) = inf
        return float(peak_signal_noise_ratio(a, b, data_range=data_range))


def ssim_map(a: np.ndarray, b: np.ndarray, data_range: float = DATA_RANGE) -> np.ndarray:
    """(H, W) SSIM of Wang et al. 2004 per pixel, averaged over channels: scikit-image's
    `structural_similarity` with the paper's settings (11 x 11 Gaussian window of sigma 1.5, K1
    0.01, K2 0.03, population covariance), mirrored at the border. a, b (H, W) or (H, W, C) on a
    0..data_range scale, at least 11 x 11 pixels."""
    a, b = _check_pair(a, b)
    window = 2 * SSIM_RADIUS + 1
    if min(a.shape[:2]) < window:
        raise InputError(
            "a", a.shape, f"an image of at least {window} x {window} pixels (the window)"
        )
    _, s = structural_similarity(
        a,
        b,
        data_range=data_range,
        channel_axis=-1 if a.ndim == 3 else None,
        gaussian_weights=True,
        sigma=SSIM_SIGMA,
        use_sample_covariance=False,
        K1=SSIM_K1,
        K2=SSIM_K2,
        full=True,
    )
    return s.mean(axis=-1) if a.ndim == 3 else s


def ssim(
    a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None, data_range: float = DATA_RANGE
) -> float:
    """Mean SSIM (Wang et al. 2004) of two images, over the pixels at least one window radius from
    the border (as scikit-image's and the reference implementation's mean) and, if given, inside
    `mask` (H, W). Identical images give 1.0; an empty mask gives NaN."""
    return mean_ssim(ssim_map(a, b, data_range), mask)


def mean_ssim(s: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Mean of an (H, W) SSIM map away from the border and inside `mask` (see `ssim`)."""
    keep = np.zeros(s.shape, dtype=bool)
    r = SSIM_RADIUS
    if s.shape[0] > 2 * r and s.shape[1] > 2 * r:
        keep[r:-r, r:-r] = True
    else:
        keep[:] = True
    if mask is not None:
        mask = np.asarray(mask, dtype=bool)
        if mask.shape != s.shape:
            raise InputError("mask", mask.shape, f"(H, W) = {s.shape}")
        keep &= mask
    return float(s[keep].mean()) if keep.any() else float("nan")
