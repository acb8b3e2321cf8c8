import numpy as np
import pytest

from area3d_perception.grid import GridSpec
from area3d_planner.fusion import FusedGrid


def set_occupancy(grid: FusedGrid, occ: np.ndarray, conf: float = 0.9) -> None:
    """Write evidence counters so that grid.occupancy() == occ (flat int8)."""
    grid.hit_count[:] = 0
    grid.free_count[:] = 0
    grid.conf_sum[:] = 0
    grid.hit_count[occ == 1] = 1
    grid.conf_sum[occ == 1] = conf
    grid.log_residual[:] = 0
    grid.log_residual[occ == 1] = np.log1p(-min(conf, grid.max_confidence))
    grid.free_count[occ == 0] = 1


@pytest.fixture
def pocket_grid() -> FusedGrid:
    """1 m cube at 5 cm: a closed box of occupied voxels (walls one voxel thick) around an
    unobserved interior, open on its +x face; everything else known free."""
    spec = GridSpec.from_bounds(np.zeros(3), np.ones(3), 0.05)
    grid = FusedGrid(spec, np.zeros(3), np.ones(3), gamma=0.01)
    occ = np.zeros(spec.shape, np.int8)
    lo, hi = 7, 13  # box voxels 7..12 on each axis
    occ[lo:hi, lo:hi, lo:hi] = 1
    occ[lo + 1 : hi - 1, lo + 1 : hi - 1, lo + 1 : hi - 1] = -1  # interior, never observed
    occ[hi - 1, lo + 1 : hi - 1, lo + 1 : hi - 1] = -1  # the opening on +x
    set_occupancy(grid, occ.ravel())
    return grid


@pytest.fixture
def pocket_interior() -> np.ndarray:
    spec = GridSpec.from_bounds(np.zeros(3), np.ones(3), 0.05)
    m = np.zeros(spec.shape, bool)
    m[8:12, 8:12, 8:12] = True
    return m.ravel()
