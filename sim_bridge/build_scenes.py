"""Generate the bundled scenes: meshes, textures, physics-settled MJCF and the sidecar metadata.

    python -m sim_bridge.build_scenes            # all scenes
    python -m sim_bridge.build_scenes office     # one scene

Object-level scenes (here) drop their objects onto the table from a few centimetres with small random
poses (fixed seed), step MuJoCo until everything rests and write the settled poses into a static
MJCF (no joints), so loading a scene needs no simulation. The rooms are `build_rooms.py`.
"""

from __future__ import annotations

import sys
from pathlib import Path

import mujoco
import numpy as np

from sim_bridge import meshes
from sim_bridge.build_rooms import ROOM_SCENES, SEED, build_room_scene
from sim_bridge.holdout_parts import place_apart
from sim_bridge.mjcf import Mjcf, blank_scene, floor_plane, vec
from sim_bridge.scanned_objects import add_scanned, footprint, place_scanned
from sim_bridge.scene import Scene
from sim_bridge.scene_layout import ROI_RIM
from sim_bridge.scenes import SCENES_DIR, scene_to_json
from sim_bridge.views import orbit_views

TABLE_TOP_Z = 0.75  # metres, a standard table height
TABLE_SIZE = (0.9, 0.6, 0.03)  # metres, full extents of the table top
SETTLE_SECONDS = 3.0  # simulated time for the drop to come to rest

OBJECT_SCENES: dict[str, list[str]] = {
    "single_object": ["blob"],
    "five_objects": ["mug", "bowl", "vase", "toy_chair", "l_shape"],
    "clutter7_a": ["mug", "blob", "tunnel_block", "torus_knot", "lamp", "wire_rack", "bowl"],
    "clutter7_b": ["vase", "toy_chair", "l_shape", "torus_knot", "blob", "mug", "tunnel_block"],
}

# Tabletops of scanned objects (sim_bridge/scanned/, `scanned_objects.py`).
SCANNED_SCENES: dict[str, list[str]] = {
    "scanned_objects": [
        "003_cracker_box",
        "004_sugar_box",
        "005_tomato_soup_can",
        "006_mustard_bottle",
        "035_power_drill",
    ],
}

PALETTE = [
    ("stripes", (200, 60, 50), (240, 200, 170)),
    ("checker", (40, 90, 170), (220, 220, 230)),
    ("noise", (60, 140, 70), (200, 230, 150)),
    ("dots", (230, 190, 40), (90, 50, 20)),
    ("stripes", (120, 60, 160), (230, 210, 240)),
    ("noise", (160, 110, 60), (240, 220, 190)),
    ("checker", (30, 30, 30), (230, 120, 40)),
]


def _table(doc: Mjcf, folder: Path) -> None:
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
    doc: Mjcf, folder: Path, kinds: list[str], rng
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


def _settle(doc: Mjcf, objects, rng) -> list[tuple[np.ndarray, np.ndarray]]:
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
            f'<body name="{body}" pos="{x:.4f} {y:.4f} {TABLE_TOP_Z + 0.02:.4f}" quat="{vec(quat)}"><freejoint/>'
            f'<inertial pos="{vec(com)}" mass="{mass}" diaginertia="{vec(inertia)}"/>'
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


def _asset_dict(doc: Mjcf) -> dict[str, bytes]:
    folder = _FOLDER[doc.name]
    return {p.name: p.read_bytes() for p in folder.iterdir() if p.suffix in (".obj", ".png")}


def _lights_object() -> list[str]:
    return [
        '<light name="sun" directional="true" pos="0 0 3" dir="0.3 0.4 -1" diffuse="0.5 0.5 0.5" castshadow="false"/>',
    ]


def _fresh_folder(name: str) -> Path:
    """The bundled scene's folder, emptied of the files a build writes."""
    folder = SCENES_DIR / name
    folder.mkdir(parents=True, exist_ok=True)
    for old in folder.iterdir():
        if old.suffix in (".obj", ".png", ".xml", ".json"):
            old.unlink()
    return folder


def build_object_scene(name: str) -> Scene:
    folder = _fresh_folder(name)
    _FOLDER[name] = folder
    rng = np.random.default_rng(SEED + sum(map(ord, name)))
    doc = Mjcf(name)
    floor = doc.material(folder, "floor", "checker", (90, 90, 95), (150, 150, 155), repeat=(2, 2))
    _table(doc, folder)
    objects = _object_assets(doc, folder, OBJECT_SCENES[name], rng)
    poses = _settle(doc, objects, rng)
    for (body, mesh_name, mat, _r, _m), (pos, quat) in zip(objects, poses, strict=True):
        doc.bodies.append(
            f'<body name="{body}" pos="{vec(pos)}" quat="{vec(quat)}"><geom type="mesh" mesh="{mesh_name}" material="{mat}"/></body>'
        )
    doc.write(folder / "scene.xml", _lights_object(), floor_plane(floor))
    return _object_scene_metadata(name, folder)


def build_scanned_scene(name: str) -> Scene:
    """A table with scanned objects (`SCANNED_SCENES[name]`) standing on it at seeded places and
    headings, apart from each other (placed, not dropped: each stands on its flat base)."""
    folder = _fresh_folder(name)
    rng = np.random.default_rng(SEED + sum(map(ord, name)))
    doc = Mjcf(name)
    floor = doc.material(folder, "floor", "checker", (90, 90, 95), (150, 150, 155), repeat=(2, 2))
    _table(doc, folder)
    kinds = sorted(SCANNED_SCENES[name], key=lambda k: -footprint(k).radius)  # largest first
    radii = np.array([footprint(k).radius for k in kinds])
    half = np.array([0.32, 0.22])  # the middle of the table: close enough to hide each other
    where = place_apart(rng, radii, -half, half, [])
    for i, (kind, xy) in enumerate(zip(kinds, where, strict=True)):
        add_scanned(doc, None, kind)
        place_scanned(doc, f"obj{i}", kind, xy, TABLE_TOP_Z, rng.uniform(-np.pi, np.pi))
    doc.write(folder / "scene.xml", _lights_object(), floor_plane(floor))
    return _object_scene_metadata(name, folder)


def _object_scene_metadata(name: str, folder: Path) -> Scene:
    """A tabletop scene's bounds and views from its written geometry; writes `scene.json`."""
    scene = blank_scene(name, "object", folder)
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
    elif name in SCANNED_SCENES:
        scene = build_scanned_scene(name)
    elif name in ROOM_SCENES:
        scene = build_room_scene(name)
    else:
        raise ValueError(
            f"name: got {name!r}, expected one of {[*OBJECT_SCENES, *SCANNED_SCENES, *ROOM_SCENES]}"
        )
    write_preview(scene)
    return scene


def main(argv: list[str] | None = None) -> None:
    names = (sys.argv[1:] if argv is None else argv) or [
        *OBJECT_SCENES,
        *SCANNED_SCENES,
        *ROOM_SCENES,
    ]
    for name in names:
        scene = build_scene(name)
        print(
            f"{name}: {scene.mjcf_path}  {len(scene.initial_views)} initial, {len(scene.eval_views)} eval views"
        )


if __name__ == "__main__":
    main()
