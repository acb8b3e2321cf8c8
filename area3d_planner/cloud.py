"""The fused uncertainty grid as a point cloud (one point per non-empty voxel) and as PointCloud2."""

from __future__ import annotations

import numpy as np

from area3d_planner.fusion import OCCUPIED, FusedGrid

CLOUD_DTYPE = np.dtype(
    [
        ("x", np.float32),
        ("y", np.float32),
        ("z", np.float32),
        ("uncertainty", np.float32),
        ("geometric", np.float32),
        ("semantic", np.float32),
        ("occupancy", np.float32),
        ("hard", np.float32),
    ]
)

# A voxel carrying only the global weight gamma is "empty": publishing every unexplored voxel of a
# room would drown the display, so the cloud keeps voxels whose fused uncertainty exceeds gamma by
# this margin, plus every occupied voxel.
EMPTY_MARGIN = 1e-6


def grid_to_cloud(grid: FusedGrid, field: np.ndarray | None = None) -> np.ndarray:
    """Structured array (CLOUD_DTYPE) of the non-empty voxels, at voxel centres in `world`.

    A voxel is non-empty when it is occupied, or its fused uncertainty (or `field` (N,), e.g. a
    decayed copy) is > gamma + EMPTY_MARGIN. uncertainty = the fused U, geometric and semantic =
    the two fields, occupancy = -1 unknown, 0 free, 1 occupied (as float32), hard = 1 on the
    voxels no view is expected to resolve (`FusedGrid.hard`), else 0.
    """
    occ = grid.occupancy()
    geo = grid.geometric(occ)
    u = grid.fused(occ, geo) if field is None else np.asarray(field, np.float32)
    keep = np.flatnonzero((occ == OCCUPIED) | (u > grid.gamma + EMPTY_MARGIN))
    ijk = np.stack(np.unravel_index(keep, grid.spec.shape), axis=1)
    xyz = grid.spec.lower + (ijk + 0.5) * grid.spec.voxel_size
    cloud = np.empty(keep.size, CLOUD_DTYPE)
    cloud["x"], cloud["y"], cloud["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    cloud["uncertainty"] = u[keep]
    cloud["geometric"] = geo[keep]
    cloud["semantic"] = grid.semantic()[keep]
    cloud["occupancy"] = occ[keep]
    cloud["hard"] = grid.hard(occ)[keep]
    return cloud
