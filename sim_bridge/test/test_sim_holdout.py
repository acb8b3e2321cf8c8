"""Generated hold-out scenes and metadata derived from geometry alone (no sidecar JSON)."""

import shutil

import numpy as np
import pytest

from area3d_msgs_py.backproject import backproject
from sim_bridge.holdout_scenes import write_holdout_scene
from sim_bridge.render import RgbdRenderer
from sim_bridge.scene_layout import scene_layout
from sim_bridge.scenes import SCENES_DIR, load_scene
from sim_bridge.validity import check_pose

NEW_KINDS = [(kind, seed) for kind in ("shelf_wall", "thin_objects") for seed in (0, 1, 2)]
HOLDOUT = [("tabletop", 0), ("tabletop", 3), ("alcove_room", 0), ("alcove_room", 1), *NEW_KINDS]
HOLDOUT += [("scanned_counter", 0), ("scanned_counter", 1)]
LEVEL = {"tabletop": "object", "alcove_room": "room", "shelf_wall": "object"}
LEVEL |= {"thin_objects": "object", "scanned_counter": "object"}


@pytest.fixture(scope="module")
def holdout(tmp_path_factory):
    root = tmp_path_factory.mktemp("holdout")
    return {
        (kind, seed): load_scene(write_holdout_scene(kind, root / f"{kind}_{seed}", seed))
        for kind, seed in HOLDOUT
    }


def geom_box(scene, name):
    """(lo, hi) world bounding box of a named geom of the scene."""
    from sim_bridge.geoms import geom_meshes

    model, data = scene.model()
    return geom_meshes(model, data, [model.geom(name).id])[0].bounds


def assert_views_valid_and_distinct(scene):
    views = np.concatenate([scene.initial_views, scene.eval_views])
    for T in views:
        check = check_pose(scene, T)
        assert check.ok, check.reason
    gap = np.linalg.norm(
        scene.eval_views[:, None, :3, 3] - scene.initial_views[None, :, :3, 3], axis=2
    )
    assert gap.min() > 0.05  # no held-out view sits on an initial one


def roi_share_of_depth(scene, T, size=(240, 180)):
    """Share of a view's valid depth pixels that back-project into the scene's ROI."""
    with RgbdRenderer(scene, width=size[0], height=size[1]) as renderer:
        _, depth = renderer.render(T)
    points, _ = backproject(depth, renderer.K, T)
    assert len(points) > 0.3 * depth.size
    return np.all((points >= scene.roi_min) & (points <= scene.roi_max), axis=1).mean()


@pytest.mark.parametrize(("kind", "seed"), HOLDOUT)
def test_holdout_scene_is_derived_from_geometry_at_the_right_level(holdout, kind, seed):
    scene = holdout[(kind, seed)]
    assert not list(scene.mjcf_path.parent.glob("*.json"))
    assert scene.name == f"{kind}_s{seed}" and scene.level == LEVEL[kind]
    assert scene.initial_views.shape == ((4, 4, 4) if LEVEL[kind] == "object" else (15, 4, 4))
    assert len(scene.eval_views) >= 18
    assert np.all(scene.roi_min < scene.roi_max)
    assert np.all(scene.workspace_min < scene.workspace_max)
    assert_views_valid_and_distinct(scene)


@pytest.mark.parametrize("seed", [0, 3])
def test_tabletop_roi_holds_the_objects_and_not_the_floor_or_legs(holdout, seed):
    scene = holdout[("tabletop", seed)]
    for name in ("cupboard_top", "cupboard_back", "hidden_box", "box"):
        lo, hi = geom_box(scene, name)
        assert np.all(lo >= scene.roi_min - 1e-6) and np.all(hi <= scene.roi_max + 1e-6), name
    model, _ = scene.model()
    for body in ("mug", "bottle", "hidden_blob"):
        geom = model.body(body).geomadr[0]
        lo, hi = geom_box(scene, model.geom(geom).name or geom)
        assert np.all(lo >= scene.roi_min - 1e-6) and np.all(hi <= scene.roi_max + 1e-6), body
    _, leg_top = geom_box(scene, "table_leg0")
    _, table_top = geom_box(scene, "table_top")
    assert scene.roi_min[2] > leg_top[2]  # legs (and the floor under them) are outside
    assert table_top[2] - 0.03 < scene.roi_min[2] < table_top[2]  # a slab of the top is inside
    assert scene.ground_truth_mesh().vertices[:, 2].min() > 0.7
    assert scene.workspace_min[2] > table_top[2]  # the camera stays above the support


@pytest.mark.parametrize("seed", [0, 1])
def test_alcove_room_roi_is_the_interior_and_the_camera_stays_inside(holdout, seed):
    scene = holdout[("alcove_room", seed)]
    # 5 x 4 m interior, floor at 0, walls 2.6 m high, 0.1 m thick
    assert np.allclose(scene.roi_min[:2], [-2.51, -2.01], atol=1e-3)
    assert np.allclose(scene.roi_max[:2], [2.51, 2.01], atol=1e-3)
    assert scene.roi_min[2] < 0.0 and scene.roi_max[2] > 2.0
    assert np.all(scene.workspace_min[:2] >= [-2.5, -2.0]) and np.all(
        scene.workspace_max[:2] <= [2.5, 2.0]
    )
    assert scene.workspace_min[2] >= 0.3 and scene.workspace_max[2] <= 2.3
    heights = np.round(scene.eval_views[:, 2, 3], 2)
    assert len(np.unique(heights)) >= 2  # held-out views at several heights
    yaws = np.arctan2(scene.initial_views[:, 1, 2], scene.initial_views[:, 0, 2])
    assert np.ptp(np.unwrap(np.sort(yaws))) > np.pi  # initial views look in many directions
    assert np.all(scene.initial_views[:, 2, 2] < 0)  # ... all slightly down


@pytest.mark.parametrize(
    ("kind", "seed"),
    [
        ("tabletop", 0),
        ("alcove_room", 1),
        ("shelf_wall", 0),
        ("shelf_wall", 1),
        ("thin_objects", 2),
        ("scanned_counter", 1),
    ],
)
def test_initial_views_see_the_roi(holdout, kind, seed):
    scene = holdout[(kind, seed)]
    for T in scene.initial_views[:2]:
        # (a tall shelf or a floor lamp is seen from further away, with the floor and walls around)
        assert roi_share_of_depth(scene, T) > {"tabletop": 0.4, "alcove_room": 0.9}.get(kind, 0.25)


@pytest.mark.parametrize("name", ["clutter7_a", "living_room"])
def test_a_bundled_scene_without_its_sidecar_derives_the_same_roi(tmp_path, name):
    for f in (SCENES_DIR / name).iterdir():
        if f.suffix != ".json":
            shutil.copy(f, tmp_path / f.name)
    bundled, derived = load_scene(name), load_scene(tmp_path / "scene.xml")
    assert derived.level == bundled.level
    assert np.allclose(derived.roi_min, bundled.roi_min, atol=0.01)
    assert np.allclose(derived.roi_max, bundled.roi_max, atol=0.01)
    assert_views_valid_and_distinct(derived)
    assert roi_share_of_depth(derived, derived.initial_views[0]) > 0.4


def box(lo, hi):
    return np.asarray(lo, dtype=float), np.asarray(hi, dtype=float)


def test_layout_of_a_table_keeps_the_objects_and_drops_legs_and_floor():
    parts = [
        box([-0.6, -0.4, 0.71], [0.6, 0.4, 0.75]),  # table top
        *[
            box([x - 0.02, y - 0.02, 0.0], [x + 0.02, y + 0.02, 0.71])
            for x in (-0.5, 0.5)
            for y in (-0.3, 0.3)
        ],
        box([0.0, 0.0, 0.75], [0.1, 0.1, 0.85]),  # an object
        box([-3.0, -3.0, 1.9], [-2.9, -2.9, 2.0]),  # a lamp far off the table: not on the support
    ]
    lo, hi = np.array([p[0] for p in parts]), np.array([p[1] for p in parts])
    layout = scene_layout(lo[:-1], hi[:-1], plane_z=0.0)
    assert layout["level"] == "object" and layout["support_z"] == pytest.approx(0.75)
    assert np.allclose(layout["roi_min"], [-0.06, -0.06, 0.73])
    assert np.allclose(layout["roi_max"], [0.16, 0.16, 0.87])
    assert layout["workspace_min"][2] > 0.75
    # the far lamp makes the footprint room-sized: the scene is then treated as a room
    assert scene_layout(lo, hi, plane_z=0.0)["level"] == "room"


def test_layout_of_a_small_walled_room_is_a_room_by_its_walls():
    # a 2.0 x 1.4 m closet (footprint diagonal 2.4 m < ROOM_DIAGONAL) with 2.4 m walls
    lo = np.array(
        [[-1.1, -0.8, -0.1], [-1.1, -0.8, 0], [1.0, -0.8, 0], [-1.1, -0.8, 0], [-1.1, 0.7, 0]]
    )
    hi = np.array(
        [[1.1, 0.8, 0.0], [-1.0, 0.8, 2.4], [1.1, 0.8, 2.4], [1.1, -0.7, 2.4], [1.1, 0.8, 2.4]]
    )
    layout = scene_layout(lo, hi)
    assert layout["level"] == "room" and layout["floor_z"] == pytest.approx(0.0)
    assert np.allclose(layout["interior_min"], [-1.0, -0.7, 0.0])
    assert np.allclose(layout["interior_max"], [1.0, 0.7, 2.4])
    assert np.allclose(layout["workspace_min"], [-0.7, -0.4, 0.4])
    assert np.allclose(layout["workspace_max"], [0.7, 0.4, 2.0])


def test_layout_rejects_boxes_of_the_wrong_shape_or_inverted():
    with pytest.raises(ValueError, match=r"lo, hi: got shapes \(2, 2\)"):
        scene_layout(np.zeros((2, 2)), np.ones((2, 2)))
    with pytest.raises(ValueError, match="inverted"):
        scene_layout(np.ones((1, 3)), np.zeros((1, 3)))


def test_holdout_writer_rejects_bad_input(tmp_path):
    with pytest.raises(ValueError, match="kind: got 'castle'"):
        write_holdout_scene("castle", tmp_path / "a")
    with pytest.raises(ValueError, match="seed: got -1"):
        write_holdout_scene("tabletop", tmp_path / "b", -1)
    (tmp_path / "c").mkdir()
    (tmp_path / "c" / "scene.json").write_text("{}")
    with pytest.raises(ValueError, match="folder: got .*scene.json"):
        write_holdout_scene("tabletop", tmp_path / "c")


def test_a_room_mjcf_without_metadata_puts_every_view_inside_the_walls(tmp_path):
    path = tmp_path / "bare_room.xml"
    path.write_text(
        """<mujoco><worldbody><light directional="true" dir="0 0 -1"/>
        <geom type="plane" size="0 0 0.1"/>
        <geom type="box" pos="0 -2.05 1.3" size="3.1 0.05 1.3"/>
        <geom type="box" pos="0 2.05 1.3" size="3.1 0.05 1.3"/>
        <geom type="box" pos="-3.05 0 1.3" size="0.05 2 1.3"/>
        <geom type="box" pos="3.05 0 1.3" size="0.05 2 1.3"/>
        <geom type="box" pos="0.5 0.3 0.4" size="0.6 0.4 0.4"/>
        </worldbody></mujoco>"""
    )
    scene = load_scene(path)
    assert scene.level == "room" and len(scene.initial_views) == 15
    eyes = np.concatenate([scene.initial_views, scene.eval_views])[:, :3, 3]
    assert np.all(np.abs(eyes[:, 0]) < 3.0) and np.all(np.abs(eyes[:, 1]) < 2.0)
    assert np.all((eyes[:, 2] > 0.3) & (eyes[:, 2] < 2.5))
    assert_views_valid_and_distinct(scene)


def geom_boxes(scene):
    """{name: (lo, hi)} world bounding box of every named solid geom of the scene."""
    from sim_bridge.geoms import geom_meshes, solid_geom_ids

    model, data = scene.model()
    ids = solid_geom_ids(model)
    return {
        model.geom(int(g)).name or f"geom{int(g)}": m.bounds
        for g, m in zip(ids, geom_meshes(model, data, ids), strict=True)
    }


def wall_sides(scene, walls):
    """[(axis, inward sign, face)] of each wall box: the face towards the ROI's centre."""
    centre = (scene.roi_min + scene.roi_max) / 2
    out = []
    for lo, hi in walls:
        axis = int(np.argmin((hi - lo)[:2]))  # the wall's thin axis
        sign = 1.0 if centre[axis] > (lo[axis] + hi[axis]) / 2 else -1.0
        out.append((axis, sign, hi[axis] if sign > 0 else lo[axis]))
    return out


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_shelf_against_walls_is_seen_from_its_open_side_only(holdout, seed):
    scene = holdout[("shelf_wall", seed)]
    boxes = geom_boxes(scene)
    walls = [boxes[n] for n in ("wall_back", "wall_side") if n in boxes]
    assert len(walls) == (2 if seed % 2 == 0 else 1)  # even seeds: a corner
    sides = wall_sides(scene, walls)
    eyes = {
        "initial": scene.initial_views[:, :3, 3],
        "held-out": scene.eval_views[:, :3, 3],
    }
    for axis, sign, face in sides:
        # the ROI stops before the wall face, the workspace stays in front of it
        assert sign * (scene.roi_min[axis] if sign > 0 else scene.roi_max[axis]) > sign * face
        ws_near = scene.workspace_min[axis] if sign > 0 else scene.workspace_max[axis]
        assert sign * (ws_near - face) >= 0.1 - 1e-9
        for what, points in eyes.items():
            assert np.all(sign * (points[:, axis] - face) >= 0.1), what  # no view behind a wall
    for lo, hi in walls:  # no part of a wall is inside the ROI
        assert np.any((lo > scene.roi_max) | (hi < scene.roi_min))
    # the shelf, the cabinet and every object on them are inside the ROI (up to the wall gap)
    for name, (lo, hi) in boxes.items():
        if not name.startswith("wall"):
            assert np.all(lo >= scene.roi_min - 0.011) and np.all(hi <= scene.roi_max + 0.011), name
    # the initial views face the open side: away from the wall, or along the corner's diagonal
    inward = np.zeros(2)
    for axis, sign, _ in sides:
        inward[axis] += sign
    centre = (scene.roi_min + scene.roi_max)[:2] / 2
    mean_dir = (eyes["initial"][:, :2] - centre).mean(axis=0)
    cos = mean_dir @ inward / np.linalg.norm(mean_dir) / np.linalg.norm(inward)
    assert cos > np.cos(np.deg2rad(20))
    # the held-out views spread over the open side, wider than the initial arc
    az = np.arctan2(*(eyes["held-out"][:, :2] - centre).T[::-1])
    az0 = np.arctan2(inward[1], inward[0])
    spread = np.ptp(np.angle(np.exp(1j * (az - az0))))
    assert spread > np.deg2rad(100 if len(walls) == 2 else 150)
    assert_views_valid_and_distinct(scene)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_thin_objects_are_thin_textureless_and_glossy_and_all_in_the_roi(holdout, seed):
    import mujoco

    scene = holdout[("thin_objects", seed)]
    model, _ = scene.model()
    boxes = geom_boxes(scene)
    for name, (lo, hi) in boxes.items():
        assert np.all(lo >= scene.roi_min - 1e-6) and np.all(hi <= scene.roi_max + 1e-6), name
    legs = [n for n in boxes if n.startswith("stool_leg")]
    assert len(legs) >= 3
    for name in legs + ["lamp_pole"]:
        assert model.geom(name).size[0] <= 0.015  # a thin leg or pole: a radius under 1.5 cm
    lamp_top = boxes["lamp_pole"][1][2]
    assert lamp_top > 1.3 and scene.roi_max[2] > lamp_top

    def material(body):
        return model.mat(int(model.geom_matid[model.body(body).geomadr[0]]))

    shade, bowl = material("lamp_shade"), material("bowl")
    assert shade.texid[mujoco.mjtTextureRole.mjTEXROLE_RGB] == -1  # a plain shade, no texture
    assert bowl.texid[mujoco.mjtTextureRole.mjTEXROLE_RGB] == -1 and bowl.specular[0] >= 0.9
    large = ("screen_panel", "cabinet", "low_table_top")[seed % 3]  # a large plain surface
    assert np.prod(np.sort(boxes[large][1] - boxes[large][0])[1:]) > 0.15  # m^2, its 2 long sides
    rgb = mujoco.mjtTextureRole.mjTEXROLE_RGB
    assert model.mat(int(model.geom_matid[model.geom(large).id])).texid[rgb] == -1
    assert_views_valid_and_distinct(scene)


def test_layout_of_a_shelf_against_a_wall_is_an_object_seen_from_the_open_side():
    parts = [
        box([-1.5, 0.0, 0.0], [1.5, 0.1, 2.4]),  # the wall
        box([-0.6, -0.36, 0.0], [-0.58, -0.01, 1.8]),  # the shelf's sides
        box([0.58, -0.36, 0.0], [0.6, -0.01, 1.8]),
        box([-0.58, -0.022, 0.0], [0.58, -0.01, 1.8]),  # its back board: tall, 1.16 m long
        *[box([-0.58, -0.36, z - 0.02], [0.58, -0.022, z]) for z in (0.1, 0.6, 1.1, 1.8)],
        box([0.0, -0.2, 0.6], [0.1, -0.1, 0.75]),  # objects on a board and on top
        box([-0.3, -0.15, 1.8], [-0.2, -0.05, 1.95]),
    ]
    lo, hi = np.array([p[0] for p in parts]), np.array([p[1] for p in parts])
    layout = scene_layout(lo, hi, plane_z=0.0)
    # the 3 m wall made this a room before; the shelf unit and its objects are the object now
    assert layout["level"] == "object" and layout["support_z"] == pytest.approx(0.0)
    assert layout["walls"] == [(1, -1.0, 0.0)] and layout["open_azimuth_deg"] == -90.0
    assert np.allclose(layout["roi_min"], [-0.6, -0.36, -0.02])
    assert np.allclose(layout["roi_max"], [0.6, -0.01, 1.97])  # up to 1 cm before the wall
    assert layout["workspace_max"][1] == pytest.approx(-0.1)  # 10 cm in front of the wall
    assert layout["workspace_min"][1] < -0.36 - 1.0  # and far out on the open side


def test_layout_of_a_counter_in_a_corner_keeps_its_worktop_objects_off_the_walls():
    parts = [
        box([-1.2, 0.0, 0.0], [1.2, 0.1, 2.4]),  # north wall
        box([1.2, -1.8, 0.0], [1.3, 0.1, 2.4]),  # east wall
        box([0.4, -0.6, 0.0], [1.195, -0.005, 0.85]),  # cabinet
        box([0.4, -0.63, 0.85], [1.195, -0.005, 0.88]),  # worktop
        box([0.6, -0.3, 0.88], [0.7, -0.2, 1.0]),  # objects on it
        box([1.1, -0.1, 0.88], [1.19, -0.05, 1.1]),
    ]
    lo, hi = np.array([p[0] for p in parts]), np.array([p[1] for p in parts])
    layout = scene_layout(lo, hi, plane_z=0.0)
    assert layout["level"] == "object" and layout["support_z"] == pytest.approx(0.88)
    assert layout["open_azimuth_deg"] == pytest.approx(-135.0)  # the corner's diagonal
    assert np.allclose(layout["roi_min"], [0.54, -0.36, 0.86])
    assert np.allclose(layout["roi_max"], [1.19, -0.01, 1.12])  # the walls' faces stop it
    assert np.allclose(layout["workspace_max"][:2], [1.1, -0.1])


def test_layout_counts_a_backdrop_once_and_a_large_or_walled_in_footprint_stays_a_room():
    backdrop = box([-0.6, 0.0, 0.0], [0.6, 0.05, 2.0])  # near both edges of a shallow footprint
    thing = box([-0.1, -0.25, 0.0], [0.1, -0.15, 0.3])
    lo, hi = np.array([backdrop[0], thing[0]]), np.array([backdrop[1], thing[1]])
    layout = scene_layout(lo, hi, plane_z=0.0)
    assert layout["level"] == "object" and layout["walls"] == [(1, -1.0, 0.0)]
    assert layout["roi_max"][1] == pytest.approx(-0.15)  # the thing, not the backdrop
    assert layout["workspace_min"][1] < -0.8 and layout["workspace_max"][1] == pytest.approx(-0.1)
    # one wall, but the furniture in front of it spans more than ROOM_DIAGONAL: a room
    far = box([1.6, -2.8, 0.0], [2.0, -2.4, 0.8])
    wall = box([-2.0, 0.0, 0.0], [2.0, 0.1, 2.4])
    lo, hi = np.array([wall[0], thing[0], far[0]]), np.array([wall[1], thing[1], far[1]])
    assert scene_layout(lo, hi, plane_z=0.0)["level"] == "room"
    # walls on three sides enclose a room, however small
    west, east = box([-1.0, -1.0, 0.0], [-0.9, 0.1, 2.4]), box([0.9, -1.0, 0.0], [1.0, 0.1, 2.4])
    north = box([-1.0, 0.0, 0.0], [1.0, 0.1, 2.4])
    lo = np.array([west[0], east[0], north[0], thing[0]])
    hi = np.array([west[1], east[1], north[1], thing[1]])
    assert scene_layout(lo, hi, plane_z=0.0)["level"] == "room"


@pytest.mark.parametrize("name", ["living_room", "office"])
def test_bundled_rooms_derive_their_sidecar_room_from_geometry(name):
    import mujoco

    from sim_bridge.scene_layout import geometry_boxes

    bundled = load_scene(name)  # from its sidecar
    model = mujoco.MjModel.from_xml_path(str(bundled.mjcf_path))
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    layout = scene_layout(*geometry_boxes(model, data))
    assert layout["level"] == "room"
    for key in ("roi_min", "roi_max", "workspace_min", "workspace_max"):
        assert np.allclose(layout[key], getattr(bundled, key), atol=1e-9), key


@pytest.mark.parametrize("seed", [0, 1])
def test_alcove_room_workspace_is_the_interior_off_the_walls(holdout, seed):
    scene = holdout[("alcove_room", seed)]
    # 5 x 4 m interior, walls 2.6 m high: 0.3 m in from the walls, 0.4 to 2.0 m above the floor
    assert np.allclose(scene.workspace_min, [-2.2, -1.7, 0.4])
    assert np.allclose(scene.workspace_max, [2.2, 1.7, 2.0])


def test_the_command_line_asks_for_help_without_writing_a_folder_named_help(
    tmp_path, monkeypatch, capsys
):
    from sim_bridge.holdout_scenes import main

    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as stop:
        main(["--help"])
    assert stop.value.code == 0 and "out_dir" in capsys.readouterr().out
    with pytest.raises(SystemExit) as stop:
        main(["out", "one"])  # a seed that is no number: refused by argparse, nothing written
    assert stop.value.code == 2 and "invalid int value: 'one'" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []
