"""The bundled room scenes (living_room, office): furniture from primitives plus scaled procedural
meshes inside a 6 x 5 m room, with hand-placed initial and held-out views."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from area3d_msgs_py.camera_pose import look_at
from sim_bridge import meshes
from sim_bridge.mjcf import (
    ROOM_HALF,
    WALL_HEIGHT,
    Mjcf,
    blank_scene,
    mesh_asset,
    mesh_body,
    room_shell,
    table4,
)
from sim_bridge.scene import INITIAL_VIEWS, Scene
from sim_bridge.scenes import SCENES_DIR, scene_to_json

SEED = 7  # fixed so that regenerating gives the same scenes (the object scenes add their name)
ROOM_SCENES = ("living_room", "office")
VIEW_CLEARANCE_ROOM = 0.4  # metres: bundled room views keep this far from every surface


def _living_room(doc: Mjcf, folder: Path) -> None:
    room_shell(doc, folder)
    fabric = doc.material(folder, "fabric", "checker", (60, 80, 130), (90, 110, 160), repeat=(6, 6))
    wood = doc.material(folder, "wood", "stripes", (110, 70, 40), (160, 115, 70), repeat=(4, 4))
    dark = doc.material(folder, "dark", "noise", (25, 25, 30), (60, 60, 70), repeat=(4, 4), seed=2)
    rug = doc.material(folder, "rug", "dots", (170, 40, 40), (230, 200, 150), repeat=(3, 3))
    plant = doc.material(folder, "plant", "noise", (40, 110, 40), (120, 180, 80), seed=4)
    books = doc.material(folder, "books", "stripes", (200, 60, 40), (40, 90, 160), repeat=(5, 1))
    # Sofa against the south wall.
    doc.box("sofa_base", [0.0, -2.05, 0.22], [2.0, 0.8, 0.44], fabric)
    doc.box("sofa_back", [0.0, -2.38, 0.6], [2.0, 0.16, 0.5], fabric)
    doc.box("sofa_arm_l", [-1.08, -2.05, 0.32], [0.16, 0.8, 0.64], fabric)
    doc.box("sofa_arm_r", [1.08, -2.05, 0.32], [0.16, 0.8, 0.64], fabric)
    doc.box("rug", [0.0, -0.7, 0.005], [2.4, 1.6, 0.01], rug)
    table4(doc, "coffee_table", (0.0, -0.8), (1.1, 0.6), 0.42, wood, dark)
    # TV stand and TV opposite the sofa, against the north wall.
    doc.box("tv_stand", [0.0, 2.25, 0.25], [1.6, 0.45, 0.5], wood)
    doc.box("tv", [0.0, 2.3, 0.95], [1.3, 0.06, 0.75], dark)
    # Bookshelf on the west wall.
    for i, z in enumerate([0.02, 0.5, 1.0, 1.5, 1.98]):
        doc.box(f"shelf{i}", [-2.82, 0.6, z], [0.35, 1.2, 0.03], wood)
    doc.box("shelf_side_a", [-2.82, 0.0, 1.0], [0.35, 0.03, 2.0], wood)
    doc.box("shelf_side_b", [-2.82, 1.2, 1.0], [0.35, 0.03, 2.0], wood)
    for i, z in enumerate([0.26, 0.76, 1.26]):
        doc.box(f"books{i}", [-2.84, 0.45 + 0.1 * i, z], [0.25, 0.7, 0.42], books)
    # An L-shaped partition in the north-east: an alcove with a cabinet behind it (occluded corner).
    doc.box("partition_a", [1.9, 0.6, 1.0], [1.3, 0.1, 2.0], dark)
    doc.box("partition_b", [1.3, 1.15, 1.0], [0.1, 1.0, 2.0], dark)
    doc.box("alcove_cabinet", [2.6, 1.4, 0.45], [0.7, 0.5, 0.9], wood)
    # Armchair, dining table with chairs, floor lamp and a plant (meshes).
    doc.box("armchair_seat", [-1.6, -1.2, 0.22], [0.8, 0.8, 0.44], fabric)
    doc.box("armchair_back", [-1.95, -1.2, 0.6], [0.12, 0.8, 0.5], fabric)
    table4(doc, "dining_table", (1.6, -1.0), (1.2, 0.8), 0.75, wood, dark)
    chair = mesh_asset(doc, folder, "chair", meshes.toy_chair(), [4.0, 4.0, 7.0])
    mesh_body(doc, "chair_a", chair, [1.6, -1.65, 0.0], np.pi / 2, "wood")
    mesh_body(doc, "chair_b", chair, [1.6, -0.35, 0.0], -np.pi / 2, "wood")
    lamp = mesh_asset(doc, folder, "floor_lamp", meshes.lamp(), [6.0, 6.0, 7.5])
    mesh_body(doc, "floor_lamp", lamp, [-2.4, -2.0, 0.0], 0.7, "dark")
    blob = mesh_asset(doc, folder, "plant_blob", meshes.blob(seed=11), [3.5, 3.5, 5.0])
    doc.cylinder("plant_pot", [-2.5, 2.1, 0.2], 0.2, 0.4, "wood")
    mesh_body(doc, "plant", blob, [-2.5, 2.1, 0.4], 0.0, plant)


def _office(doc: Mjcf, folder: Path) -> None:
    room_shell(doc, folder, ("checker", (205, 210, 215), (225, 228, 232)))
    desk = doc.material(
        folder, "desk", "noise", (190, 170, 140), (220, 205, 180), repeat=(4, 4), seed=6
    )
    dark = doc.material(folder, "dark", "noise", (30, 30, 35), (70, 70, 80), repeat=(4, 4), seed=2)
    grey = doc.material(folder, "grey", "stripes", (120, 125, 135), (150, 155, 165), repeat=(6, 6))
    board = doc.material(folder, "board", "dots", (245, 245, 245), (40, 60, 160), repeat=(4, 2))
    plant = doc.material(folder, "plant", "noise", (40, 110, 40), (120, 180, 80), seed=4)
    chair = mesh_asset(doc, folder, "chair", meshes.toy_chair(), [4.0, 4.0, 7.0])
    # Three desks with monitors and chairs in a row along the south wall.
    for i, x in enumerate([-1.8, 0.0, 1.8]):
        table4(doc, f"desk{i}", (x, -1.9), (1.4, 0.7), 0.74, desk, dark)
        doc.box(f"monitor{i}", [x, -2.05, 1.05], [0.6, 0.04, 0.36], dark)
        doc.box(f"monitor_stand{i}", [x, -2.05, 0.8], [0.08, 0.08, 0.14], dark)
        mesh_body(
            doc,
            f"chair{i}",
            chair,
            [x + 0.1 * (i - 1), -1.15, 0.0],
            -np.pi / 2 + 0.3 * (i - 1),
            "grey",
        )
    # Cubicle partitions (1.3 m high) between the desks.
    for i, x in enumerate([-0.9, 0.9]):
        doc.box(f"cubicle{i}", [x, -1.8, 0.65], [0.05, 1.3, 1.3], grey)
    # Meeting table in the middle, filing cabinets and a whiteboard.
    table4(doc, "meeting_table", (0.0, 0.6), (2.0, 1.0), 0.74, desk, dark)
    for i, x in enumerate([-1.0, 1.0]):
        mesh_body(doc, f"meeting_chair{i}", chair, [x, 1.35, 0.0], np.pi / 2, "grey")
    for i, y in enumerate([-0.2, 0.35, 0.9]):
        doc.box(f"cabinet{i}", [2.7, y, 0.65], [0.5, 0.5, 1.3], grey)
    doc.box("whiteboard", [-2.93, 0.5, 1.4], [0.03, 1.8, 1.0], board)
    # A storage corner behind a tall bookcase (occluded from most of the room).
    doc.box("bookcase", [-1.6, 1.5, 0.95], [1.6, 0.4, 1.9], desk)
    doc.box("boxes_behind", [-2.3, 2.1, 0.3], [0.6, 0.5, 0.6], dark)
    doc.box("printer", [-1.3, 2.15, 0.4], [0.6, 0.5, 0.8], grey)
    blob = mesh_asset(doc, folder, "plant_blob", meshes.blob(seed=12), [3.0, 3.0, 5.0])
    doc.cylinder("plant_pot", [2.6, 2.1, 0.2], 0.2, 0.4, desk)
    mesh_body(doc, "plant", blob, [2.6, 2.1, 0.4], 0.0, plant)


def _lights_room() -> list[str]:
    return [
        '<light name="ceiling_a" pos="-1.5 0 2.5" dir="0 0 -1" diffuse="0.35 0.35 0.35" castshadow="false" attenuation="1 0.1 0"/>',
        '<light name="ceiling_b" pos="1.5 0 2.5" dir="0 0 -1" diffuse="0.35 0.35 0.35" castshadow="false" attenuation="1 0.1 0"/>',
    ]


def build_room_scene(name: str) -> Scene:
    from sim_bridge.validity import valid_positions

    folder = SCENES_DIR / name
    folder.mkdir(parents=True, exist_ok=True)
    for old in folder.iterdir():
        if old.suffix in (".obj", ".png", ".xml", ".json"):
            old.unlink()
    doc = Mjcf(name)
    {"living_room": _living_room, "office": _office}[name](doc, folder)
    (folder / "scene.xml").write_text(doc.xml(_lights_room()))
    hx, hy = ROOM_HALF
    scene = blank_scene(name, "room", folder)
    # ROI: the furnished interior, walls' inner faces and the floor's top included (1 cm slack).
    scene.roi_min = np.array([-hx - 0.01, -hy - 0.01, -0.01])
    scene.roi_max = np.array([hx + 0.01, hy + 0.01, WALL_HEIGHT - 0.1])
    # Camera positions: inside the room, 0.3 m off the walls, between knee and above-head height.
    scene.workspace_min = np.array([-hx + 0.3, -hy + 0.3, 0.4])
    scene.workspace_max = np.array([hx - 0.3, hy - 0.3, 2.0])
    rng = np.random.default_rng(SEED)
    # O_0: 15 views from the west half of the room, looking east-ish (limited arc of headings).
    eyes = np.array(
        [(x, y, z) for x in (-2.3, -1.6, -0.9) for y in (-1.2, -0.4, 0.3, 1.0, 1.6) for z in (1.5,)]
    )
    eyes[:, 2] += rng.uniform(-0.2, 0.2, len(eyes))
    eyes = _nudge_valid(scene, eyes, valid_positions)
    heading = np.deg2rad(rng.uniform(-50, 50, len(eyes)))
    targets = eyes + np.stack([np.cos(heading), np.sin(heading), np.full(len(eyes), -0.45)], 1)
    scene.initial_views = np.stack([look_at(e, t) for e, t in zip(eyes, targets, strict=True)])
    assert len(scene.initial_views) == INITIAL_VIEWS["room"]
    # Held-out views: a 5 x 4 grid over the whole room, each looking towards the room centre.
    eyes = np.array(
        [
            (x, y, 1.3 + 0.15 * ((i + j) % 3))
            for i, x in enumerate(np.linspace(-2.4, 2.4, 5))
            for j, y in enumerate(np.linspace(-1.9, 1.9, 4))
        ]
    )
    eyes = _nudge_valid(scene, eyes, valid_positions)
    targets = np.array([0.0, 0.0, 0.6]) + 0.3 * (eyes - [0, 0, 1.3])
    targets[:, 2] = 0.6
    scene.eval_views = np.stack([look_at(e, t) for e, t in zip(eyes, targets, strict=True)])
    (folder / "scene.json").write_text(scene_to_json(scene))
    return scene


def _nudge_valid(scene: Scene, eyes: np.ndarray, valid_positions) -> np.ndarray:
    """Move each camera position that is too close to geometry to the nearest valid position."""
    eyes = eyes.copy()
    ok = valid_positions(scene, eyes, clearance=VIEW_CLEARANCE_ROOM)
    offsets = np.random.default_rng(SEED).uniform(-1.0, 1.0, (4000, 3)) * [1.0, 1.0, 0.4]
    offsets = offsets[np.argsort(np.linalg.norm(offsets, axis=1))]
    for i in np.flatnonzero(~ok):
        good = np.flatnonzero(
            valid_positions(scene, eyes[i] + offsets, clearance=VIEW_CLEARANCE_ROOM)
        )
        if len(good) == 0:
            raise RuntimeError(
                f"{scene.name}: no free camera position within 1 m of {eyes[i].tolist()}"
            )
        eyes[i] = eyes[i] + offsets[good[0]]
    return eyes
