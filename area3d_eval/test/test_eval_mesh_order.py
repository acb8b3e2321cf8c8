"""The vectorised mesh operations against their definitions: the crop against Open3D's own crop,
the surface sample and the canonical order against the sorts of corner coordinates they stand
for, array for array and bit for bit, on meshes full of the cases that make them differ (repeated
positions, -0.0, repeated and degenerate triangles, vertices on the box's faces)."""

import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st

from area3d_eval.mesh_order import crop_arrays, position_classes, row_order
from area3d_eval.metrics import sample_surface
from area3d_eval.open3d_loader import import_open3d
from area3d_eval.reconstruct import crop_mesh
from area3d_eval.render import canonical_mesh
from area3d_msgs_py.errors import InputError

o3d = import_open3d()


def _open3d_mesh(vertices, triangles, colours=None, normals=None, triangle_normals=None):
    mesh = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(vertices), o3d.utility.Vector3iVector(triangles)
    )
    if colours is not None:
        mesh.vertex_colors = o3d.utility.Vector3dVector(colours)
    if normals is not None:
        mesh.vertex_normals = o3d.utility.Vector3dVector(normals)
    if triangle_normals is not None:
        mesh.triangle_normals = o3d.utility.Vector3dVector(triangle_normals)
    return mesh


def _arrays(mesh):
    return (
        np.asarray(mesh.vertices),
        np.asarray(mesh.triangles),
        np.asarray(mesh.vertex_colors) if mesh.has_vertex_colors() else None,
        np.asarray(mesh.vertex_normals) if mesh.has_vertex_normals() else None,
        np.asarray(mesh.triangle_normals) if mesh.has_triangle_normals() else None,
    )


def _assert_same(mine, theirs):
    for a, b in zip(mine, theirs, strict=True):
        assert (a is None) == (b is None)
        if a is not None:
            assert a.shape == b.shape and np.array_equal(a, b)


@st.composite
def grid_meshes(draw):
    """Vertices on a coarse grid (many repeated positions, signed zeros, some on the crop box's
    faces), triangles drawn at random (repeats, reversed copies, degenerate ones)."""
    n = draw(st.integers(1, 30))
    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    vertices = rng.integers(0, 4, (n, 3)) / 4.0
    vertices = np.where(rng.random((n, 3)) < 0.1, -vertices, vertices)  # -0.0, and some outside
    triangles = rng.integers(0, n, (draw(st.integers(0, 60)), 3))
    if len(triangles) and draw(st.booleans()):  # a repeat, rotated or reversed
        t = triangles[rng.integers(len(triangles))]
        triangles = np.vstack([triangles, np.roll(t, 1), t[::-1]])
    return vertices, triangles.astype(np.int32), rng


@settings(max_examples=300, deadline=None)
@given(grid_meshes())
def test_the_crop_is_open3ds_array_for_array(mesh):
    vertices, triangles, rng = mesh
    colours, normals = rng.random((len(vertices), 3)), rng.random((len(vertices), 3))
    triangle_normals = rng.random((len(triangles), 3)) if len(triangles) else None
    lo, hi = np.array([0.0, 0.0, 0.25]), np.array([0.75, 0.75, 1.0])
    theirs = _open3d_mesh(vertices, triangles, colours, normals, triangle_normals).crop(
        o3d.geometry.AxisAlignedBoundingBox(lo, hi)
    )
    v, t, (c, n), (tn,) = crop_arrays(
        vertices, triangles, lo, hi, (colours, normals), (triangle_normals,)
    )
    _assert_same((v, t, c, n, tn), _arrays(theirs))
    mine = crop_mesh(_open3d_mesh(vertices, triangles, colours, normals, triangle_normals), lo, hi)
    _assert_same(_arrays(mine), _arrays(theirs))


def test_the_crop_of_a_noisy_sphere_is_open3ds():
    sphere = trimesh.creation.icosphere(subdivisions=5, radius=0.1)
    rng = np.random.default_rng(0)
    vertices = sphere.vertices + rng.normal(0.0, 0.002, sphere.vertices.shape)
    mesh = _open3d_mesh(vertices, sphere.faces.astype(np.int32), rng.random(vertices.shape))
    mesh.compute_vertex_normals()
    lo, hi = np.array([-0.05, -0.2, -0.2]), np.array([0.2, 0.06, 0.2])
    theirs = mesh.crop(o3d.geometry.AxisAlignedBoundingBox(lo, hi))
    mine = crop_mesh(mesh, lo, hi)
    assert 0 < len(mine.triangles) < len(mesh.triangles)
    _assert_same(_arrays(mine), _arrays(theirs))


def _sample_by_coordinates(vertices, triangles, num_points, seed):
    """The definition sample_surface implements: every triangle starts at its lexicographically
    smallest corner (the first of equal ones), the triangles are sorted by their nine corner
    coordinates, then sampled by area."""
    corners = vertices[triangles]
    flat = corners.reshape(-1, 3)
    rank = np.empty(len(flat), dtype=np.int64)
    rank[np.lexsort(flat.T[::-1])] = np.arange(len(flat))
    start = np.argmin(rank.reshape(-1, 3), axis=1)
    corners = corners[np.arange(len(corners))[:, None], (start[:, None] + np.arange(3)) % 3]
    corners = corners[np.lexsort(corners.reshape(-1, 9).T[::-1])]
    a, b, c = corners[:, 0], corners[:, 1], corners[:, 2]
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    if not area.sum() > 0:
        return np.zeros((0, 3))
    rng = np.random.default_rng(seed)
    face = rng.choice(len(corners), size=num_points, p=area / area.sum())
    r1, r2 = rng.random(num_points), rng.random(num_points)
    flip = r1 + r2 > 1.0
    r1, r2 = np.where(flip, 1.0 - r1, r1), np.where(flip, 1.0 - r2, r2)
    return a[face] + r1[:, None] * (b[face] - a[face]) + r2[:, None] * (c[face] - a[face])


@settings(max_examples=300, deadline=None)
@given(grid_meshes(), st.integers(1, 400))
def test_the_surface_sample_is_its_definition_bit_for_bit(mesh, num_points):
    vertices, triangles, _ = mesh
    if len(triangles) == 0:
        return
    mine = sample_surface(vertices, triangles, num_points, seed=5)
    theirs = _sample_by_coordinates(vertices, triangles.astype(np.int64), num_points, 5)
    assert mine.shape == theirs.shape and np.array_equal(mine, theirs)


@settings(max_examples=200, deadline=None)
@given(grid_meshes())
def test_the_canonical_order_sorts_triangles_by_their_ranked_corners(mesh):
    vertices, triangles, _ = mesh
    v, t, _ = canonical_mesh(vertices, triangles)
    assert np.array_equal(v, vertices[np.lexsort(vertices.T[::-1])])
    assert np.all(t[:, 0] <= t[:, 1]) and np.all(t[:, 0] <= t[:, 2])
    assert np.array_equal(t, t[np.lexsort(t.T[::-1])])  # sorted, as triples
    # the same triangles, each rotated (orientation kept): as sets of cyclic triples
    expect = {
        tuple(np.roll(r, -int(np.argmin(r))))
        for r in np.argsort(np.lexsort(vertices.T[::-1]))[triangles]
    }
    assert {tuple(r) for r in t} == expect


def test_rows_sort_alike_packed_or_not_and_equal_positions_share_a_class():
    rng = np.random.default_rng(2)
    rows = rng.integers(0, 7, (500, 3))
    assert np.array_equal(row_order(rows, 7), np.lexsort(rows.T[::-1]))
    assert np.array_equal(row_order(rows * 2**21, 7 * 2**21), np.lexsort(rows.T[::-1]))  # unpacked
    points = np.array([[0.0, 1.0, 2.0], [-0.0, 1.0, 2.0], [0.0, 0.5, 9.0], [0.0, 1.0, 2.0]])
    assert position_classes(points).tolist() == [1, 1, 0, 1]


def test_a_surface_with_a_non_finite_corner_is_refused_and_an_unused_vertex_ignored():
    vertices = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [np.nan, 0.0, 0.0]])
    with pytest.raises(InputError, match="vertices.*nan.*finite corners"):
        sample_surface(vertices, np.array([[0, 1, 3]]), 10)
    points = sample_surface(vertices, np.array([[0, 1, 2]]), 10)
    assert points.shape == (10, 3) and np.all(points[:, 2] == 0.0)
