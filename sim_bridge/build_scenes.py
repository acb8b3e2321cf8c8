"""Generate the bundled scenes: meshes, textures, physics-settled MJCF and the sidecar metadata.

    python -m sim_bridge.build_scenes            # all scenes
    python -m sim_bridge.build_scenes office     # one scene

Object-level scenes drop their objects onto the table from a few centimetres with small random
poses (fixed seed), step MuJoCo until everything rests and write the settled poses into a static
MJCF (no joints), so loading a scene needs no simulation.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass, field
from pathlib import Path

import mujoco
import numpy as np

from area3d_msgs_py.camera_pose import look_at
from sim_bridge import meshes
from sim_bridge.scene import GAMMA, INITIAL_VIEWS, TAU, Scene
from sim_bridge.scene_layout import ROI_RIM
from sim_bridge.scenes import SCENES_DIR, scene_to_json
from sim_bridge.textures import write_texture
from sim_bridge.views import orbit_views

SEED = 7  # fixed so that regenerating gives the same scenes
TABLE_TOP_Z = 0.75  # metres, a standard table height
TABLE_SIZE = (0.9, 0.6, 0.03)  # metres, full extents of the table top
SETTLE_SECONDS = 3.0  # simulated time for the drop to come to rest
WIDTH, HEIGHT = 640, 480  # offscreen buffer for the default camera resolution

OBJECT_SCENES: dict[str, list[str]] = {
    "single_object": ["blob"],
    "five_objects": ["mug", "bowl", "vase", "toy_chair", "l_shape"],
    "clutter7_a": ["mug", "blob", "tunnel_block", "torus_knot", "lamp", "wire_rack", "bowl"],
    "clutter7_b": ["vase", "toy_chair", "l_shape", "torus_knot", "blob", "mug", "tunnel_block"],
}
ROOM_SCENES = ("living_room", "office")

PALETTE = [
    ("stripes", (200, 60, 50), (240, 200, 170)),
    ("checker", (40, 90, 170), (220, 220, 230)),
    ("noise", (60, 140, 70), (200, 230, 150)),
    ("dots", (230, 190, 40), (90, 50, 20)),
    ("stripes", (120, 60, 160), (230, 210, 240)),
    ("noise", (160, 110, 60), (240, 220, 190)),
    ("checker", (30, 30, 30), (230, 120, 40)),
]


@dataclass
class _Mjcf:
    """Accumulates MJCF assets and world-body children."""

    name: str
    assets: list[str] = field(default_factory=list)
    bodies: list[str] = field(default_factory=list)
    textures: set = field(default_factory=set)

    def material(self, folder: Path, name: str, kind: str, a, b, repeat=(1, 1), seed=0) -> str:
        if name not in self.textures:
            write_texture(folder / f"{name}.png", kind, a, b, seed)
            self.assets.append(f'<texture name="{name}" type="2d" file="{name}.png"/>')
            self.assets.append(
                f'<material name="{name}" texture="{name}" texrepeat="{repeat[0]} {repeat[1]}" texuniform="{"true" if repeat != (1, 1) else "false"}" specular="0.1"/>'
            )
            self.textures.add(name)
        return name

    def box(self, name, centre, extents, material) -> None:
        c, h = np.asarray(centre), np.asarray(extents) / 2
        self.bodies.append(
            f'<geom name="{name}" type="box" pos="{_v(c)}" size="{_v(h)}" material="{material}"/>'
        )

    def cylinder(self, name, centre, radius, height, material) -> None:
        self.bodies.append(
            f'<geom name="{name}" type="cylinder" pos="{_v(centre)}" size="{radius:.4f} {height / 2:.4f}" material="{material}"/>'
        )

    def xml(self, lights: list[str], extra_world: str = "") -> str:
        return f"""<mujoco model="{self.name}">
  <compiler angle="radian" inertiafromgeom="false"/>
  <option timestep="0.002"/>
  <visual>
    <global offwidth="{WIDTH}" offheight="{HEIGHT}"/>
    <quality offsamples="0"/>
    <headlight ambient="0.35 0.35 0.35" diffuse="0.45 0.45 0.45" specular="0.05 0.05 0.05"/>
  </visual>
  <asset>
    {chr(10).join("    " + a for a in self.assets).strip()}
  </asset>
  <worldbody>
    {chr(10).join("    " + a for a in lights).strip()}
    {extra_world}
    {chr(10).join("    " + b for b in self.bodies).strip()}
  </worldbody>
</mujoco>
"""


def _v(x) -> str:
    return " ".join(f"{float(a):.5f}" for a in np.asarray(x).ravel())


def _table(doc: _Mjcf, folder: Path) -> None:
    wood = doc.material(folder, "wood", "stripes", (120, 80, 45), (170, 120, 70), repeat=(4, 4))
    metal = doc.material(
        folder, "metal", "noise", (80, 80, 85), (140, 140, 150), repeat=(8, 8), seed=3
    )
    sx, sy, sz = TABLE_SIZE
    doc.box("table_top", [0, 0, TABLE_TOP_Z - sz / 2], TABLE_SIZE, wood)
    for i, (x, y) in enumerate([(-1, -1), (-1, 1), (1, -1), (1, 1)]):
        doc.box(
            f"table_leg{i}",
            [x * (sx / 2 - 0.05), y * (sy / 2 - 0.05), (TABLE_TOP_Z - sz) / 2],
            [0.04, 0.04, TABLE_TOP_Z - sz],
            metal,
        )


def _object_assets(
    doc: _Mjcf, folder: Path, kinds: list[str], rng
) -> list[tuple[str, str, float, float]]:
    """Write each object's mesh and texture; returns (body name, mesh name, radius, mass)."""
    out = []
    for i, kind in enumerate(kinds):
        gen = meshes.GENERATORS[kind]
        mesh = gen(seed=i + 1) if kind == "blob" else gen()
        mesh_name = f"obj{i}_{kind}"
        meshes.write_obj(mesh, folder / f"{mesh_name}.obj")
        kind_tex, a, b = PALETTE[i % len(PALETTE)]
        mat = doc.material(folder, f"tex{i}", kind_tex, a, b, seed=i)
        doc.assets.append(f'<mesh name="{mesh_name}" file="{mesh_name}.obj"/>')
        radius = float(np.linalg.norm(mesh.extents[:2]) / 2)
        out.append((f"obj{i}", mesh_name, mat, radius, mesh))
    return out


def _slots(n: int, rng) -> np.ndarray:
    """(n, 2) table positions, metres: a jittered grid over the middle of the table top."""
    if n == 1:
        return np.zeros((1, 2))
    cols = int(np.ceil(np.sqrt(n * 1.5)))
    rows = int(np.ceil(n / cols))
    xs = np.linspace(-0.27, 0.27, cols) if cols > 1 else np.zeros(1)
    ys = np.linspace(-0.15, 0.15, rows) if rows > 1 else np.zeros(1)
    grid = np.array([(x, y) for y in ys for x in xs])[:n]
    return grid + rng.uniform(-0.015, 0.015, grid.shape)


def _settle(doc: _Mjcf, objects, rng) -> list[tuple[np.ndarray, np.ndarray]]:
    """Drop the objects onto the table and simulate until they rest; returns (pos, quat) each."""
    slots = _slots(len(objects), rng)
    dynamic = []
    for (body, mesh_name, mat, _radius, mesh), (x, y) in zip(objects, slots, strict=True):
        yaw = rng.uniform(-np.pi, np.pi)
        tilt = rng.normal(0, 0.05, 2)
        quat = np.zeros(4)
        mujoco.mju_euler2Quat(quat, np.array([tilt[0], tilt[1], yaw]), "xyz")
        com = mesh.center_mass
        mass = 0.3
        inertia = mass * (mesh.extents**2).sum() / 12 * np.ones(3)
        dynamic.append(
            f'<body name="{body}" pos="{x:.4f} {y:.4f} {TABLE_TOP_Z + 0.02:.4f}" quat="{_v(quat)}"><freejoint/>'
            f'<inertial pos="{_v(com)}" mass="{mass}" diaginertia="{_v(inertia)}"/>'
            f'<geom type="mesh" mesh="{mesh_name}" material="{mat}" friction="1.0 0.02 0.001"/></body>'
        )
    xml = doc.xml([], '<geom name="floor" type="plane" size="0 0 0.05"/>' + "\n".join(dynamic))
    model = mujoco.MjModel.from_xml_string(xml, _asset_dict(doc))
    data = mujoco.MjData(model)
    for _ in range(int(SETTLE_SECONDS / model.opt.timestep)):
        mujoco.mj_step(model, data)
    poses = []
    for body, *_ in objects:
        b = model.body(body).id
        poses.append((data.xpos[b].copy(), data.xquat[b].copy()))
    speed = np.abs(data.qvel).max()
    if speed > 0.05:
        print(
            f"warning: {doc.name} not fully at rest after {SETTLE_SECONDS} s (max |qvel| {speed:.3f})"
        )
    return poses


_FOLDER: dict[str, Path] = {}


def _asset_dict(doc: _Mjcf) -> dict[str, bytes]:
    folder = _FOLDER[doc.name]
    return {p.name: p.read_bytes() for p in folder.iterdir() if p.suffix in (".obj", ".png")}


def _lights_object() -> list[str]:
    return [
        '<light name="sun" directional="true" pos="0 0 3" dir="0.3 0.4 -1" diffuse="0.5 0.5 0.5" castshadow="false"/>',
    ]


def build_object_scene(name: str) -> Scene:
    folder = SCENES_DIR / name
    folder.mkdir(parents=True, exist_ok=True)
    for old in folder.iterdir():
        if old.suffix in (".obj", ".png", ".xml", ".json"):
            old.unlink()
    _FOLDER[name] = folder
    rng = np.random.default_rng(SEED + sum(map(ord, name)))
    doc = _Mjcf(name)
    floor = doc.material(folder, "floor", "checker", (90, 90, 95), (150, 150, 155), repeat=(2, 2))
    _table(doc, folder)
    objects = _object_assets(doc, folder, OBJECT_SCENES[name], rng)
    poses = _settle(doc, objects, rng)
    for (body, mesh_name, mat, _r, _m), (pos, quat) in zip(objects, poses, strict=True):
        doc.bodies.append(
            f'<body name="{body}" pos="{_v(pos)}" quat="{_v(quat)}"><geom type="mesh" mesh="{mesh_name}" material="{mat}"/></body>'
        )
    (folder / "scene.xml").write_text(
        doc.xml(
            _lights_object(),
            f'<geom name="floor" type="plane" size="0 0 0.05" material="{floor}"/>',
        )
    )

    # Scene bounds from the settled geometry.
    scene = _placeholder(name, "object", folder)
    mesh = scene.scene_mesh()
    top = TABLE_TOP_Z
    obj_hi = max(float(mesh.vertices[mesh.vertices[:, 2] > top + 1e-4][:, 2].max()), top + 0.05)
    sx, sy, _ = TABLE_SIZE
    objects_lo = mesh.vertices[mesh.vertices[:, 2] > top + 1e-4].min(axis=0)
    objects_hi = mesh.vertices[mesh.vertices[:, 2] > top + 1e-4].max(axis=0)
    # ROI: the objects plus a rim of table top around them (not the whole table).
    table_lo, table_hi = np.array([-sx / 2, -sy / 2]), np.array([sx / 2, sy / 2])
    scene.roi_min = np.array([*np.maximum(objects_lo[:2] - ROI_RIM, table_lo), top - 0.02])
    scene.roi_max = np.array([*np.minimum(objects_hi[:2] + ROI_RIM, table_hi), obj_hi + 0.02])
    # Camera positions: around the table, 0.3-1.0 m from the objects (paper, Sec. 4 setting).
    scene.workspace_min = np.array([-1.0, -0.9, top + 0.05])
    scene.workspace_max = np.array([1.0, 0.9, top + 1.0])
    centre = np.array([*((objects_lo[:2] + objects_hi[:2]) / 2), top + 0.4 * (obj_hi - top)])
    reach = max(0.45, 0.9 * float(np.linalg.norm(objects_hi[:2] - objects_lo[:2])))
    reach = min(reach, 0.8)
    # O_0: four views from the front (-y) quarter only, so the back of the objects is unseen.
    scene.initial_views = orbit_views(
        centre, reach, np.array([-110.0, -97.0, -84.0, -71.0]), np.array([18.0, 30.0, 22.0, 34.0])
    )
    # Held-out views: a ring all around plus a higher ring.
    az = np.concatenate([np.arange(12) * 30.0 + 10.0, np.arange(6) * 60.0 + 40.0])
    el = np.concatenate([np.full(12, 28.0), np.full(6, 60.0)])
    scene.eval_views = orbit_views(centre, reach + 0.05, az, el)
    (folder / "scene.json").write_text(scene_to_json(scene))
    return scene


def _placeholder(name: str, level: str, folder: Path) -> Scene:
    z3 = np.zeros(3)
    return Scene(
        name,
        level,
        folder / "scene.xml",
        z3,
        z3,
        z3,
        z3,
        np.zeros((0, 4, 4)),
        np.zeros((0, 4, 4)),
        GAMMA[level],
        TAU[level],
    )


# ---------------------------------------------------------------------------------------------
# Rooms: furniture from primitives plus scaled procedural meshes.

ROOM_HALF = (3.0, 2.5)  # metres: 6 m x 5 m interior
WALL_HEIGHT = 2.6
WALL_THICK = 0.1
VIEW_CLEARANCE_ROOM = 0.4  # metres: bundled room views keep this far from every surface


def _room_shell(
    doc: _Mjcf,
    folder: Path,
    wall_kind=("noise", (215, 210, 195), (235, 232, 222)),
    half: tuple[float, float] = ROOM_HALF,
) -> None:
    """Floor slab and four walls around an interior of 2 half[0] x 2 half[1] m centred on the
    origin, with a doorway in the north wall."""
    hx, hy = half
    floor = doc.material(folder, "floor", "stripes", (130, 95, 60), (175, 135, 90), repeat=(3, 3))
    wall = doc.material(folder, "wall", *wall_kind, repeat=(2, 2), seed=5)
    t, h = WALL_THICK, WALL_HEIGHT
    doc.box("floor", [0, 0, -0.05], [2 * hx + 2 * t, 2 * hy + 2 * t, 0.1], floor)
    doc.box("wall_south", [0, -hy - t / 2, h / 2], [2 * hx + 2 * t, t, h], wall)
    doc.box("wall_west", [-hx - t / 2, 0, h / 2], [t, 2 * hy, h], wall)
    doc.box("wall_east", [hx + t / 2, 0, h / 2], [t, 2 * hy, h], wall)
    # North wall with a doorway (1 m wide, 2.1 m high) so the room is not a closed box.
    door_x0, door_x1 = 1.2, 2.2
    doc.box(
        "wall_north_a", [(-hx - t + door_x0) / 2, hy + t / 2, h / 2], [door_x0 + hx + t, t, h], wall
    )
    doc.box(
        "wall_north_b", [(door_x1 + hx + t) / 2, hy + t / 2, h / 2], [hx + t - door_x1, t, h], wall
    )
    doc.box(
        "wall_north_lintel",
        [(door_x0 + door_x1) / 2, hy + t / 2, (h + 2.1) / 2],
        [door_x1 - door_x0, t, h - 2.1],
        wall,
    )


def _mesh_asset(doc: _Mjcf, folder: Path, name: str, mesh, scale) -> str:
    meshes.write_obj(mesh, folder / f"{name}.obj")
    doc.assets.append(f'<mesh name="{name}" file="{name}.obj" scale="{_v(scale)}"/>')
    return name


def _table4(doc, name, centre_xy, size, height, top_mat, leg_mat) -> None:
    x, y = centre_xy
    sx, sy = size
    doc.box(f"{name}_top", [x, y, height - 0.02], [sx, sy, 0.04], top_mat)
    for i, (a, b) in enumerate([(-1, -1), (-1, 1), (1, -1), (1, 1)]):
        doc.cylinder(
            f"{name}_leg{i}",
            [x + a * (sx / 2 - 0.06), y + b * (sy / 2 - 0.06), (height - 0.04) / 2],
            0.025,
            height - 0.04,
            leg_mat,
        )


def _chair_mesh_body(doc, name, mesh_name, pos, yaw, material) -> None:
    quat = np.zeros(4)
    mujoco.mju_euler2Quat(quat, np.array([0.0, 0.0, yaw]), "xyz")
    doc.bodies.append(
        f'<body name="{name}" pos="{_v(pos)}" quat="{_v(quat)}"><geom type="mesh" mesh="{mesh_name}" material="{material}"/></body>'
    )


def _living_room(doc: _Mjcf, folder: Path) -> None:
    _room_shell(doc, folder)
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
    _table4(doc, "coffee_table", (0.0, -0.8), (1.1, 0.6), 0.42, wood, dark)
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
    _table4(doc, "dining_table", (1.6, -1.0), (1.2, 0.8), 0.75, wood, dark)
    chair = _mesh_asset(doc, folder, "chair", meshes.toy_chair(), [4.0, 4.0, 7.0])
    _chair_mesh_body(doc, "chair_a", chair, [1.6, -1.65, 0.0], np.pi / 2, "wood")
    _chair_mesh_body(doc, "chair_b", chair, [1.6, -0.35, 0.0], -np.pi / 2, "wood")
    lamp = _mesh_asset(doc, folder, "floor_lamp", meshes.lamp(), [6.0, 6.0, 7.5])
    _chair_mesh_body(doc, "floor_lamp", lamp, [-2.4, -2.0, 0.0], 0.7, "dark")
    blob = _mesh_asset(doc, folder, "plant_blob", meshes.blob(seed=11), [3.5, 3.5, 5.0])
    doc.cylinder("plant_pot", [-2.5, 2.1, 0.2], 0.2, 0.4, "wood")
    _chair_mesh_body(doc, "plant", blob, [-2.5, 2.1, 0.4], 0.0, plant)


def _office(doc: _Mjcf, folder: Path) -> None:
    _room_shell(doc, folder, ("checker", (205, 210, 215), (225, 228, 232)))
    desk = doc.material(
        folder, "desk", "noise", (190, 170, 140), (220, 205, 180), repeat=(4, 4), seed=6
    )
    dark = doc.material(folder, "dark", "noise", (30, 30, 35), (70, 70, 80), repeat=(4, 4), seed=2)
    grey = doc.material(folder, "grey", "stripes", (120, 125, 135), (150, 155, 165), repeat=(6, 6))
    board = doc.material(folder, "board", "dots", (245, 245, 245), (40, 60, 160), repeat=(4, 2))
    plant = doc.material(folder, "plant", "noise", (40, 110, 40), (120, 180, 80), seed=4)
    chair = _mesh_asset(doc, folder, "chair", meshes.toy_chair(), [4.0, 4.0, 7.0])
    # Three desks with monitors and chairs in a row along the south wall.
    for i, x in enumerate([-1.8, 0.0, 1.8]):
        _table4(doc, f"desk{i}", (x, -1.9), (1.4, 0.7), 0.74, desk, dark)
        doc.box(f"monitor{i}", [x, -2.05, 1.05], [0.6, 0.04, 0.36], dark)
        doc.box(f"monitor_stand{i}", [x, -2.05, 0.8], [0.08, 0.08, 0.14], dark)
        _chair_mesh_body(
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
    _table4(doc, "meeting_table", (0.0, 0.6), (2.0, 1.0), 0.74, desk, dark)
    for i, x in enumerate([-1.0, 1.0]):
        _chair_mesh_body(doc, f"meeting_chair{i}", chair, [x, 1.35, 0.0], np.pi / 2, "grey")
    for i, y in enumerate([-0.2, 0.35, 0.9]):
        doc.box(f"cabinet{i}", [2.7, y, 0.65], [0.5, 0.5, 1.3], grey)
    doc.box("whiteboard", [-2.93, 0.5, 1.4], [0.03, 1.8, 1.0], board)
    # A storage corner behind a tall bookcase (occluded from most of the room).
    doc.box("bookcase", [-1.6, 1.5, 0.95], [1.6, 0.4, 1.9], desk)
    doc.box("boxes_behind", [-2.3, 2.1, 0.3], [0.6, 0.5, 0.6], dark)
    doc.box("printer", [-1.3, 2.15, 0.4], [0.6, 0.5, 0.8], grey)
    blob = _mesh_asset(doc, folder, "plant_blob", meshes.blob(seed=12), [3.0, 3.0, 5.0])
    doc.cylinder("plant_pot", [2.6, 2.1, 0.2], 0.2, 0.4, desk)
    _chair_mesh_body(doc, "plant", blob, [2.6, 2.1, 0.4], 0.0, plant)


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
    _FOLDER[name] = folder
    doc = _Mjcf(name)
    {"living_room": _living_room, "office": _office}[name](doc, folder)
    (folder / "scene.xml").write_text(doc.xml(_lights_room()))
    hx, hy = ROOM_HALF
    scene = _placeholder(name, "room", folder)
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


def write_preview(scene: Scene, size: tuple[int, int] = (320, 240)) -> None:
    """Render an overview (the held-out view that sees furthest) to `preview.png` beside the scene."""
    from PIL import Image

    from sim_bridge.render import RgbdRenderer

    with RgbdRenderer(scene) as renderer:
        frames = [renderer.render(T) for T in scene.eval_views]
    score = [
        np.nanmedian(d) * np.isfinite(d).mean() if scene.level == "room" else T[2, 3]
        for (_, d), T in zip(frames, scene.eval_views, strict=True)
    ]
    rgb = frames[int(np.argmax(score))][0]
    Image.fromarray(rgb).resize(size, Image.Resampling.LANCZOS).save(
        scene.mjcf_path.parent / "preview.png", optimize=True
    )


def build_scene(name: str) -> Scene:
    """Regenerate one bundled scene's files (and its preview picture) and return it."""
    if name in OBJECT_SCENES:
        scene = build_object_scene(name)
    elif name in ROOM_SCENES:
        scene = build_room_scene(name)
    else:
        raise ValueError(f"name: got {name!r}, expected one of {[*OBJECT_SCENES, *ROOM_SCENES]}")
    write_preview(scene)
    return scene


def main(argv: list[str] | None = None) -> None:
    names = (sys.argv[1:] if argv is None else argv) or [*OBJECT_SCENES, *ROOM_SCENES]
    for name in names:
        scene = build_scene(name)
        print(
            f"{name}: {scene.mjcf_path}  {len(scene.initial_views)} initial, {len(scene.eval_views)} eval views"
        )


if __name__ == "__main__":
    main()
