"""Candidate view seeds, orientation bins and the cached Monte Carlo visibility masks."""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from area3d_msgs_py.errors import InputError
from area3d_perception.grid import GridSpec
from area3d_planner.raycast import (
    VOXEL_OCCUPIED,
    VOXEL_RELEVANT,
    score_all_views,
    score_views,
    visibility_masks,
)

UP = np.array([0.0, 0.0, 1.0])
CHUNKS_PER_THREAD = 16  # seed chunks per worker thread when building masks (load balance)


@dataclass(frozen=True)
class VisibilityParams:
    """Tunables of the visibility cache (defaults: paper where it fixes them, else our choice)."""

    yaw_bins: int = 12  # 30 degree yaw steps: a coarse yaw/pitch grid (paper, "Visibility Gate")
    pitch_bins: int = 5  # pitch from pitch_min_deg to pitch_max_deg
    pitch_min_deg: float = -60.0  # looking down onto a table or floor
    pitch_max_deg: float = 30.0  # looking slightly up
    mc_rays: int = 256  # R_pre, Monte Carlo rays per seed and bin (paper Algorithm 1)
    hfov_deg: float = 90.0  # paper, supplement: FOV 90 degrees
    width: int = 640  # image aspect of the frustum
    height: int = 480
    max_range: float = 5.0  # paper, supplement: max depth 5 m (far plane at optical z = 5 m)
    rng_seed: int = 0  # ray sampling is reproducible
    # "coverage": a voxel's weight estimates how much of it the view sees (rays scaled by range^2),
    # so utility counts uncertain voxels in view; "ray_fraction": share of rays reaching it.
    weighting: str = "coverage"

    def validate(self) -> None:
        if self.weighting not in ("coverage", "ray_fraction"):
            raise InputError("weighting", self.weighting, "'coverage' or 'ray_fraction'")
        for name in ("yaw_bins", "pitch_bins", "mc_rays", "width", "height"):
            value = getattr(self, name)
            if int(value) < 1:
                raise InputError(name, value, "an integer >= 1")
        if not (0 < self.hfov_deg < 180):
            raise InputError("hfov_deg", self.hfov_deg, "a value in (0, 180) degrees")
        if not (self.max_range > 0 and np.isfinite(self.max_range)):
            raise InputError("max_range", self.max_range, "a finite value > 0 metres")
        if not (-90 < self.pitch_min_deg <= self.pitch_max_deg < 90):
            raise InputError(
                "pitch_min_deg/pitch_max_deg",
                (self.pitch_min_deg, self.pitch_max_deg),
                "-90 < pitch_min_deg <= pitch_max_deg < 90",
            )


def look_rotation(forward: np.ndarray) -> np.ndarray:
    """(3, 3) R_world_cam of an optical frame with z along `forward`, x horizontal (zero roll), y down.

    forward: (3,) direction, need not be unit; straight up/down falls back to x = world +x.
    """
    z = np.asarray(forward, dtype=np.float64)
    z = z / np.linalg.norm(z)
    x = np.cross(z, UP)
    nx = np.linalg.norm(x)
    x = np.array([1.0, 0.0, 0.0]) if nx < 1e-9 else x / nx
    y = np.cross(z, x)
    return np.stack([x, y, z], axis=1)


def look_at(position: np.ndarray, target: np.ndarray) -> np.ndarray:
    """(4, 4) T_world_cam at `position` whose optical axis points at `target` (zero roll)."""
    T = np.eye(4)
    T[:3, :3] = look_rotation(np.asarray(target, float) - np.asarray(position, float))
    T[:3, 3] = position
    return T


def orientation_bins(params: VisibilityParams) -> tuple[np.ndarray, np.ndarray]:
    """Yaw x pitch bins: (forward (B, 3) unit directions, rotations (B, 3, 3) R_world_cam).

    B = yaw_bins * pitch_bins, bin index = yaw_index * pitch_bins + pitch_index.
    """
    yaws = np.deg2rad(np.arange(params.yaw_bins) * 360.0 / params.yaw_bins)
    if params.pitch_bins == 1:
        pitches = np.deg2rad([0.5 * (params.pitch_min_deg + params.pitch_max_deg)])
    else:
        pitches = np.deg2rad(
            np.linspace(params.pitch_min_deg, params.pitch_max_deg, params.pitch_bins)
        )
    yy, pp = np.meshgrid(yaws, pitches, indexing="ij")
    yy, pp = yy.ravel(), pp.ravel()
    forward = np.stack([np.cos(pp) * np.cos(yy), np.cos(pp) * np.sin(yy), np.sin(pp)], axis=1)
    rotations = np.stack([look_rotation(f) for f in forward])
    return forward, rotations


def frustum_rays(params: VisibilityParams) -> tuple[np.ndarray, np.ndarray]:
    """mc_rays directions uniform over the image plane (stratified, jittered, seeded).

    Returns (dirs (R, 3) unit optical-frame directions, t_far (R,) ray length to z = max_range).
    """
    rng = np.random.default_rng(params.rng_seed)
    r = params.mc_rays
    tan_x = np.tan(np.deg2rad(params.hfov_deg) / 2)
    tan_y = tan_x * params.height / params.width
    cols = max(1, int(round(np.sqrt(r * params.width / params.height))))
    cell = np.arange(r)
    u = ((cell % cols) + rng.random(r)) / cols
    rows = int(np.ceil(r / cols))
    v = ((cell // cols) + rng.random(r)) / rows
    d = np.stack([(2 * u - 1) * tan_x, (2 * v - 1) * tan_y, np.ones(r)], axis=1)
    norms = np.linalg.norm(d, axis=1)
    return d / norms[:, None], params.max_range * norms


def candidate_seeds(
    workspace_lo: np.ndarray,
    workspace_hi: np.ndarray,
    seed_spacing: float,
    spec: GridSpec,
    occupancy: np.ndarray,
    clearance: float = 0.05,  # same default as sim_bridge.validity.check_pose
    allow_unknown: bool = False,
    scene: object | None = None,
) -> np.ndarray:
    """Centres of a `seed_spacing` voxelisation of the workspace that are valid camera positions.

    A seed is kept when it lies inside the workspace, no occupied voxel centre is closer than
    clearance + voxel_size / 2, its voxel is known free (or outside the grid) unless
    allow_unknown, and, with a scene, `sim_bridge.validity.valid_positions` accepts it.
    Returns (S, 3) float64 world metres.
    """
    lo = np.asarray(workspace_lo, dtype=np.float64)
    hi = np.asarray(workspace_hi, dtype=np.float64)
    if (
        lo.shape != (3,)
        or hi.shape != (3,)
        or not np.all(hi > lo)
        or not np.all(np.isfinite(hi - lo))
    ):
        raise InputError(
            "workspace", [lo.tolist(), hi.tolist()], "workspace_min < workspace_max on every axis"
        )
    if not (seed_spacing > 0 and np.isfinite(seed_spacing)):
        raise InputError("seed_spacing", seed_spacing, "a finite value > 0 metres")
    counts = np.maximum(np.floor((hi - lo) / seed_spacing + 1e-9).astype(int), 1)
    offset = lo + 0.5 * ((hi - lo) - (counts - 1) * seed_spacing)
    axes = [offset[a] + np.arange(counts[a]) * seed_spacing for a in range(3)]
    seeds = np.stack([g.ravel() for g in np.meshgrid(*axes, indexing="ij")], axis=1)
    seeds = seeds[np.all((seeds >= lo) & (seeds <= hi), axis=1)]

    occupied = np.flatnonzero(occupancy == 1)
    if occupied.size:
        tree = cKDTree(spec.centers()[occupied])
        dist, _ = tree.query(
            seeds, k=1, distance_upper_bound=clearance + 0.5 * spec.voxel_size + 1e-12
        )
        seeds = seeds[~np.isfinite(dist)]
    if not allow_unknown and seeds.size:
        vox, inside = spec.flat_index(seeds)
        seeds = seeds[~inside | (occupancy[vox] == 0)]
    if scene is not None and seeds.size:  # anything with valid_positions(points, clearance)
        seeds = seeds[np.asarray(scene.valid_positions(seeds, clearance), dtype=bool)]
    return seeds.reshape(-1, 3)


class VisibilityCache:
    """Cached visibility masks of every view (seed s, orientation bin b), view index s * B + b.

    CSR layout: the mask of view v is voxel_ids[indptr[v]:indptr[v+1]] (int32 flat voxel index)
    with weights (float32): the fraction of the view's Monte Carlo rays that reach the voxel.
    Scoring a view against a field U (N,) is the dot product sum_i w_i U[id_i].
    """

    def __init__(
        self,
        spec: GridSpec,
        seeds: np.ndarray,
        forward: np.ndarray,
        rotations: np.ndarray,
        indptr: np.ndarray,
        voxel_ids: np.ndarray,
        weights: np.ndarray,
    ) -> None:
        self.spec = spec
        self.seeds = seeds
        self.forward = forward
        self.rotations = rotations
        self.indptr = indptr
        self.voxel_ids = voxel_ids
        self.weights = weights

    @property
    def num_seeds(self) -> int:
        return int(self.seeds.shape[0])

    @property
    def num_bins(self) -> int:
        return int(self.forward.shape[0])

    @property
    def num_views(self) -> int:
        return self.num_seeds * self.num_bins

    @classmethod
    def build(
        cls,
        spec: GridSpec,
        occupancy: np.ndarray,
        seeds: np.ndarray,
        params: VisibilityParams | None = None,
        relevant: np.ndarray | None = None,
        threads: int | None = None,
    ) -> VisibilityCache:
        """Cast params.mc_rays rays per (seed, bin) with first-hit termination on occupied voxels.

        occupancy: (N,) int8 (-1 unknown, 0 free, 1 occupied). seeds: (S, 3) camera centres.
        relevant: (N,) bool, the voxels recorded in the masks (default: every voxel that is not
        known free; a field that is 0 elsewhere scores the same, with far smaller masks). Rays
        are cast only towards the bounding box of the relevant voxels.
        threads: worker threads (default: CPU count); the result does not depend on it.
        """
        params = params or VisibilityParams()
        params.validate()
        occupancy = np.ascontiguousarray(occupancy, dtype=np.int8)
        if occupancy.shape != (spec.num_voxels,):
            raise InputError(
                "occupancy", occupancy.shape, f"({spec.num_voxels},) int8 flat occupancy"
            )
        seeds = np.ascontiguousarray(np.asarray(seeds, dtype=np.float64).reshape(-1, 3))
        if relevant is None:
            relevant = occupancy != 0
        relevant = np.ascontiguousarray(relevant, dtype=np.bool_)
        forward, rotations = orientation_bins(params)
        dirs, t_far = frustum_rays(params)
        rel_ids = np.flatnonzero(relevant)
        if rel_ids.size:
            ijk = np.stack(np.unravel_index(rel_ids, spec.shape), axis=1)
            box_lo = spec.lower + ijk.min(axis=0) * spec.voxel_size
            box_hi = spec.lower + (ijk.max(axis=0) + 1) * spec.voxel_size
        else:
            box_lo = box_hi = spec.lower.copy()
        tan_x = np.tan(np.deg2rad(params.hfov_deg) / 2)
        cos_half_diag = 1.0 / np.sqrt(1.0 + tan_x**2 * (1.0 + (params.height / params.width) ** 2))
        scale_by_range = params.weighting == "coverage"
        if scale_by_range:
            # Rays are uniform on the image plane z = 1 (area 4 tan_x tan_y): each stands for
            # area / R there, i.e. a solid angle of (area / R) cos^3 of its angle to the axis.
            tan_y = tan_x * params.height / params.width
            cos_axis = dirs[:, 2] / np.linalg.norm(dirs, axis=1)
            ray_weight = (4 * tan_x * tan_y / dirs.shape[0]) * cos_axis**3 / spec.voxel_size**2
        else:
            ray_weight = np.full(dirs.shape[0], 1.0 / dirs.shape[0])
        shape = np.asarray(spec.shape, np.int64)
        flags = (occupancy == 1).astype(np.uint8) * VOXEL_OCCUPIED
        flags |= relevant.astype(np.uint8) * VOXEL_RELEVANT
        threads = max(1, min(threads or os.cpu_count() or 1, max(1, seeds.shape[0])))
        # Small chunks handed out in order balance the threads (seeds differ a lot in cost);
        # each thread reuses one scratch pair for all its chunks.
        n_chunks = min(seeds.shape[0], threads * CHUNKS_PER_THREAD) if threads > 1 else 1
        chunks = np.array_split(np.arange(seeds.shape[0]), max(1, n_chunks))
        scratch = threading.local()
        ray_weight = np.ascontiguousarray(ray_weight, np.float64)

        def run(idx: np.ndarray):
            if not hasattr(scratch, "counts"):
                scratch.counts = np.zeros(spec.num_voxels, np.float64)
                scratch.touched = np.empty(spec.num_voxels, np.int32)
            return visibility_masks(
                np.ascontiguousarray(seeds[idx]),
                rotations,
                dirs,
                t_far,
                spec.lower,
                spec.voxel_size,
                shape,
                flags,
                box_lo,
                box_hi,
                cos_half_diag,
                ray_weight,
                scale_by_range,
                scratch.counts,
                scratch.touched,
            )

        if threads == 1:
            parts = [run(chunks[0])]
        else:
            with ThreadPoolExecutor(max_workers=threads) as pool:
                parts = list(pool.map(run, chunks))
        nnz = np.concatenate([p[0] for p in parts])
        indptr = np.zeros(nnz.size + 1, np.int64)
        np.cumsum(nnz, out=indptr[1:])
        voxel_ids = np.concatenate([p[1] for p in parts]) if parts else np.zeros(0, np.int32)
        weights = np.concatenate([p[2] for p in parts]) if parts else np.zeros(0, np.float32)
        return cls(spec, seeds, forward, rotations, indptr, voxel_ids, weights)

    def score(self, field: np.ndarray) -> np.ndarray:
        """(num_views,) float64 mask-weighted utility of every view under field U (N,)."""
        return score_all_views(
            self.indptr, self.voxel_ids, self.weights, np.asarray(field, np.float64)
        )

    def score_seed(self, field: np.ndarray, seed: int) -> np.ndarray:
        """(num_bins,) float64 utilities of one seed's views (same sums as `score`)."""
        b = self.num_bins
        return score_views(self.indptr, self.voxel_ids, self.weights, field, seed * b, seed * b + b)

    def mask(self, view: int) -> tuple[np.ndarray, np.ndarray]:
        """(voxel ids int32, weights float32) of one view."""
        lo, hi = self.indptr[view], self.indptr[view + 1]
        return self.voxel_ids[lo:hi], self.weights[lo:hi]

    def view_pose(self, view: int) -> np.ndarray:
        """(4, 4) T_world_cam of a view (optical frame)."""
        s, b = divmod(int(view), self.num_bins)
        T = np.eye(4)
        T[:3, :3] = self.rotations[b]
        T[:3, 3] = self.seeds[s]
        return T
