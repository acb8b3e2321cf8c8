"""Render a coloured triangle mesh at a camera pose by CPU ray casting (Open3D RaycastingScene)."""

from __future__ import annotations

from typing import Any

import numpy as np

from area3d_eval.mesh_order import row_order, smallest_first
from area3d_eval.open3d_loader import import_open3d
from area3d_msgs_py.backproject import pixel_rays
from area3d_msgs_py.errors import InputError

UNCOLOURED_GREY = 0.5  # colour of meshes without vertex colours, in [0, 1]


def mesh_arrays(mesh: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """(vertices (V, 3) float64, triangles (F, 3) int64, vertex colours (V, 3) float64 in [0, 1] or None)
    of an open3d.geometry.TriangleMesh or a trimesh.Trimesh."""
    if (
        hasattr(mesh, "triangles")
        and hasattr(mesh, "vertex_colors")
        and hasattr(mesh, "has_vertex_colors")
    ):
        vertices = np.asarray(mesh.vertices, dtype=np.float64)
        triangles = np.asarray(mesh.triangles, dtype=np.int64)
        colours = (
            np.asarray(mesh.vertex_colors, dtype=np.float64) if mesh.has_vertex_colors() else None
        )
        return vertices, triangles, colours
    if hasattr(mesh, "faces") and hasattr(mesh, "vertices"):
        vertices = np.asarray(mesh.vertices, dtype=np.float64)
        triangles = np.asarray(mesh.faces, dtype=np.int64)
        colours = None
        visual = getattr(mesh, "visual", None)
        if visual is not None and getattr(visual, "kind", None) in ("vertex", "face"):
            colours = np.asarray(visual.vertex_colors, dtype=np.float64)[:, :3] / 255.0
        return vertices, triangles, colours
    raise InputError(
        "mesh", type(mesh).__name__, "an open3d.geometry.TriangleMesh or a trimesh.Trimesh"
    )


def canonical_mesh(
    vertices: np.ndarray, triangles: np.ndarray, colours: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """The same mesh listed in one order whatever order it came in: vertices sorted by position
    (colours with them), each triangle starting at its smallest vertex index (orientation kept),
    triangles sorted. Open3D's multi-threaded mesh extraction lists the same surface in a different
    order from run to run, and a ray-casting tree built from another order can answer a query
    that lies as near two triangles (a shared edge) with the other one, the result differing in
    its last bits."""
    vertices = np.asarray(vertices, dtype=np.float64)
    triangles = np.asarray(triangles, dtype=np.int64)
    order = np.lexsort(vertices.T[::-1])
    rank = np.empty(len(order), dtype=np.int64)
    rank[order] = np.arange(len(order))
    tri = rank[triangles].reshape(-1, 3)
    tri = tri[np.arange(len(tri))[:, None], smallest_first(tri)]
    tri = tri[row_order(tri, max(len(order), 1))]
    return vertices[order], tri, None if colours is None else np.asarray(colours)[order]


def raycasting_scene(vertices: np.ndarray, triangles: np.ndarray) -> Any:
    """An open3d RaycastingScene of the triangles (pass them `canonical_mesh`'s order), its tree
    built on one thread: Embree's parallel build gives a different tree from run to run, and with
    it, rarely, another answer in the last bits (see `canonical_mesh`). Queries use every core."""
    o3d = import_open3d()
    scene = o3d.t.geometry.RaycastingScene(nthreads=1)
    scene.add_triangles(
        o3d.core.Tensor(np.asarray(vertices, dtype=np.float32)),
        o3d.core.Tensor(np.asarray(triangles, dtype=np.uint32)),
    )
    return scene


def camera_rays(K: np.ndarray, T_world_cam: np.ndarray, width: int, height: int) -> np.ndarray:
    """(H, W, 6) float32 rays [origin, direction] in `world`, one per pixel centre (u + 0.5, v + 0.5).

    Directions are R K^-1 [u, v, 1], not normalised: their optical z component is 1, so the hit
    parameter t of a ray is the depth along optical z.
    """
    cam = pixel_rays(K, height, width).astype(np.float64)
    directions = cam @ np.asarray(T_world_cam, dtype=np.float64)[:3, :3].T
    origins = np.broadcast_to(T_world_cam[:3, 3], directions.shape)
    return np.concatenate([origins, directions], axis=-1).astype(np.float32)


class MeshRenderer:
    """A mesh loaded once into a RaycastingScene, rendered at many poses."""

    def __init__(self, mesh: Any) -> None:
        self.vertices, self.triangles, colours = canonical_mesh(*mesh_arrays(mesh))
        if colours is None:
            colours = np.full_like(self.vertices, UNCOLOURED_GREY)
        self.colours = colours
        self.empty = len(self.triangles) == 0
        if not self.empty:
            self._scene = raycasting_scene(self.vertices, self.triangles)

    def distances(self, points: np.ndarray) -> np.ndarray:
        """(N,) float32 distance (metres) of each point (N, 3) to the nearest point of the mesh's
        triangles (inf for an empty mesh)."""
        points = np.asarray(points, dtype=np.float32).reshape(-1, 3)
        if self.empty:
            return np.full(len(points), np.inf, np.float32)
        o3d = import_open3d()
        return self._scene.compute_distance(o3d.core.Tensor(points)).numpy()

    def render(
        self, K: np.ndarray, T_world_cam: np.ndarray, width: int, height: int
    ) -> tuple[np.ndarray, np.ndarray]:
        """(rgb (H, W, 3) uint8, depth (H, W) float32 metres along optical z, NaN = no surface).
        Pixels without a surface are black."""
        o3d = import_open3d()
        K = np.asarray(K, dtype=np.float64)
        T_world_cam = np.asarray(T_world_cam, dtype=np.float64)
        if K.shape != (3, 3):
            raise InputError("K", K.shape, "(3, 3) intrinsics")
        if T_world_cam.shape != (4, 4):
            raise InputError("T_world_cam", T_world_cam.shape, "a (4, 4) pose")
        if self.empty:
            return np.zeros((height, width, 3), np.uint8), np.full(
                (height, width), np.nan, np.float32
            )
        rays = camera_rays(K, T_world_cam, width, height)
        hits = self._scene.cast_rays(o3d.core.Tensor(rays))
        t = hits["t_hit"].numpy()
        hit = np.isfinite(t)
        depth = np.where(hit, t, np.nan).astype(np.float32)
        prim = hits["primitive_ids"].numpy()[hit].astype(np.int64)
        uv = hits["primitive_uvs"].numpy()[hit].astype(np.float64)
        corners = self.colours[self.triangles[prim]]  # (N, 3 corners, 3 channels)
        # Open3D's barycentric (u, v) weight the triangle's 2nd and 3rd vertices.
        weights = np.stack([1.0 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]], axis=1)
        colour = np.einsum("nk,nkc->nc", weights, corners)
        rgb = np.zeros((height, width, 3), np.uint8)
        rgb[hit] = np.clip(np.rint(colour * 255.0), 0, 255).astype(np.uint8)
        return rgb, depth


def render_mesh(
    mesh: Any, K: np.ndarray, T_world_cam: np.ndarray, width: int, height: int
) -> tuple[np.ndarray, np.ndarray]:
    """Ray-cast `mesh` (open3d or trimesh, vertex colours in [0, 1]) from the optical frame T_world_cam.

    K (3, 3) with pixel centres at (u + 0.5, v + 0.5). Returns (rgb (H, W, 3) uint8 with black where
    nothing is hit, depth (H, W) float32 metres along optical z, NaN where nothing is hit).
    """
    return MeshRenderer(mesh).render(K, T_world_cam, width, height)
