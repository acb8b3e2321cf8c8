"""Generated hold-out scenes: kinds of scene that no parameter of the project was tuned on.

Each writer puts one MJCF file, its textures and its meshes into a folder of its own and writes no
sidecar JSON, so `load_scene(path)` derives the scene's level, ROI, workspace and views from the
geometry (`sim_bridge.scenes.derive_scene`), as it would for a user's model. A seed changes the
layout, the textures and the lighting direction. Placement is physics-free: every object stands on
its support at a sampled position and yaw, apart from every other object.

    python -m sim_bridge.holdout_scenes OUT_DIR [SEED ...]   # every kind, seeds 0 and 1 by default
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path

import numpy as np

from sim_bridge import meshes
from sim_bridge.holdout_parts import (
    bottle_mesh,
    lights,
    place_apart,
    scene_folder,
    seeded_rng,
)
from sim_bridge.holdout_scanned import write_scanned_counter
from sim_bridge.holdout_shelf import write_shelf_wall
from sim_bridge.holdout_thin import write_thin_objects
from sim_bridge.mjcf import Mjcf, floor_plane, mesh_asset, mesh_body, room_shell, table4

# Tabletop: a 1.2 x 0.8 m table (the bundled tabletops use 0.9 x 0.6 m) at a standard height.
TABLE_TOP_SIZE = (1.2, 0.8)
TABLE_HEIGHT = 0.75
CUPBOARD_SIZE = (0.36, 0.26, 0.30)  # width (x), depth (y), height; open towards +y
PANEL = 0.015  # cupboard panel thickness, metres
TABLE_EDGE_KEEPOUT = 0.08  # objects stay this far in from the table edge
# Room: a 5 x 4 m interior (the bundled rooms are 6 x 5 m) with an alcove behind a partition.
ROOM_HALF = (2.5, 2.0)
PARTITION_HEIGHT = 2.0
ALCOVE_DEPTH = 1.3  # metres from the side wall to the partition
ALCOVE_OPENING = 1.1  # metres of gap between the partition's end and the end wall


def write_tabletop(folder: Path, seed: int = 0) -> Path:
    """Write a tabletop scene into `folder` and return its MJCF path (`tabletop_s{seed}.xml`).

    A 1.2 x 0.8 m table on legs on a floor plane; on it an open cupboard (box panels, open towards
    +y) with two small objects inside, plus a box, a mug and a bottle on the table top.
    """
    rng = seeded_rng(seed)
    folder = scene_folder(folder)
    name = f"tabletop_s{seed}"
    doc = Mjcf(name)
    pick = rng.permutation(4)
    palette = [
        ("checker", (40, 90, 170), (220, 220, 230)),
        ("stripes", (200, 60, 50), (240, 200, 170)),
        ("dots", (230, 190, 40), (90, 50, 20)),
        ("noise", (60, 140, 70), (200, 230, 150)),
    ]
    floor = doc.material(folder, "floor", "checker", (90, 90, 95), (150, 150, 155), repeat=(2, 2))
    wood = doc.material(folder, "wood", "stripes", (120, 80, 45), (170, 120, 70), repeat=(4, 4))
    metal = doc.material(folder, "metal", "noise", (80, 80, 85), (140, 140, 150), seed=3)
    panel = doc.material(folder, "panel", "noise", (200, 190, 170), (235, 225, 205), seed=seed)
    mats = [doc.material(folder, f"tex{i}", *palette[k], seed=seed + i) for i, k in enumerate(pick)]
    table4(doc, "table", (0.0, 0.0), TABLE_TOP_SIZE, TABLE_HEIGHT, wood, metal)
    top = TABLE_HEIGHT
    half = np.array(TABLE_TOP_SIZE) / 2 - TABLE_EDGE_KEEPOUT
    # The cupboard at one end of the table, its open side facing +y.
    w, d, h = CUPBOARD_SIZE
    side = rng.choice([-1.0, 1.0])
    cx = side * (half[0] - w / 2 - rng.uniform(0.0, 0.08))
    cy = rng.uniform(-0.1, 0.05)
    t = PANEL
    doc.box("cupboard_bottom", [cx, cy, top + t / 2], [w, d, t], panel)
    doc.box("cupboard_top", [cx, cy, top + h - t / 2], [w, d, t], panel)
    for i, sx in enumerate((-1, 1)):
        doc.box(f"cupboard_side{i}", [cx + sx * (w - t) / 2, cy, top + h / 2], [t, d, h], panel)
    doc.box("cupboard_back", [cx, cy - (d - t) / 2, top + h / 2], [w - 2 * t, t, h], panel)
    # Two small objects inside it, on its bottom panel.
    inner = top + t
    doc.box("hidden_box", [cx - w / 4 + 0.01, cy, inner + 0.03], [0.06, 0.06, 0.06], mats[0])
    blob = mesh_asset(
        doc, folder, "hidden_blob", meshes.blob(radius=0.035, seed=seed + 5), [1, 1, 1]
    )
    mesh_body(doc, "hidden_blob", blob, [cx + w / 4 - 0.01, cy + 0.02, inner], 0.0, mats[1])
    # A box, a mug and a bottle on the free part of the table top.
    keepout = [(np.array([cx - w / 2, cy - d / 2]), np.array([cx + w / 2, cy + d / 2 + 0.1]))]
    box_size = np.array([rng.uniform(0.08, 0.14), rng.uniform(0.06, 0.1), rng.uniform(0.06, 0.12)])
    radii = np.array([np.linalg.norm(box_size[:2]) / 2, 0.06, 0.04])
    where = place_apart(rng, radii, -half, half, keepout)
    doc.box("box", [*where[0], top + box_size[2] / 2], box_size, mats[2])
    mug = mesh_asset(doc, folder, "mug", meshes.mug(), [1, 1, 1])
    mesh_body(doc, "mug", mug, [*where[1], top], rng.uniform(-np.pi, np.pi), mats[3])
    bottle = mesh_asset(doc, folder, "bottle", bottle_mesh(), [1, 1, 1])
    mesh_body(doc, "bottle", bottle, [*where[2], top], 0.0, mats[1])
    return doc.write(folder / f"{name}.xml", lights(rng), floor_plane(floor))


def write_alcove_room(folder: Path, seed: int = 0) -> Path:
    """Write a furnished room into `folder` and return its MJCF path (`alcove_room_s{seed}.xml`).

    A 5 x 4 m room (floor slab, four 2.6 m walls with a doorway, no ceiling, like the bundled
    rooms) with a bookshelf, a table with chairs, and an alcove behind a partition wall at one end
    (a cabinet, a box and a plant in it) that only views near its opening or inside it can see.
    """
    rng = seeded_rng(seed)
    folder = scene_folder(folder)
    name = f"alcove_room_s{seed}"
    doc = Mjcf(name)
    hx, hy = ROOM_HALF
    room_shell(doc, folder, ("noise", (210, 205, 190), (235, 230, 220)), half=ROOM_HALF)
    wood = doc.material(folder, "wood", "stripes", (110, 70, 40), (160, 115, 70), repeat=(4, 4))
    dark = doc.material(folder, "dark", "noise", (25, 25, 30), (60, 60, 70), repeat=(4, 4), seed=2)
    books = doc.material(folder, "books", "stripes", (200, 60, 40), (40, 90, 160), repeat=(5, 1))
    plant = doc.material(folder, "plant", "noise", (40, 110, 40), (120, 180, 80), seed=4)
    grey = doc.material(folder, "grey", "checker", (120, 125, 135), (170, 175, 185), seed=seed)
    # The alcove at the east or west end, its opening at the north or south end of the partition.
    ex = rng.choice([-1.0, 1.0])  # side of the alcove
    ny = rng.choice([-1.0, 1.0])  # end of the partition that is open
    px = ex * (hx - ALCOVE_DEPTH)
    length = 2 * hy - ALCOVE_OPENING
    doc.box(
        "partition",
        [px, -ny * (hy - length / 2), PARTITION_HEIGHT / 2],
        [0.1, length, PARTITION_HEIGHT],
        dark,
    )
    ax = ex * (hx - ALCOVE_DEPTH / 2)  # middle of the alcove
    doc.box("alcove_cabinet", [ex * (hx - 0.3), -ny * 0.9, 0.45], [0.5, 0.8, 0.9], wood)
    doc.box("alcove_box", [ax, -ny * (hy - 0.35), 0.25], [0.45, 0.45, 0.5], grey)
    blob = mesh_asset(doc, folder, "plant_blob", meshes.blob(seed=20 + seed), [3.5, 3.5, 5.0])
    doc.cylinder("plant_pot", [ax - ex * 0.2, ny * 0.1, 0.2], 0.2, 0.4, wood)
    mesh_body(doc, "plant", blob, [ax - ex * 0.2, ny * 0.1, 0.4], 0.0, plant)
    # A bookshelf against the wall opposite the alcove.
    sx = -ex * (hx - 0.2)
    sy = rng.uniform(-0.8, 0.4)
    for i, z in enumerate([0.02, 0.5, 1.0, 1.5, 1.98]):
        doc.box(f"shelf{i}", [sx, sy + 0.6, z], [0.35, 1.2, 0.03], wood)
    doc.box("shelf_side_a", [sx, sy, 1.0], [0.35, 0.03, 2.0], wood)
    doc.box("shelf_side_b", [sx, sy + 1.2, 1.0], [0.35, 0.03, 2.0], wood)
    for i, z in enumerate([0.26, 0.76, 1.26]):
        doc.box(f"books{i}", [sx - ex * 0.02, sy + 0.45 + 0.1 * i, z], [0.25, 0.7, 0.42], books)
    # A table with two chairs in the open part of the room.
    tx = -ex * rng.uniform(0.2, 0.6)
    ty = rng.uniform(-0.6, 0.6)
    table4(doc, "table", (tx, ty), (1.2, 0.8), 0.75, wood, dark)
    chair = mesh_asset(doc, folder, "chair", meshes.toy_chair(), [4.0, 4.0, 7.0])
    mesh_body(doc, "chair_a", chair, [tx, ty - 0.65, 0.0], np.pi / 2, "grey")
    mesh_body(doc, "chair_b", chair, [tx, ty + 0.65, 0.0], -np.pi / 2, "grey")
    path = folder / f"{name}.xml"
    path.write_text(doc.xml(lights(rng)))
    return path


HOLDOUT_WRITERS: dict[str, Callable[[Path, int], Path]] = {
    "tabletop": write_tabletop,
    "alcove_room": write_alcove_room,
    "shelf_wall": write_shelf_wall,
    "thin_objects": write_thin_objects,
    "scanned_counter": write_scanned_counter,
}


def write_holdout_scene(kind: str, folder: Path, seed: int = 0) -> Path:
    """Write the hold-out scene `kind` (a key of HOLDOUT_WRITERS: "tabletop", "alcove_room",
    "shelf_wall", "thin_objects", "scanned_counter") with `seed` into `folder` (one scene per folder: the scenes share
    asset names) and return its MJCF path."""
    if kind not in HOLDOUT_WRITERS:
        raise ValueError(f"kind: got {kind!r}, expected one of {list(HOLDOUT_WRITERS)}")
    return HOLDOUT_WRITERS[kind](Path(folder), seed)


def write_holdout_scenes(out_dir: Path, seeds: tuple[int, ...] = (0, 1)) -> list[Path]:
    """Every kind with every seed, each in `out_dir/<kind>_s<seed>/`; returns the MJCF paths."""
    return [
        write_holdout_scene(kind, Path(out_dir) / f"{kind}_s{seed}", seed)
        for kind in HOLDOUT_WRITERS
        for seed in seeds
    ]


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        prog="python -m sim_bridge.holdout_scenes",
        description="Write the hold-out scenes of every kind, one folder per kind and seed.",
    )
    parser.add_argument("out_dir", type=Path, help="folder to write the scenes into")
    parser.add_argument("seeds", type=int, nargs="*", default=[0, 1], help="seeds (default: 0 1)")
    args = parser.parse_args(argv)
    for path in write_holdout_scenes(args.out_dir, tuple(args.seeds)):
        print(path)


if __name__ == "__main__":
    main()
