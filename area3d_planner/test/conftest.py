import numpy as np
import pytest

from area3d_msgs_py.camera_pose import look_at
from area3d_msgs_py.grid import GridSpec
from area3d_planner.config import PlannerConfig
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


# A 64x48 camera with a 90 degree horizontal field of view.
WALL_K = np.array([[32.0, 0, 32], [0, 32.0, 24], [0, 0, 1]])
# five distinct directions onto a wall: straight on, 50 degrees left, right, above and below
WALL_DIRECTIONS = ((0.0, 0.0), (50.0, 0.0), (-50.0, 0.0), (0.0, 50.0), (0.0, -50.0))


def banded_wall_view(
    azimuth_deg: float,
    elevation_deg: float,
    wall_x: float = 0.625,
    bands_y: tuple = ((0.15, 0.3), (0.7, 0.85)),
    band_z: tuple = (0.3, 0.7),
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A view of the wall x = wall_x from (azimuth, elevation) about (wall_x, 0.5, 0.5), 0.525 m
    away, with `WALL_K`: its depth (H, W) float32, a confidence of 0.2 on the bands of the wall
    (world y in each of `bands_y`, z in `band_z`) and 0.9 elsewhere, wherever it is seen from,
    and the pose T_world_cam (4, 4)."""

    target = np.array([wall_x, 0.5, 0.5])
    a, e = np.radians(azimuth_deg), np.radians(elevation_deg)
    eye = target - 0.525 * np.array([np.cos(a) * np.cos(e), np.sin(a) * np.cos(e), np.sin(e)])
    T = look_at(eye, target)
    v, u = np.mgrid[0:48, 0:64]
    rays = np.stack([(u + 0.5 - 32) / 32, (v + 0.5 - 24) / 32, np.ones((48, 64))], -1)
    world = rays @ T[:3, :3].T
    t = (wall_x - eye[0]) / world[..., 0]  # distance along each ray to the plane, as optical z
    depth = np.where(t > 0, t, np.nan).astype(np.float32)
    y, z = eye[1] + t * world[..., 1], eye[2] + t * world[..., 2]
    bands = np.zeros(depth.shape, bool)
    for low, high in bands_y:
        bands |= (y > low) & (y < high)
    bands &= (z > band_z[0]) & (z < band_z[1])
    return depth, np.where(bands, 0.2, 0.9).astype(np.float32), T


def server_config(**kw) -> PlannerConfig:
    """A small room-level planner over a 1 m cube at 5 cm, the region of interest its far 70 %
    along x (`wall_frame` looks at it)."""
    base = dict(
        workspace_min=(0.0, 0.0, 0.0),
        workspace_max=(1.0, 1.0, 1.0),
        roi_min=(0.3, 0.0, 0.0),
        roi_max=(1.0, 1.0, 1.0),
        voxel_size=0.05,
        level="room",
        seed_spacing=0.2,
        yaw_bins=6,
        pitch_bins=2,
        face_res=32,
        budget=6,
    )
    base.update(kw)
    return PlannerConfig(**base)


def closed_loop_config() -> PlannerConfig:
    return server_config(budget=20, mode="closed_loop")


def wall_frame() -> tuple:
    """(depth, confidence, K, T): a 64x48 view along +x onto a wall 0.525 m away."""
    T = look_at(np.array([0.1, 0.5, 0.5]), np.array([1.0, 0.5, 0.5]))
    depth = np.full((48, 64), 0.525, np.float32)
    return depth, np.full_like(depth, 0.8), WALL_K, T


def wall_frames() -> list:
    """(stamp, depth, confidence, K, T) of three frames from different places, each seeing a wall
    at another depth (stamps 1, 2, 3)."""
    out = []
    for i, (y, d) in enumerate([(0.5, 0.525), (0.3, 0.6), (0.7, 0.45)]):
        T = look_at(np.array([0.1, y, 0.5]), np.array([1.0, y, 0.5]))
        depth = np.full((48, 64), d, np.float32)
        out.append((i + 1, depth, np.full_like(depth, 0.6 + 0.1 * i), WALL_K, T))
    return out
