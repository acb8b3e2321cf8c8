"""Exact, listing-independent operations on triangle-mesh arrays (numpy).

Open3D's multi-threaded mesh extraction lists the same surface in a different order from run to
run, so everything the metrics compute from a mesh first puts it in an order of its own
(`render.canonical_mesh`, `metrics.sample_surface`). These are the sorts they share, and the crop
of a reconstruction to its region of interest, each in a few vectorised passes: a room's mesh has
hundreds of thousands of triangles and is evaluated after every few views.
"""

from __future__ import annotations

import numpy as np

__all__ = ["crop_arrays", "position_classes", "row_order", "smallest_first"]


def row_order(rows: np.ndarray, size: int | None = None) -> np.ndarray:
    """Stable order of the rows (N, 3) sorted lexicographically (first column first); with
    `size`, the rows are integers in [0, size) and are sorted as one packed key when it fits."""
    if size is not None and size**3 < 2**62:
        rows = np.asarray(rows, dtype=np.int64)
        return np.argsort((rows[:, 0] * size + rows[:, 1]) * size + rows[:, 2], kind="stable")
    return np.lexsort(np.asarray(rows).T[::-1])


def smallest_first(rows: np.ndarray) -> np.ndarray:
    """(N, 3) column indices that rotate each row to start at its smallest entry (the first of
    equal smallest ones), keeping its cyclic order: rows[np.arange(N)[:, None], result]."""
    start = np.argmin(rows, axis=1)
    return (start[:, None] + np.arange(3)) % 3


def _runs(sorted_rows: np.ndarray) -> np.ndarray:
    """(N,) bool: the sorted row starts a run of equal rows (compared exactly, -0.0 == 0.0)."""
    starts = np.ones(len(sorted_rows), dtype=bool)
    starts[1:] = np.any(sorted_rows[1:] != sorted_rows[:-1], axis=1)
    return starts


def position_classes(vertices: np.ndarray) -> np.ndarray:
    """(V,) int64: for each vertex the rank of its position among the distinct positions, in
    lexicographic order (x, then y, then z). Equal positions share a class, so comparing classes
    compares positions (a position with a NaN coordinate equals no other)."""
    vertices = np.asarray(vertices, dtype=np.float64)
    order = np.lexsort(vertices.T[::-1])
    classes = np.empty(len(order), dtype=np.int64)
    classes[order] = np.cumsum(_runs(vertices[order])) - 1
    return classes


def _first_of_equal(rows: np.ndarray, order: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(first, number) for rows and their stable sorted `order`: the index of the first of each
    set of equal rows, ascending, and for every row the position in `first` of its set's."""
    starts = _runs(rows[order])
    is_first = np.zeros(len(order), dtype=bool)
    is_first[order[starts]] = True  # a stable sort puts each set's first row first
    number = np.cumsum(is_first) - 1
    of_row = np.empty(len(order), dtype=np.int64)
    of_row[order] = number[order[starts][np.cumsum(starts) - 1]]
    return np.flatnonzero(is_first), of_row


def crop_arrays(
    vertices: np.ndarray,
    triangles: np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
    vertex_attributes: tuple[np.ndarray | None, ...] = (),
    triangle_attributes: tuple[np.ndarray | None, ...] = (),
) -> tuple[np.ndarray, np.ndarray, list, list]:
    """The part of a mesh inside the box [lo, hi] (bounds included), as Open3D's
    `TriangleMesh.crop(AxisAlignedBoundingBox)` gives it, array for array and in the same order:
    the vertices inside; the triangles with all three corners inside; then vertices at the same
    position merged into the first, triangles with the same corners in the same cyclic order
    reduced to the first, vertices no triangle uses dropped, triangles with a repeated corner
    dropped. Vertex attributes (colours, normals) follow their vertices, triangle attributes their
    triangles; an empty result has none (as Open3D's).

    Returns (vertices (V', 3), triangles (F', 3) int64, vertex attributes, triangle attributes).
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    triangles = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    v_attrs = [None if a is None else np.asarray(a) for a in vertex_attributes]
    t_attrs = [None if a is None else np.asarray(a) for a in triangle_attributes]

    def take_vertices(index: np.ndarray) -> None:
        nonlocal vertices
        vertices = vertices[index]
        v_attrs[:] = [None if a is None else a[index] for a in v_attrs]

    def take_triangles(index: np.ndarray) -> None:
        nonlocal triangles
        triangles = triangles[index]
        t_attrs[:] = [None if a is None else a[index] for a in t_attrs]

    def keep_vertices(index: np.ndarray) -> None:
        """Keep the vertices `index` (ascending); corners of the others become -1."""
        nonlocal triangles
        new_index = np.full(len(vertices), -1, dtype=np.int64)
        new_index[index] = np.arange(len(index))
        triangles = new_index[triangles]
        take_vertices(index)

    keep_vertices(np.flatnonzero(np.all((vertices >= lo) & (vertices <= hi), axis=1)))
    take_triangles(np.flatnonzero(np.all(triangles >= 0, axis=1)))
    if len(vertices) > 0:
        first, merged = _first_of_equal(vertices, np.lexsort(vertices.T[::-1]))
        if len(first) < len(vertices):
            take_vertices(first)
            triangles = merged[triangles]
        cyclic = triangles[np.arange(len(triangles))[:, None], smallest_first(triangles)]
        first, _ = _first_of_equal(cyclic, row_order(cyclic, len(vertices)))
        take_triangles(first)
        used = np.zeros(len(vertices), dtype=bool)
        used[triangles.reshape(-1)] = True
        if not used.all():
            keep_vertices(np.flatnonzero(used))
        t0, t1, t2 = triangles.T
        take_triangles(np.flatnonzero((t0 != t1) & (t1 != t2) & (t0 != t2)))
    if len(vertices) == 0:
        v_attrs = [None] * len(v_attrs)
    if len(triangles) == 0:
        t_attrs = [None] * len(t_attrs)
    return vertices, triangles, v_attrs, t_attrs
