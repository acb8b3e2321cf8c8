"""The geometric uncertainty field: confidence splatted into voxels, plus free space carved by rays.

Per voxel three accumulators, all (nx, ny, nz) on a `GridSpec`:

    evidence   sum of normalised confidences of the pixels that landed in it (`splat_confidence`)
    hits       how many pixels landed in it
    free       how many camera rays passed through it before their hit (`carve_free_space`)

`geometric_uncertainty` turns them into U_geo in [0, 1]: a surface voxel (hits > 0) gets
1 - evidence / hits, a voxel only ever crossed by rays (known free) gets 0, and a voxel nothing has
seen gets `unobserved_uncertainty` (the paper: low confidence and unobserved space mean high
uncertainty).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from area3d_msgs_py.backproject import backproject
from area3d_msgs_py.carving import check_grid_array, check_points
from area3d_msgs_py.errors import InputError
from area3d_msgs_py.grid import GridSpec

# Unobserved space is maximally uncertain (DESIGN.md: "unobserved space means high uncertainty").
UNOBSERVED_UNCERTAINTY = 1.0


@njit(cache=True)
def _splat_points(points, weights, lower, inv_voxel, shape, evidence, hits):  # pragma: no cover
    nx, ny, nz = shape[0], shape[1], shape[2]
    for n in range(points.shape[0]):
        w = weights[n]
        if not np.isfinite(w):
            continue
        fi = (points[n, 0] - lower[0]) * inv_voxel
        fj = (points[n, 1] - lower[1]) * inv_voxel
        fk = (points[n, 2] - lower[2]) * inv_voxel
        if not (fi >= 0 and fj >= 0 and fk >= 0):  # also rejects NaN
            continue
        i, j, k = int(fi), int(fj), int(fk)
        if i >= nx or j >= ny or k >= nz:
            continue
        flat = (i * ny + j) * nz + k
        evidence[flat] += w
        hits[flat] += 1


def splat_confidence(
    spec: GridSpec,
    points: np.ndarray,
    weights: np.ndarray,
    evidence: np.ndarray | None = None,
    hits: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Accumulate per-point weights and counts into the voxels that contain the points.

    spec: the grid. points: (N, 3) world metres. weights: (N,) normalised confidence in [0, 1].
    evidence, hits: (nx, ny, nz) float32 accumulators updated in place (new zeros when None).
    Points outside the grid or non-finite are ignored.
    Returns (evidence, hits).
    """
    points = check_points("points", points)
    weights = np.asarray(weights, dtype=np.float64).reshape(-1)
    if weights.shape[0] != points.shape[0]:
        raise InputError(
            "weights", f"length {weights.shape[0]}", f"one weight per point ({points.shape[0]})"
        )
    evidence = (
        np.zeros(spec.shape, np.float32)
        if evidence is None
        else check_grid_array("evidence", evidence, spec)
    )
    hits = (
        np.zeros(spec.shape, np.float32) if hits is None else check_grid_array("hits", hits, spec)
    )
    _splat_points(
        points,
        weights,
        spec.lower,
        1.0 / spec.voxel_size,
        np.asarray(spec.shape, dtype=np.int64),
        evidence.reshape(-1),
        hits.reshape(-1),
    )
    return evidence, hits


def geometric_uncertainty(
    conf_sum: np.ndarray,
    hit_count: np.ndarray,
    observed_mask: np.ndarray,
    unobserved_uncertainty: float = UNOBSERVED_UNCERTAINTY,
) -> np.ndarray:
    """U_geo per voxel in [0, 1].

    conf_sum: (nx, ny, nz) summed normalised confidence; hit_count: (nx, ny, nz) pixel counts;
    observed_mask: (nx, ny, nz) bool, True where any ray has crossed the voxel (e.g. free > 0).
    Surface voxels (hit_count > 0) get 1 - conf_sum / hit_count; observed voxels without hits get 0;
    the rest get `unobserved_uncertainty`.
    Returns (nx, ny, nz) float32.
    """
    conf_sum = np.asarray(conf_sum, dtype=np.float32)
    hit_count = np.asarray(hit_count, dtype=np.float32)
    observed_mask = np.asarray(observed_mask, dtype=bool)
    if hit_count.shape != conf_sum.shape or observed_mask.shape != conf_sum.shape:
        raise InputError(
            "hit_count/observed_mask",
            (hit_count.shape, observed_mask.shape),
            f"the shape of conf_sum {conf_sum.shape}",
        )
    if not (0.0 <= unobserved_uncertainty <= 1.0):
        raise InputError("unobserved_uncertainty", unobserved_uncertainty, "a value in [0, 1]")
    surface = hit_count > 0
    u = np.where(observed_mask, np.float32(0.0), np.float32(unobserved_uncertainty)).astype(
        np.float32
    )
    mean_conf = conf_sum[surface] / hit_count[surface]
    u[surface] = np.clip(1.0 - mean_conf, 0.0, 1.0)
    return u


def splat_depth_frame(
    spec: GridSpec,
    depth: np.ndarray,
    confidence: np.ndarray,
    K: np.ndarray,
    T_world_cam: np.ndarray,
    evidence: np.ndarray,
    hits: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Back-project a frame (X = T (D K^-1 x), the paper) and splat its confidence into the grid.

    depth: (H, W) metres, NaN = no return. confidence: (H, W) in [0, 1]. Returns (evidence, hits).
    """
    if confidence.shape != depth.shape:
        raise InputError(
            "confidence", f"shape {confidence.shape}", f"the depth shape {depth.shape}"
        )
    points, pixel = backproject(depth, K, T_world_cam)
    return splat_confidence(spec, points, confidence.reshape(-1)[pixel], evidence, hits)
