"""Pose validity: what the simulated camera refuses, and the vectorised seed filter agrees."""

import numpy as np
import pytest

from area3d_msgs_py.camera_pose import look_at
from sim_bridge.scenes import load_scene
from sim_bridge.validity import check_pose, valid_positions

TABLE_TOP = 0.75


@pytest.fixture(scope="module")
def scene():
    return load_scene("clutter7_a")


def pose_at(p):
    return look_at(np.asarray(p, dtype=float), [0.0, 0.0, TABLE_TOP])


def test_initial_and_eval_views_are_valid(scene):
    for T in np.concatenate([scene.initial_views, scene.eval_views]):
        assert check_pose(scene, T).ok


def test_a_pose_inside_an_object_is_refused(scene):
    model, data = scene.model()
    centre = data.xpos[model.body("obj1").id]  # the settled blob, origin at its base centre
    T = pose_at(centre + [0, 0, 0.06])
    check = check_pose(scene, T)
    assert not check.ok and "geometry" in check.reason and check.kind == "inside_geometry"


def test_a_pose_inside_the_room_furniture_is_refused():
    room = load_scene("living_room")
    T = look_at([2.6, 1.4, 0.45], [0, 0, 0.5])  # centre of the cabinet in the alcove
    check = check_pose(room, T)
    assert not check.ok and "inside" in check.reason


def test_clearance_to_the_table_top_is_enforced(scene):
    corner = np.array([0.42, 0.27, TABLE_TOP])  # table corner, away from every object
    assert check_pose(scene, pose_at(corner + [0, 0, 0.06]), clearance=0.05).ok
    refused = check_pose(scene, pose_at(corner + [0, 0, 0.06]), clearance=0.08)
    assert not refused.ok and "clearance" in refused.reason and refused.kind == "too_close"
    assert check_pose(scene, pose_at(corner + [0, 0, 0.09]), clearance=0.08).ok


def test_outside_the_workspace_is_refused(scene):
    p = scene.workspace_max + [0.1, 0.0, 0.0]
    check = check_pose(scene, pose_at(p))
    assert not check.ok and "workspace" in check.reason and check.kind == "outside_workspace"


def test_non_orthonormal_and_mirrored_rotations_are_refused(scene):
    T = scene.initial_views[0].copy()
    T[:3, :3] *= 1.01
    assert "orthonormal" in check_pose(scene, T).reason
    T = scene.initial_views[0].copy()
    T[:3, 0] *= -1  # det = -1
    assert not check_pose(scene, T).ok


def test_non_finite_poses_are_refused(scene):
    T = scene.initial_views[0].copy()
    T[1, 3] = np.nan
    check = check_pose(scene, T)
    assert not check.ok and "finite" in check.reason and check.kind == "invalid_pose"
    assert not check_pose(scene, np.eye(3)).ok


def test_valid_positions_agrees_with_check_pose(scene):
    rng = np.random.default_rng(3)
    lo = scene.workspace_min - 0.1
    hi = scene.workspace_max + 0.1
    points = rng.uniform(lo, hi, (400, 3))
    points[:100] = rng.uniform(scene.roi_min, scene.roi_max, (100, 3))  # many near the objects
    ok = valid_positions(scene, points, clearance=0.05)
    expected = [check_pose(scene, pose_at(p), clearance=0.05).ok for p in points]
    assert ok.tolist() == expected
    assert 0 < ok.sum() < len(points)


def _inside_box(points, transform, extents):
    local = (points - transform[:3, 3]) @ transform[:3, :3]
    return np.all(np.abs(local) < np.asarray(extents) / 2, axis=1)


def test_the_inside_of_a_mesh_is_the_voxels_whose_centre_it_holds_overlapping_parts_once():
    """The mesh occupancy the pose check uses (`_filled_grid`): exactly the voxels whose centre
    lies inside a tilted box, and inside the union of two overlapping tilted boxes merged into
    one mesh (where counting the surfaces a ray crosses, odd = inside, would leave their
    overlap out); voxels outside the box around the mesh read as outside."""
    import trimesh

    from sim_bridge.validity import _filled_grid

    rng = np.random.default_rng(7)
    pitch = 0.01
    parts = []
    for _ in range(2):
        transform = trimesh.transformations.random_rotation_matrix(rng.random(3))
        transform[:3, 3] = rng.uniform(-0.03, 0.03, 3)
        parts.append((transform, rng.uniform(0.05, 0.12, 3)))
    for count in (1, 2):
        mesh = trimesh.util.concatenate(
            [trimesh.creation.box(extents=e, transform=T) for T, e in parts[:count]]
        )
        lo, grid = _filled_grid(mesh, pitch)
        ijk = np.stack(np.meshgrid(*[np.arange(n) for n in grid.shape], indexing="ij"), -1)
        centres = lo + (ijk.reshape(-1, 3) + 0.5) * pitch
        expected = np.zeros(len(centres), bool)
        for T, e in parts[:count]:
            expected |= _inside_box(centres, T, e)
        assert expected.sum() > 100  # the test means something
        np.testing.assert_array_equal(grid.reshape(-1), expected)
        # a grid's edge voxels are outside the mesh
        assert not grid[0].any() and not grid[-1].any() and not grid[:, :, -1].any()
