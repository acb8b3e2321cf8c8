"""World-frame triangle meshes of a MuJoCo model's geoms (the ground truth and the pose checker use them)."""

from __future__ import annotations

import mujoco
import numpy as np
import trimesh
from trimesh.intersections import slice_faces_plane

# Tessellation of primitive geoms; fine enough that their facets stay within ~1 mm of the true
# surface at the sizes used in the bundled scenes.
PRIMITIVE_SECTIONS = 48


def _local_mesh(model: mujoco.MjModel, geom_id: int) -> trimesh.Trimesh | None:
    kind = model.geom_type[geom_id]
    size = model.geom_size[geom_id]
    if kind == mujoco.mjtGeom.mjGEOM_MESH:
        mesh_id = model.geom_dataid[geom_id]
        v0, nv = model.mesh_vertadr[mesh_id], model.mesh_vertnum[mesh_id]
        f0, nf = model.mesh_faceadr[mesh_id], model.mesh_facenum[mesh_id]
        vertices = model.mesh_vert[v0 : v0 + nv].astype(np.float64)
        faces = model.mesh_face[f0 : f0 + nf].astype(np.int64)
        return trimesh.Trimesh(vertices, faces, process=False)
    if kind == mujoco.mjtGeom.mjGEOM_BOX:
        return trimesh.creation.box(extents=2 * size)
    if kind == mujoco.mjtGeom.mjGEOM_SPHERE:
        return trimesh.creation.icosphere(subdivisions=3, radius=size[0])
    if kind == mujoco.mjtGeom.mjGEOM_ELLIPSOID:
        sphere = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
        sphere.vertices *= size[:3]
        return sphere
    if kind == mujoco.mjtGeom.mjGEOM_CYLINDER:
        return trimesh.creation.cylinder(
            radius=size[0], height=2 * size[1], sections=PRIMITIVE_SECTIONS
        )
    if kind == mujoco.mjtGeom.mjGEOM_CAPSULE:
        return trimesh.creation.capsule(
            radius=size[0], height=2 * size[1], count=[PRIMITIVE_SECTIONS, PRIMITIVE_SECTIONS // 2]
        )
    return None  # planes (infinite) and height fields are not part of the reconstructable surface


def solid_geom_ids(model: mujoco.MjModel) -> np.ndarray:
    """(G,) ids of geoms with a closed surface (everything but planes, height fields, invisible geoms)."""
    keep = (
        (model.geom_type != mujoco.mjtGeom.mjGEOM_PLANE)
        & (model.geom_type != mujoco.mjtGeom.mjGEOM_HFIELD)
        & (model.geom_rgba[:, 3] > 0)
    )
    return np.flatnonzero(keep)


def geom_meshes(model: mujoco.MjModel, data: mujoco.MjData, geom_ids=None) -> list[trimesh.Trimesh]:
    """World-frame trimesh of each geom in `geom_ids` (default: all solid geoms); `data` after mj_forward."""
    out = []
    for g in solid_geom_ids(model) if geom_ids is None else geom_ids:
        mesh = _local_mesh(model, int(g))
        if mesh is None:
            continue
        R = data.geom_xmat[g].reshape(3, 3)
        mesh = trimesh.Trimesh(mesh.vertices @ R.T + data.geom_xpos[g], mesh.faces, process=False)
        out.append(mesh)
    return out


def ground_planes(
    model: mujoco.MjModel, data: mujoco.MjData
) -> list[tuple[np.ndarray, np.ndarray]]:
    """(point (3,), unit normal (3,)) of each plane geom in world; the free side is along the normal."""
    planes = []
    for g in np.flatnonzero(model.geom_type == mujoco.mjtGeom.mjGEOM_PLANE):
        R = data.geom_xmat[g].reshape(3, 3)
        planes.append((data.geom_xpos[g].copy(), R[:, 2].copy()))
    return planes


def clip_to_box(mesh: trimesh.Trimesh, lo: np.ndarray, hi: np.ndarray) -> trimesh.Trimesh:
    """The part of `mesh`'s surface inside the axis-aligned box [lo, hi] (triangles cut at its faces)."""
    vertices, faces = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    for axis in range(3):
        for origin, sign in ((lo, 1.0), (hi, -1.0)):
            if len(faces) == 0:
                break
            normal = np.zeros(3)
            normal[axis] = sign
            vertices, faces = slice_faces_plane(
                vertices,
                faces,
                plane_normal=normal,
                plane_origin=np.asarray(origin, dtype=np.float64),
            )[:2]
    return trimesh.Trimesh(vertices, faces, process=False)
