"""Scenes load with consistent metadata; rendered depth lands on the ground-truth mesh."""

import json
import re

import numpy as np
import pytest
import trimesh

from area3d_eval.open3d_loader import import_open3d
from area3d_msgs_py.backproject import backproject
from sim_bridge.render import RgbdRenderer
from sim_bridge.scenes import list_scenes, load_scene
from sim_bridge.validity import check_pose

OBJECT_SCENES = ["single_object", "five_objects", "clutter7_a", "clutter7_b", "scanned_objects"]
ROOM_SCENES = ["living_room", "office"]


def distance_to(mesh, points):
    o3d = import_open3d()
    rs = o3d.t.geometry.RaycastingScene()
    rs.add_triangles(mesh.vertices.astype(np.float32), mesh.faces.astype(np.uint32))
    return rs.compute_distance(points.astype(np.float32)).numpy()


def test_all_bundled_scenes_are_listed():
    assert set(OBJECT_SCENES + ROOM_SCENES) <= set(list_scenes())


@pytest.mark.parametrize("name", OBJECT_SCENES + ROOM_SCENES)
def test_bundled_scene_metadata_is_consistent(name):
    scene = load_scene(name)
    level = "object" if name in OBJECT_SCENES else "room"
    assert scene.name == name and scene.level == level
    assert scene.mjcf_path.is_file()
    assert scene.initial_views.shape == ((4, 4, 4) if level == "object" else (15, 4, 4))
    assert scene.eval_views.shape[1:] == (4, 4) and 12 <= len(scene.eval_views) <= 24
    assert (scene.gamma, scene.tau) == ((0.01, 0.01) if level == "object" else (0.005, 0.05))
    assert np.all(scene.workspace_min < scene.workspace_max) and np.all(
        scene.roi_min < scene.roi_max
    )
    for T in np.concatenate([scene.initial_views, scene.eval_views]):
        assert check_pose(scene, T).ok, check_pose(scene, T).reason
        # every view looks towards the ROI: its optical axis passes near the ROI box
        assert T[:3, 2] @ ((scene.roi_min + scene.roi_max) / 2 - T[:3, 3]) > 0
    gt = scene.ground_truth_mesh()
    assert len(gt.faces) > 100
    assert np.all(gt.vertices >= scene.roi_min - 1e-6) and np.all(
        gt.vertices <= scene.roi_max + 1e-6
    )


@pytest.mark.parametrize("name", OBJECT_SCENES)
def test_held_out_depth_back_projects_onto_the_ground_truth_mesh(name):
    scene = load_scene(name)
    gt = scene.ground_truth_mesh()
    rng = np.random.default_rng(0)
    points = []
    with RgbdRenderer(scene) as renderer:
        for T in scene.eval_views:
            _, depth = renderer.render(T)
            p, _ = backproject(depth, renderer.K, T)
            inside = np.all((p > scene.roi_min + 0.005) & (p < scene.roi_max - 0.005), axis=1)
            points.append(p[inside][rng.choice(inside.sum(), 2000, replace=False)])
    d = distance_to(gt, np.vstack(points))
    assert np.percentile(d, 95) < 0.003
    assert np.median(d) < 0.001


def seen_fraction(scene, views, samples):
    """Fraction of surface `samples` (N, 3) that some view's depth image shows (depth-test)."""
    seen = np.zeros(len(samples), dtype=bool)
    with RgbdRenderer(scene) as renderer:
        K = renderer.K
        for T in views:
            _, depth = renderer.render(T)
            cam = (samples - T[:3, 3]) @ T[:3, :3]
            z = cam[:, 2]
            front = z > 0.01
            u = np.floor(K[0, 0] * cam[front, 0] / z[front] + K[0, 2]).astype(int)
            v = np.floor(K[1, 1] * cam[front, 1] / z[front] + K[1, 2]).astype(int)
            on = (u >= 0) & (u < 640) & (v >= 0) & (v < 480)
            idx = np.flatnonzero(front)[on]
            seen[idx] |= np.abs(depth[v[on], u[on]] - z[idx]) < 0.01 + 0.01 * z[idx]
    return seen.mean()


@pytest.mark.parametrize("name", ["five_objects", "clutter7_a", "office"])
def test_initial_views_leave_the_back_side_for_the_agent_to_find(name):
    scene = load_scene(name)
    samples, _ = trimesh.sample.sample_surface(scene.ground_truth_mesh(), 30000, seed=0)
    if scene.level == "object":  # the objects' surfaces, not the table top around them
        samples = samples[samples[:, 2] > scene.roi_min[2] + 0.025]
    initial = seen_fraction(scene, scene.initial_views, samples)
    held_out = seen_fraction(scene, scene.eval_views, samples)
    assert initial < 0.8
    assert held_out > initial + 0.15


USER_MJCF = """
<mujoco model="user">
  <worldbody>
    <light pos="0 0 3"/>
    <geom name="ground" type="plane" size="0 0 0.1"/>
    <geom name="crate" type="box" pos="0.2 0.1 0.15" size="0.15 0.1 0.15" rgba="0.8 0.3 0.2 1"/>
    <geom name="ball" type="sphere" pos="-0.2 0 0.1" size="0.1" rgba="0.2 0.5 0.8 1"/>
  </worldbody>
</mujoco>
"""


def test_a_user_mjcf_gets_derived_bounds_and_views(tmp_path):
    path = tmp_path / "user_scene.xml"
    path.write_text(USER_MJCF)
    scene = load_scene(str(path))
    assert scene.level == "object" and scene.name == "user_scene"
    # no table: the ground plane is the support; ROI = bounding box of the two solid geoms, 2 cm
    # below the support and above the tallest
    assert np.allclose(scene.roi_min, [-0.3, -0.1, -0.02], atol=2e-3)
    assert np.allclose(scene.roi_max, [0.35, 0.2, 0.32], atol=2e-3)
    assert np.all(scene.workspace_min[:2] < scene.roi_min[:2]) and np.all(
        scene.workspace_max > scene.roi_max
    )
    assert scene.workspace_min[2] == pytest.approx(0.1)  # kept above the ground plane
    assert scene.initial_views.shape == (4, 4, 4) and len(scene.eval_views) >= 12
    for T in scene.initial_views:
        assert check_pose(scene, T).ok
    with RgbdRenderer(scene, width=160, height=120) as renderer:
        _, depth = renderer.render(scene.initial_views[0])
    assert np.isfinite(depth[60, 80])


def test_unknown_scene_name_is_rejected_naming_the_choices():
    with pytest.raises(ValueError, match="scene: got 'no_such_scene'.*single_object"):
        load_scene("no_such_scene")


def test_a_file_mujoco_cannot_load_is_refused_on_one_line_naming_it(tmp_path):
    path = tmp_path / "mesh.xml"
    path.write_text("ply\nformat ascii 1.0\nend_header\n")  # not MJCF
    with pytest.raises(ValueError, match="MuJoCo could not load it") as info:
        load_scene(str(path))
    assert str(path) in str(info.value) and "\n" not in str(info.value)


def test_a_sidecar_gives_the_fields_it_has_and_the_rest_is_derived(tmp_path):
    """A sidecar with the region only (KeyError 'workspace_min' before): that region, the rest
    as derived; a sidecar that is no JSON, or a field of the wrong shape, refused naming it."""
    path = tmp_path / "user_scene.xml"
    path.write_text(USER_MJCF)
    derived = load_scene(str(path))
    sidecar = tmp_path / "user_scene.json"
    sidecar.write_text(json.dumps({"roi_min": [-0.2, -0.1, 0.0], "roi_max": [0.2, 0.1, 0.3]}))
    scene = load_scene(str(path))
    assert scene.roi_min.tolist() == [-0.2, -0.1, 0.0] and scene.roi_max.tolist() == [0.2, 0.1, 0.3]
    np.testing.assert_array_equal(scene.workspace_min, derived.workspace_min)
    np.testing.assert_array_equal(scene.initial_views, derived.initial_views)
    for text, why in (
        ('{"roi_min": [0, 0,}', "not JSON"),
        ('{"roi_min": [0, 0]}', "roi_min: got shape (2,), expected (3,)"),
        ('{"initial_views": [[1, 2]]}', "initial_views"),
        ('{"level": "house"}', "level: got 'house'"),
    ):
        sidecar.write_text(text)
        with pytest.raises(ValueError, match=re.escape(why)) as info:
            load_scene(str(path))
        assert str(sidecar) in str(info.value)


@pytest.mark.parametrize(
    ("scale", "why"), [(0.002, "expected objects of centimetres"), (400.0, "at most 50 m")]
)
def test_a_scene_in_other_units_than_metres_is_refused(tmp_path, scale, why):
    """The user scene at 1/500 (millimetres read as metres: it ran, reconstructing nothing, with
    a PSNR of 100 dB) and at 400 times (centimetres read as metres: a 'room' of 100 m)."""
    scaled = re.sub(
        r'(size|pos)="([^"]+)"',
        lambda m: f'{m.group(1)}="{" ".join(str(float(v) * scale) for v in m.group(2).split())}"',
        USER_MJCF,
    )
    path = tmp_path / "scaled.xml"
    path.write_text(scaled)
    with pytest.raises(ValueError, match=why) as info:
        load_scene(str(path))
    assert str(path) in str(info.value)
