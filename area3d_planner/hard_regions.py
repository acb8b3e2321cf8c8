"""Hard regions: the hard voxels of the map (`FusedGrid.hard`) grouped into connected regions.

A hard voxel is a region voxel observed from several distinct directions that never reached a
usable confidence: no view is expected to resolve it (a dark, shiny or thin surface, a deep gap).
An operator wants them as places, not as voxels: each connected group (26-connectivity: voxels
that share a face, an edge or a corner) becomes one region with its centroid, the size of its
axis-aligned bounding box, its voxel count, the most distinct directions any of its voxels was
observed from and the mean fused uncertainty of its voxels. Regions come largest first; a single
voxel is a region too.

Pure numpy / scipy, no ROS: `hard_regions` on integer voxel coordinates, `cloud_hard_regions` on
the planner's grid cloud (`cloud.grid_to_cloud`), `points_hard_regions` on a saved grid's points
(the report, which imports no message code). Rows are `area3d_msgs_py.hard_region.HARD_REGION_DTYPE`,
what the node publishes with `codecs.hard_regions_to_msg`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from scipy import ndimage

from area3d_msgs_py.errors import InputError
from area3d_msgs_py.hard_region import HARD_REGION_DTYPE

if TYPE_CHECKING:  # the report reads saved grids without the fusion kernels
    from area3d_planner.fusion import FusedGrid

# 26-connectivity: face, edge and corner neighbours belong to one region
CONNECTIVITY = np.ones((3, 3, 3), bool)


def hard_regions(
    ijk: np.ndarray,
    lower: np.ndarray,
    voxel_size: float,
    direction_count: np.ndarray,
    uncertainty: np.ndarray,
) -> np.ndarray:
    """The connected regions of a set of voxels, largest first.

    ijk: (K, 3) integer voxel coordinates of the hard voxels (each once); lower: (3,) world
    metres of the corner of voxel (0, 0, 0); voxel_size: metres; direction_count: (K,) distinct
    directions each voxel was observed from; uncertainty: (K,) its fused uncertainty.
    Returns (R,) HARD_REGION_DTYPE: centroid = mean of the voxel centres, extent = the bounding
    box of the voxels (a single voxel: voxel_size on each axis), voxel_count, direction_count =
    the most of any of its voxels, mean_uncertainty. Ordered by voxel count, then mean
    uncertainty (both descending), then centroid.
    """
    ijk = np.asarray(ijk)
    if ijk.ndim != 2 or ijk.shape[1] != 3 or not np.issubdtype(ijk.dtype, np.integer):
        raise InputError("ijk", f"{ijk.dtype} {ijk.shape}", "(K, 3) integer voxel coordinates")
    direction_count = np.asarray(direction_count).reshape(-1)
    uncertainty = np.asarray(uncertainty, np.float64).reshape(-1)
    if direction_count.size != len(ijk) or uncertainty.size != len(ijk):
        raise InputError(
            "direction_count/uncertainty",
            (direction_count.size, uncertainty.size),
            f"one value per voxel ({len(ijk)})",
        )
    if not (np.isfinite(voxel_size) and voxel_size > 0):
        raise InputError("voxel_size", voxel_size, "a voxel edge > 0 metres")
    if len(ijk) == 0:
        return np.zeros(0, HARD_REGION_DTYPE)
    # label only the box the hard voxels span: they are few in a grid of millions
    origin = ijk.min(axis=0)
    local = ijk - origin
    mask = np.zeros(local.max(axis=0) + 1, bool)
    mask[tuple(local.T)] = True
    labels, count = ndimage.label(mask, structure=CONNECTIVITY)
    label = labels[tuple(local.T)] - 1  # (K,) region of each voxel, 0-based

    centres = np.asarray(lower, np.float64) + (ijk + 0.5) * float(voxel_size)
    voxels = np.bincount(label, minlength=count)
    order = np.argsort(label, kind="stable")
    starts = np.flatnonzero(np.r_[True, np.diff(label[order]) != 0])
    regions = np.zeros(count, HARD_REGION_DTYPE)
    regions["voxel_count"] = voxels
    for axis in range(3):
        regions["centroid"][:, axis] = np.bincount(label, centres[:, axis], count) / voxels
        sorted_axis = centres[order, axis]
        low = np.minimum.reduceat(sorted_axis, starts)
        high = np.maximum.reduceat(sorted_axis, starts)
        regions["extent"][:, axis] = high - low + float(voxel_size)
    regions["direction_count"] = np.maximum.reduceat(direction_count[order], starts)
    regions["mean_uncertainty"] = np.bincount(label, uncertainty, count) / voxels
    rank = np.lexsort(
        (
            regions["centroid"][:, 2],
            regions["centroid"][:, 1],
            regions["centroid"][:, 0],
            -regions["mean_uncertainty"],
            -regions["voxel_count"].astype(np.int64),
        )
    )
    return regions[rank]


def cloud_hard_regions(cloud: np.ndarray, grid: FusedGrid) -> np.ndarray:
    """The hard regions of `grid` from its cloud (`cloud.grid_to_cloud(grid)`: every hard voxel is
    a point of it, flagged by its `hard` field, with its fused uncertainty); the direction counts
    come from the grid."""
    rows = np.flatnonzero(np.asarray(cloud["hard"]) > 0)
    xyz = np.stack([cloud[axis][rows] for axis in "xyz"], axis=1).astype(np.float64)
    ids, _ = grid.spec.flat_index(xyz)
    ijk = np.stack(np.unravel_index(ids, grid.spec.shape), axis=1)
    directions = np.bitwise_count(grid.directions[ids])
    return hard_regions(
        ijk, grid.spec.lower, grid.spec.voxel_size, directions, cloud["uncertainty"][rows]
    )


def grid_voxel_size(xyz: np.ndarray) -> float | None:
    """The voxel edge of a grid saved as voxel centres (N, 3): the median of the gaps between
    neighbouring distinct coordinates along the axes that are one voxel wide (within half a voxel
    of the smallest; None when no two centres differ). Centres saved in float32 are a voxel apart
    only to their precision, which at tens of metres from the origin is 1e-3 of a 1 cm voxel: the
    smallest gap alone would be that much short."""
    xyz = np.asarray(xyz, np.float64).reshape(-1, 3)
    gaps = [np.diff(np.unique(xyz[:, axis])) for axis in range(3)]
    gaps = np.concatenate(gaps) if gaps else np.zeros(0)
    gaps = gaps[gaps > 1e-6]
    if not gaps.size:
        return None
    return float(np.median(gaps[gaps < 1.5 * gaps.min()]))


def points_hard_regions(
    xyz: np.ndarray, uncertainty: np.ndarray, voxel_size: float, direction_count=None
) -> np.ndarray:
    """The regions of voxels given by their centres xyz (K, 3) on a grid of `voxel_size` (a saved
    grid's hard points); direction_count (K,) where known, else 0."""
    xyz = np.asarray(xyz, np.float64).reshape(-1, 3)
    if len(xyz) == 0:
        return np.zeros(0, HARD_REGION_DTYPE)
    base = xyz.min(axis=0)
    ijk = np.rint((xyz - base) / voxel_size).astype(np.int64)
    directions = np.zeros(len(xyz), np.uint32) if direction_count is None else direction_count
    return hard_regions(ijk, base - 0.5 * voxel_size, voxel_size, directions, uncertainty)
