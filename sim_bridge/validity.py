"""Is a camera pose usable? Finite, a proper rotation, inside the workspace, clear of geometry.

The distance check uses a k-d tree of points sampled densely on every solid geom's surface (built
once per scene, lazily); points inside a solid are found with a per-geom filled voxel occupancy,
so a camera buried deep inside a wall or a cabinet is rejected too.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import mujoco
import numpy as np
import trimesh
from numba import njit
from scipy.spatial import cKDTree

from sim_bridge.geoms import geom_meshes, ground_planes, solid_geom_ids

CLEARANCE = 0.05  # metres, minimum distance from the camera centre to any surface
ROTATION_TOL = 1e-3  # max |R^T R - I| entry for a rotation to count as orthonormal
# Metres between surface samples of the distance check; the clearance test is off by at most
# about this much (object scenes are small, rooms are large).
SAMPLE_SPACING = {"object": 0.004, "room": 0.015}
# At most this many samples per geom: a wall beside an object scene is sampled more coarsely
# (1 cm on a 3 x 2.4 m wall) instead of taking millions of points.
MAX_SAMPLES_PER_GEOM = {"object": 300_000, "room": 2_000_000}
OCCUPANCY_PITCH = 0.01  # metres, voxel size of the inside-a-mesh test


class Scene(Protocol):
    """What the checks read of a scene (`sim_bridge.scenes.Scene`): its level, workspace box,
    compiled model and a cache the collider is kept in."""

    level: str
    workspace_min: np.ndarray
    workspace_max: np.ndarray
    _cache: dict

    def model(self) -> tuple[mujoco.MjModel, mujoco.MjData]: ...


# Why a pose is refused, in a word (the camera's status counts refusals by these).
INVALID_POSE, OUTSIDE_WORKSPACE, INSIDE_GEOMETRY, TOO_CLOSE = (
    "invalid_pose", "outside_workspace", "inside_geometry", "too_close"
)  # fmt: skip


@dataclass(frozen=True)
class PoseCheck:
    """ok, or why not: `reason` in words, `kind` one of the refusal kinds above ("" when ok)."""

    ok: bool
    reason: str
    kind: str = ""


class _Collider:
    """Distance-to-surface and inside-solid queries for one scene."""

    def __init__(self, scene: Scene) -> None:
        model, data = scene.model()
        spacing = SAMPLE_SPACING[scene.level]
        ids = solid_geom_ids(model)
        samples = []
        self.boxes, self.cylinders, self.ellipsoids, self.mesh_grids = [], [], [], []
        for g, mesh in zip(ids, geom_meshes(model, data, ids), strict=True):
            n = int(np.clip(2 * mesh.area / spacing**2, 50, MAX_SAMPLES_PER_GEOM[scene.level]))
            pts, _ = trimesh.sample.sample_surface(mesh, n, seed=int(g))
            samples.append(np.vstack([pts, mesh.vertices]))
            R, p, size = data.geom_xmat[g].reshape(3, 3), data.geom_xpos[g], model.geom_size[g]
            kind = model.geom_type[g]
            if kind == mujoco.mjtGeom.mjGEOM_BOX:
                self.boxes.append((R, p, size.copy()))
            elif kind == mujoco.mjtGeom.mjGEOM_CYLINDER:
                self.cylinders.append((R, p, size.copy()))
            elif kind in (mujoco.mjtGeom.mjGEOM_SPHERE, mujoco.mjtGeom.mjGEOM_ELLIPSOID):
                radii = np.full(3, size[0]) if kind == mujoco.mjtGeom.mjGEOM_SPHERE else size.copy()
                self.ellipsoids.append((R, p, radii))
            else:  # meshes and capsules: filled voxels of the world-frame surface
                self.mesh_grids.append(_filled_grid(mesh, OCCUPANCY_PITCH))
        # a room's millions of samples: an unbalanced tree builds 2-3x faster (2.2 against
        # 0.8 s in living_room) and answers the same nearest distances
        self.tree = cKDTree(np.vstack(samples), balanced_tree=False, compact_nodes=False)
        self.planes = ground_planes(model, data)

    def inside_solid(self, points: np.ndarray) -> np.ndarray:
        """(N,) bool: points (N, 3) inside any solid geom."""
        out = np.zeros(len(points), dtype=bool)
        for R, p, half in self.boxes:
            local = (points - p) @ R
            out |= np.all(np.abs(local) <= half, axis=1)
        for R, p, size in self.cylinders:
            local = (points - p) @ R
            out |= (local[:, 0] ** 2 + local[:, 1] ** 2 <= size[0] ** 2) & (
                np.abs(local[:, 2]) <= size[1]
            )
        for R, p, radii in self.ellipsoids:
            local = (points - p) @ R
            out |= ((local / radii) ** 2).sum(axis=1) <= 1.0
        for lo, grid in self.mesh_grids:
            ijk = np.floor((points - lo) / OCCUPANCY_PITCH).astype(np.int64)
            inside = np.all((ijk >= 0) & (ijk < grid.shape), axis=1)
            out[inside] |= grid[tuple(ijk[inside].T)]
        return out

    def clear(self, points: np.ndarray, clearance: float) -> np.ndarray:
        """(N,) bool: points (N, 3) at least `clearance` m from every surface, outside solids."""
        dist, _ = self.tree.query(points, k=1, distance_upper_bound=clearance)
        ok = ~np.isfinite(dist) & ~self.inside_solid(points)
        for origin, normal in self.planes:
            ok &= (points - origin) @ normal > clearance
        return ok


def _filled_grid(mesh: trimesh.Trimesh, pitch: float) -> tuple[np.ndarray, np.ndarray]:
    """(lower corner (3,), occupancy (nx, ny, nz) bool) of a closed, outward-facing mesh: the
    voxels (i, j, k), [lo + (i, j, k) pitch, lo + ((i, j, k) + 1) pitch), whose centre is
    inside it (inside one of its parts where parts overlap: a merged furniture mesh)."""
    lo = mesh.bounds[0] - pitch
    shape = np.ceil((mesh.bounds[1] + pitch - lo) / pitch).astype(np.int64) + 1
    triangles = np.ascontiguousarray(mesh.vertices[mesh.faces], dtype=np.float64)
    return lo, _winding_fill(triangles, lo, float(pitch), shape)


# Voxel centres are moved this much (in voxels, differently along x and y) before the upward ray
# test, so that no centre falls exactly on an edge of the axis-aligned triangles of a box.
_RAY_NUDGE = (0.7071e-6, 0.3183e-6)


@njit(cache=True)
def _winding_fill(triangles, lo, pitch, shape):
    """(nx, ny, nz) bool: the voxels whose centre is inside the closed, outward-facing surface
    made of triangles (T, 3, 3), by the winding number of the ray going up from each centre:
    a triangle crossed by the vertical line through a column of centres adds +1 (its normal
    points up: the ray leaves a solid) or -1 (enters one) to every centre below the crossing.
    Inside: a winding number above 0 (overlapping parts count once)."""
    nx, ny, nz = shape[0], shape[1], shape[2]
    winding = np.zeros((nx, ny, nz + 1), np.int16)
    for t in range(triangles.shape[0]):
        a, b, c = triangles[t, 0], triangles[t, 1], triangles[t, 2]
        area = (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])  # 2x, signed
        if area == 0.0:
            continue  # vertical: no vertical line crosses it
        sign = 1 if area > 0.0 else -1
        x_lo, x_hi = min(a[0], b[0], c[0]), max(a[0], b[0], c[0])
        y_lo, y_hi = min(a[1], b[1], c[1]), max(a[1], b[1], c[1])
        i0 = max(0, int(np.floor((x_lo - lo[0]) / pitch - 0.5)))
        i1 = min(nx - 1, int(np.ceil((x_hi - lo[0]) / pitch - 0.5)))
        j0 = max(0, int(np.floor((y_lo - lo[1]) / pitch - 0.5)))
        j1 = min(ny - 1, int(np.ceil((y_hi - lo[1]) / pitch - 0.5)))
        for i in range(i0, i1 + 1):
            x = lo[0] + (i + 0.5 + _RAY_NUDGE[0]) * pitch
            for j in range(j0, j1 + 1):
                y = lo[1] + (j + 0.5 + _RAY_NUDGE[1]) * pitch
                # barycentric weights (times area) of (x, y) in the triangle's projection
                wa = (b[0] - x) * (c[1] - y) - (b[1] - y) * (c[0] - x)
                wb = (c[0] - x) * (a[1] - y) - (c[1] - y) * (a[0] - x)
                wc = (a[0] - x) * (b[1] - y) - (a[1] - y) * (b[0] - x)
                if area > 0.0 and (wa < 0.0 or wb < 0.0 or wc < 0.0):
                    continue
                if area < 0.0 and (wa > 0.0 or wb > 0.0 or wc > 0.0):
                    continue
                z = (wa * a[2] + wb * b[2] + wc * c[2]) / area
                # centres below z: k + 0.5 < (z - lo) / pitch
                k = int(np.ceil((z - lo[2]) / pitch - 0.5))
                k = min(max(k, 0), nz)
                winding[i, j, 0] += sign
                winding[i, j, k] -= sign
    out = np.empty((nx, ny, nz), np.bool_)
    for i in range(nx):
        for j in range(ny):
            w = 0
            for k in range(nz):
                w += winding[i, j, k]
                out[i, j, k] = w > 0
    return out


def _collider(scene: Scene) -> _Collider:
    if "collider" not in scene._cache:
        scene._cache["collider"] = _Collider(scene)
    return scene._cache["collider"]


def valid_positions(scene: Scene, points: np.ndarray, clearance: float = CLEARANCE) -> np.ndarray:
    """(N,) bool: camera centres `points` (N, 3) world metres inside the workspace and at least
    `clearance` metres from every surface (and not inside any solid or below a ground plane)."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    ok = np.all(np.isfinite(points), axis=1)
    ok &= np.all((points >= scene.workspace_min) & (points <= scene.workspace_max), axis=1)
    if ok.any():
        ok[ok] = _collider(scene).clear(points[ok], clearance)
    return ok


def check_pose(scene: Scene, T_world_cam: np.ndarray, clearance: float = CLEARANCE) -> PoseCheck:
    """Validate a (4, 4) optical-frame pose in `world`; `reason` says what is wrong when not ok."""
    T = np.asarray(T_world_cam, dtype=np.float64)
    if T.shape != (4, 4):
        return PoseCheck(False, f"pose shape {T.shape}, expected (4, 4)", INVALID_POSE)
    if not np.all(np.isfinite(T)):
        return PoseCheck(False, "pose has non-finite entries", INVALID_POSE)
    if not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0], atol=1e-9):
        return PoseCheck(False, f"last row {T[3].tolist()}, expected [0, 0, 0, 1]", INVALID_POSE)
    R = T[:3, :3]
    err = float(np.abs(R.T @ R - np.eye(3)).max())
    if err > ROTATION_TOL or np.linalg.det(R) < 0:
        return PoseCheck(
            False,
            f"rotation is not orthonormal with det +1 (|R^T R - I| = {err:.2e}, det = {np.linalg.det(R):.3f})",
            INVALID_POSE,
        )
    p = T[:3, 3]
    if np.any(p < scene.workspace_min) or np.any(p > scene.workspace_max):
        return PoseCheck(
            False,
            f"position {np.round(p, 3).tolist()} outside the workspace {np.round(scene.workspace_min, 3).tolist()}..{np.round(scene.workspace_max, 3).tolist()}",
            OUTSIDE_WORKSPACE,
        )
    collider = _collider(scene)
    if collider.inside_solid(p[None])[0]:
        return PoseCheck(
            False, f"position {np.round(p, 3).tolist()} is inside scene geometry", INSIDE_GEOMETRY
        )
    if not collider.clear(p[None], clearance)[0]:
        dist, _ = collider.tree.query(p)
        return PoseCheck(
            False,
            f"position {np.round(p, 3).tolist()} is {dist:.3f} m from scene geometry, closer than the clearance {clearance} m",
            TOO_CLOSE,
        )
    return PoseCheck(True, "ok")
