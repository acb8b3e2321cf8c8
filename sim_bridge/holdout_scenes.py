"""Generated hold-out scenes: kinds of scene that no parameter of the project was tuned on.

Each writer puts one MJCF file, its textures and its meshes into a folder of its own and writes no
sidecar JSON, so `load_scene(path)` derives the scene's level, ROI, workspace and views from the
geometry (`sim_bridge.scenes.derive_scene`), as it would for a user's model. A seed changes the
layout, the textures and the lighting direction. Placement is physics-free: every object stands on
its support at a sampled position and yaw, apart from every other object.

    python -m sim_bridge.holdout_scenes OUT_DIR [SEED ...]   # every kind, seeds 0 and 1 by default
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
import trimesh

from sim_bridge import meshes
from sim_bridge.build_scenes import _chair_mesh_body, _mesh_asset, _Mjcf, _room_shell, _table4

# Tabletop: a 1.2 x 0.8 m table (the bundled tabletops use 0.9 x 0.6 m) at a standard height.
TABLE_TOP_SIZE = (1.2, 0.8)
TABLE_HEIGHT = 0.75
CUPBOARD_SIZE = (0.36, 0.26, 0.30)  # width (x), depth (y), height; open towards +y
PANEL = 0.015  # cupboard panel thickness, metres
TABLE_EDGE_KEEPOUT = 0.08  # objects stay this far in from the table edge
OBJECT_GAP = 0.04  # metres between the footprints of neighbouring objects
# Room: a 5 x 4 m interior (the bundled rooms are 6 x 5 m) with an alcove behind a partition.
ROOM_HALF = (2.5, 2.0)
PARTITION_HEIGHT = 2.0
ALCOVE_DEPTH = 1.3  # metres from the side wall to the partition
ALCOVE_OPENING = 1.1  # metres of gap between the partition's end and the end wall
# Shelf against a wall: a bookcase of common sizes (metres) standing on the floor against a 2.4 m
# wall; for even seeds a second wall makes a corner, with a kitchen-height cabinet in it.
WALL_HEIGHT = 2.4
WALL_THICK = 0.1
SHELF_WIDTH = (0.8, 1.1)
SHELF_DEPTH = (0.28, 0.38)
SHELF_HEIGHT = (1.2, 1.8)
BOARD = 0.02  # shelf board and side panel thickness
SHELF_CLEAR = 0.26  # least free height between two boards
CABINET_WIDTH = (0.55, 0.8)
CABINET_DEPTH = 0.55
CABINET_HEIGHT = 0.88  # worktop height (a kitchen counter)
# Thin and textureless objects on a floor: a stool with thin splayed legs, a floor lamp (a thin
# pole, a plain lamp shade), a wire rack, a glossy bowl, and one large plain surface (a cabinet, a
# screen or a low table's top), all within this area (x, y) of the floor.
THIN_AREA = (1.8, 1.3)


def _rng(seed: int) -> np.random.Generator:
    if not isinstance(seed, int | np.integer) or seed < 0:
        raise ValueError(f"seed: got {seed!r}, expected a non-negative integer")
    return np.random.default_rng(int(seed))


def _lights(rng: np.random.Generator, specular: float = 0.1) -> list[str]:
    """Two directional lights (a key light from a seeded direction above, with `specular`, a
    weaker fill light from the other side), no shadows; the model's headlight adds only its
    ambient term when rendered."""
    az = rng.uniform(0, 2 * np.pi)
    key = np.array([np.cos(az), np.sin(az), -1.6])
    fill = np.array([-np.cos(az + 0.6), -np.sin(az + 0.6), -0.8])
    return [
        f'<light name="key" directional="true" pos="0 0 4" dir="{_v3(key)}" diffuse="0.55 0.55 0.55" specular="{specular} {specular} {specular}" castshadow="false"/>',
        f'<light name="fill" directional="true" pos="0 0 4" dir="{_v3(fill)}" diffuse="0.25 0.25 0.25" specular="0 0 0" castshadow="false"/>',
    ]


def _v3(x) -> str:
    return " ".join(f"{float(a):.4f}" for a in x)


def _place(
    rng: np.random.Generator, radii: np.ndarray, lo: np.ndarray, hi: np.ndarray, keepout: list
) -> np.ndarray:
    """(N, 2) positions in the box [lo, hi] for discs of `radii` (N,) that overlap neither each other
    nor the keep-out boxes [(lo (2,), hi (2,)), ...] (rejection sampling, 200 tries each)."""
    out = []
    for r in radii:
        tries = rng.uniform(lo + r, hi - r, (200, 2))
        ok = np.ones(len(tries), dtype=bool)
        for k_lo, k_hi in keepout:
            nearest = np.clip(tries, k_lo, k_hi)
            ok &= np.linalg.norm(tries - nearest, axis=1) > r + OBJECT_GAP
        for p, q in out:
            ok &= np.linalg.norm(tries - p, axis=1) > r + q + OBJECT_GAP
        if not ok.any():
            raise RuntimeError(f"no free place for an object of radius {r:.3f} m")
        out.append((tries[np.argmax(ok)], r))
    return np.array([p for p, _ in out])


def _plain(doc: _Mjcf, name: str, rgb, specular=0.1, shininess=0.3, reflectance=0.0) -> str:
    """A material of one uniform colour with no texture (nothing for stereo to match on)."""
    if name not in doc.textures:
        rgba = " ".join(f"{c / 255:.3f}" for c in rgb) + " 1"
        doc.assets.append(
            f'<material name="{name}" rgba="{rgba}" specular="{specular}" '
            f'shininess="{shininess}" reflectance="{reflectance}"/>'
        )
        doc.textures.add(name)
    return name


def _turned(doc: _Mjcf, yaw: float) -> None:
    """Put everything in `doc` so far into one body turned by `yaw` (radians) about z."""
    doc.bodies = [f'<body name="turned" euler="0 0 {yaw:.6f}">', *doc.bodies, "</body>"]


def _bottle():
    """A closed wine-bottle-like surface of revolution (body, shoulder, neck), 0.26 m tall."""
    z = np.array([0.0, 0.0, 0.17, 0.2, 0.215, 0.25, 0.26, 0.26])
    r = np.array([0.0, 0.035, 0.035, 0.022, 0.013, 0.013, 0.014, 0.0])
    return meshes._merge([meshes.revolve(np.stack([r, z], 1), sections=24)])


def write_tabletop(folder: Path, seed: int = 0) -> Path:
    """Write a tabletop scene into `folder` and return its MJCF path (`tabletop_s{seed}.xml`).

    A 1.2 x 0.8 m table on legs on a floor plane; on it an open cupboard (box panels, open towards
    +y) with two small objects inside, plus a box, a mug and a bottle on the table top.
    """
    rng = _rng(seed)
    folder = _folder(folder)
    name = f"tabletop_s{seed}"
    doc = _Mjcf(name)
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
    _table4(doc, "table", (0.0, 0.0), TABLE_TOP_SIZE, TABLE_HEIGHT, wood, metal)
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
    blob = _mesh_asset(
        doc, folder, "hidden_blob", meshes.blob(radius=0.035, seed=seed + 5), [1, 1, 1]
    )
    _chair_mesh_body(doc, "hidden_blob", blob, [cx + w / 4 - 0.01, cy + 0.02, inner], 0.0, mats[1])
    # A box, a mug and a bottle on the free part of the table top.
    keepout = [(np.array([cx - w / 2, cy - d / 2]), np.array([cx + w / 2, cy + d / 2 + 0.1]))]
    box_size = np.array([rng.uniform(0.08, 0.14), rng.uniform(0.06, 0.1), rng.uniform(0.06, 0.12)])
    radii = np.array([np.linalg.norm(box_size[:2]) / 2, 0.06, 0.04])
    where = _place(rng, radii, -half, half, keepout)
    doc.box("box", [*where[0], top + box_size[2] / 2], box_size, mats[2])
    mug = _mesh_asset(doc, folder, "mug", meshes.mug(), [1, 1, 1])
    _chair_mesh_body(doc, "mug", mug, [*where[1], top], rng.uniform(-np.pi, np.pi), mats[3])
    bottle = _mesh_asset(doc, folder, "bottle", _bottle(), [1, 1, 1])
    _chair_mesh_body(doc, "bottle", bottle, [*where[2], top], 0.0, mats[1])
    path = folder / f"{name}.xml"
    path.write_text(
        doc.xml(
            _lights(rng), f'<geom name="floor" type="plane" size="0 0 0.05" material="{floor}"/>'
        )
    )
    return path


def write_alcove_room(folder: Path, seed: int = 0) -> Path:
    """Write a furnished room into `folder` and return its MJCF path (`alcove_room_s{seed}.xml`).

    A 5 x 4 m room (floor slab, four 2.6 m walls with a doorway, no ceiling, like the bundled
    rooms) with a bookshelf, a table with chairs, and an alcove behind a partition wall at one end
    (a cabinet, a box and a plant in it) that only views near its opening or inside it can see.
    """
    rng = _rng(seed)
    folder = _folder(folder)
    name = f"alcove_room_s{seed}"
    doc = _Mjcf(name)
    hx, hy = ROOM_HALF
    _room_shell(doc, folder, ("noise", (210, 205, 190), (235, 230, 220)), half=ROOM_HALF)
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
    blob = _mesh_asset(doc, folder, "plant_blob", meshes.blob(seed=20 + seed), [3.5, 3.5, 5.0])
    doc.cylinder("plant_pot", [ax - ex * 0.2, ny * 0.1, 0.2], 0.2, 0.4, wood)
    _chair_mesh_body(doc, "plant", blob, [ax - ex * 0.2, ny * 0.1, 0.4], 0.0, plant)
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
    _table4(doc, "table", (tx, ty), (1.2, 0.8), 0.75, wood, dark)
    chair = _mesh_asset(doc, folder, "chair", meshes.toy_chair(), [4.0, 4.0, 7.0])
    _chair_mesh_body(doc, "chair_a", chair, [tx, ty - 0.65, 0.0], np.pi / 2, "grey")
    _chair_mesh_body(doc, "chair_b", chair, [tx, ty + 0.65, 0.0], -np.pi / 2, "grey")
    path = folder / f"{name}.xml"
    path.write_text(doc.xml(_lights(rng)))
    return path


def _shelf_object(rng: np.random.Generator, k: int) -> trimesh.Trimesh:
    """The k-th kind of thing found on a bookcase (mug, bowl, vase, lumpy body, knot, L-block,
    tunnel block, bottle), sized by `rng`."""
    kinds = [
        meshes.mug,
        meshes.bowl,
        lambda: meshes.vase(radius=rng.uniform(0.03, 0.045), height=rng.uniform(0.14, 0.22)),
        lambda: meshes.blob(radius=rng.uniform(0.04, 0.06), seed=int(rng.integers(1000))),
        meshes.torus_knot,
        meshes.l_shape,
        meshes.tunnel_block,
        _bottle,
    ]
    return kinds[k % len(kinds)]()


def _shelf_corner(doc, folder: Path, rng, wall_len: float, width: float, materials, areas: list):
    """The corner of `write_shelf_wall`: a side wall, a kitchen-height cabinet with its worktop (a
    free area appended to `areas`); `materials` = (wall, wood); returns the bookcase's x beside
    the cabinet."""
    wall, wood = materials
    t = WALL_THICK
    sx = rng.choice([-1.0, 1.0])  # the side of the corner
    side_len = rng.uniform(1.6, 2.2)
    doc.box(
        "wall_side",
        [sx * (wall_len + t) / 2, (t - side_len) / 2, WALL_HEIGHT / 2],
        [t, side_len + t, WALL_HEIGHT],
        wall,
    )
    cab_w = rng.uniform(*CABINET_WIDTH)
    cab_x, cab_y = sx * (wall_len / 2 - 0.005 - cab_w / 2), -0.005 - CABINET_DEPTH / 2
    body = doc.material(folder, "cabinet", "noise", (225, 222, 212), (245, 243, 236), seed=9)
    doc.box(
        "cabinet",
        [cab_x, cab_y, (CABINET_HEIGHT - 0.03) / 2],
        [cab_w, CABINET_DEPTH, CABINET_HEIGHT - 0.03],
        body,
    )
    doc.box(
        "worktop",
        [cab_x, cab_y - 0.015, CABINET_HEIGHT - 0.015],
        [cab_w, CABINET_DEPTH + 0.03, 0.03],
        wood,
    )
    areas.append(
        [
            np.array([cab_x - cab_w / 2 + 0.04, cab_y - CABINET_DEPTH / 2, CABINET_HEIGHT]),
            np.array([cab_x + cab_w / 2 - 0.04, -0.04, CABINET_HEIGHT + 0.3]),
            [],
        ]
    )
    return cab_x - sx * (cab_w / 2 + rng.uniform(0.05, 0.25) + width / 2)


def _bookcase(doc, rng, shelf_x, width, depth, height, wood: str, areas: list) -> np.ndarray:
    """The bookcase of `write_shelf_wall`: side panels, back board, boards (each a free area
    appended to `areas`); returns the boards' heights."""
    # The bookcase: side panels, a back board 1 cm off the wall, boards from 8 cm up to the top.
    back_y = -0.01
    front_y = back_y - depth
    for i, x in enumerate((shelf_x - (width - BOARD) / 2, shelf_x + (width - BOARD) / 2)):
        doc.box(
            f"shelf_side{i}", [x, (back_y + front_y) / 2, height / 2], [BOARD, depth, height], wood
        )
    inner = width - 2 * BOARD
    doc.box("shelf_back", [shelf_x, back_y - 0.006, height / 2], [inner, 0.012, height], wood)
    most = min(5, 1 + int((height - 0.08) // (SHELF_CLEAR + BOARD)))
    tops = np.linspace(0.08, height, int(rng.integers(3, most + 1)))
    for i, z in enumerate(tops):
        doc.box(
            f"shelf_board{i}",
            [shelf_x, (back_y - 0.012 + front_y) / 2, z - BOARD / 2],
            [inner, depth - 0.012, BOARD],
            wood,
        )
        clear = tops[i + 1] - BOARD - z if i + 1 < len(tops) else 0.3
        x_lo, x_hi = shelf_x - inner / 2 + 0.02, shelf_x + inner / 2 - 0.02
        areas.append([np.array([x_lo, front_y, z]), np.array([x_hi, back_y - 0.02, z + clear]), []])
    return tops


def _books_and_pair(doc, folder: Path, rng, seed: int, shelves: list, pair: int, mats, books):
    """Rows of books on some boards, and on board `pair` a small object set back behind a taller
    one (each placed object a keep-out of its board)."""
    for i, (lo, hi, keepout) in enumerate(shelves):
        if i == pair or rng.random() < 0.35:
            continue
        x = rng.uniform(lo[0], hi[0] - 0.3)
        x0 = x
        for j in range(int(rng.integers(4, 9))):
            w, d = rng.uniform(0.02, 0.045), rng.uniform(0.14, 0.2)
            h = min(hi[2] - lo[2] - 0.02, rng.uniform(0.17, 0.25))
            material = mats[j % len(mats)] if j % 3 == 0 else books
            doc.box(f"book{i}_{j}", [x + w / 2, hi[1] - d / 2, lo[2] + h / 2], [w, d, h], material)
            x += w + 0.002
        keepout.append((np.array([x0, hi[1] - 0.2]), np.array([x, hi[1]])))
    # On one board, a small object set back behind a taller one standing in front of it.
    lo, hi, keepout = shelves[pair]
    small = meshes.blob(radius=rng.uniform(0.035, 0.045), seed=seed + 11)
    tall = meshes.vase(radius=0.045, height=min(0.22, 0.85 * (hi[2] - lo[2])))
    r_small, r_tall = (float(np.linalg.norm(m.extents[:2])) / 2 for m in (small, tall))
    px = rng.uniform(lo[0] + 0.1, hi[0] - 0.1)
    back = np.array([px, hi[1] - r_small])
    front = np.array([px + rng.uniform(-0.03, 0.03), back[1] - r_small - OBJECT_GAP - r_tall])
    for label, mesh, xy, r in (
        ("set_back", small, back, r_small),
        ("in_front", tall, front, r_tall),
    ):
        _chair_mesh_body(
            doc,
            label,
            _mesh_asset(doc, folder, label, mesh, [1, 1, 1]),
            [*xy, lo[2]],
            rng.uniform(-np.pi, np.pi),
            mats[len(keepout) % len(mats)],
        )
        keepout.append((xy - r, xy + r))


def write_shelf_wall(folder: Path, seed: int = 0) -> Path:
    """Write a shelf against a wall into `folder` and return its MJCF path (`shelf_wall_s{seed}.xml`).

    A bookcase (3 to 5 boards; rows of books, and objects of which one stands set back behind a
    taller one) stands on a floor plane against a 2.4 m wall. For even seeds a second wall makes a
    corner beside it, with a kitchen-height cabinet in the corner and objects on its worktop; for
    odd seeds a storage box stands on the floor beside the bookcase. The whole set is turned by a
    seeded multiple of 90 degrees, so its open side may face any direction.
    """
    rng = _rng(seed)
    folder = _folder(folder)
    name = f"shelf_wall_s{seed}"
    doc = _Mjcf(name)
    corner = seed % 2 == 0
    palette = [
        ("checker", (40, 90, 170), (220, 220, 230)),
        ("stripes", (200, 60, 50), (240, 200, 170)),
        ("dots", (230, 190, 40), (90, 50, 20)),
        ("noise", (60, 140, 70), (200, 230, 150)),
        ("stripes", (120, 60, 160), (230, 210, 240)),
        ("noise", (160, 110, 60), (240, 220, 190)),
    ]
    mats = [doc.material(folder, f"tex{i}", *c, seed=seed + i) for i, c in enumerate(palette)]
    floor = doc.material(folder, "floor", "stripes", (130, 95, 60), (175, 135, 90), repeat=(3, 3))
    wall = doc.material(
        folder, "wall", "noise", (200, 196, 185), (232, 228, 218), repeat=(3, 3), seed=seed
    )
    wood = doc.material(folder, "wood", "stripes", (120, 80, 45), (170, 120, 70), repeat=(4, 4))
    books = doc.material(folder, "books", "stripes", (170, 50, 40), (40, 80, 150), repeat=(6, 1))
    # The back wall's inner face is the plane y = 0; everything else stands at y < 0.
    wall_len = rng.uniform(2.2, 3.0)
    t = WALL_THICK
    doc.box("wall_back", [0, t / 2, WALL_HEIGHT / 2], [wall_len, t, WALL_HEIGHT], wall)
    width, depth = rng.uniform(*SHELF_WIDTH), rng.uniform(*SHELF_DEPTH)
    height = rng.uniform(*SHELF_HEIGHT)
    # Free areas to put things on: [lo (3,), hi (3,): hi[2] - lo[2] is the free height, keep-outs]
    areas: list[list] = []
    shelf_x = (
        _shelf_corner(doc, folder, rng, wall_len, width, (wall, wood), areas) if corner else None
    )
    if shelf_x is None:
        shelf_x = rng.uniform(-0.3, 0.3)
    tops = _bookcase(doc, rng, shelf_x, width, depth, height, wood, areas)
    shelves = areas[-len(tops) : -1]  # the boards with another above them
    pair = int(rng.integers(len(shelves)))
    _books_and_pair(doc, folder, rng, seed, shelves, pair, mats, books)
    # More objects at sampled places on every board and on the worktop, apart from each other.
    count = 0
    for lo, hi, keepout in areas:
        shapes = []
        for _ in range(int(rng.integers(1, 3 + (hi[0] - lo[0] > 0.7)))):
            mesh = _shelf_object(rng, int(rng.integers(8)))
            scale = min(1.0, 0.85 * (hi[2] - lo[2]) / mesh.extents[2])
            shapes.append((mesh, scale, float(np.linalg.norm(mesh.extents[:2]) / 2 * scale)))
        while shapes:
            try:
                where = _place(rng, np.array([r for *_, r in shapes]), lo[:2], hi[:2], keepout)
                break
            except RuntimeError:  # no room for all: leave one out
                shapes.pop()
        for (mesh, scale, _), xy in zip(shapes, where if shapes else [], strict=True):
            asset = _mesh_asset(doc, folder, f"item{count}", mesh, [scale] * 3)
            yaw = rng.uniform(-np.pi, np.pi)
            _chair_mesh_body(doc, f"item{count}", asset, [*xy, lo[2]], yaw, mats[count % 6])
            count += 1
    if not corner:  # a storage box on the floor beside the bookcase
        size = np.array([rng.uniform(0.3, 0.45), rng.uniform(0.25, 0.35), rng.uniform(0.2, 0.35)])
        bx = shelf_x + rng.choice([-1.0, 1.0]) * (width / 2 + rng.uniform(0.1, 0.3) + size[0] / 2)
        by = -0.02 - size[1] / 2 - rng.uniform(0.0, 0.2)
        doc.box("floor_box", [bx, by, size[2] / 2], size, mats[2])
    _turned(doc, float(rng.integers(4)) * np.pi / 2)
    path = folder / f"{name}.xml"
    path.write_text(
        doc.xml(
            _lights(rng), f'<geom name="floor" type="plane" size="0 0 0.05" material="{floor}"/>'
        )
    )
    return path


def _shade(bottom: float, top: float, height: float) -> trimesh.Trimesh:
    """An open lamp shade: a truncated cone shell 3 mm thick, `bottom` and `top` radii, metres."""
    t = 0.003
    profile = np.array(
        [(bottom, 0.0), (top, height), (top - t, height), (bottom - t, 0.0), (bottom, 0.0)]
    )
    return meshes._merge([meshes.revolve(profile[::-1], sections=32)])


def write_thin_objects(folder: Path, seed: int = 0) -> Path:
    """Write thin and textureless things on a floor into `folder` and return its MJCF path
    (`thin_objects_s{seed}.xml`).

    A stool with thin splayed legs, a floor lamp (a thin pole, a plain lamp shade), a wire rack, a
    glossy bowl (high specular, no texture), and one large plain surface: a standing screen, a
    cabinet or a low table with a plain top, by seed modulo 3 (the bowl stands on the low table,
    else on the stool). Everything stands on a floor plane, placed apart at sampled positions.
    """
    rng = _rng(seed)
    folder = _folder(folder)
    name = f"thin_objects_s{seed}"
    doc = _Mjcf(name)
    floor = doc.material(folder, "floor", "checker", (110, 100, 90), (160, 150, 135), repeat=(3, 3))
    wood = doc.material(folder, "wood", "stripes", (120, 80, 45), (170, 120, 70), repeat=(2, 2))
    metal = _plain(doc, "metal", (60, 60, 65), specular=0.5, shininess=0.6)
    shade = _plain(doc, "shade", rng.uniform(200, 245, 3), specular=0.05)
    glossy = _plain(
        doc, "glossy", rng.uniform(20, 200, 3), specular=1.0, shininess=1.0, reflectance=0.5
    )
    surface = _plain(doc, "plain", rng.uniform(150, 235, 3), specular=0.2)
    large = ("screen", "cabinet", "low_table")[seed % 3]  # seeds 0, 1, 2 show each
    seat_r, seat_z = rng.uniform(0.14, 0.18), rng.uniform(0.45, 0.65)
    splay = seat_r * 0.7 + rng.uniform(0.06, 0.1)  # leg foot radius
    lamp_r = rng.uniform(0.17, 0.22)
    rack = meshes.wire_rack(size=0.12)
    rack_scale = rng.uniform(2.5, 3.2)
    big = {
        "cabinet": np.array(
            [rng.uniform(0.5, 0.75), rng.uniform(0.35, 0.45), rng.uniform(0.5, 0.8)]
        ),
        "screen": np.array([rng.uniform(0.8, 1.0), 0.03, rng.uniform(1.0, 1.3)]),
        "low_table": np.array(
            [rng.uniform(0.7, 0.9), rng.uniform(0.45, 0.55), rng.uniform(0.35, 0.45)]
        ),
    }[large]
    radii = np.array(
        [
            splay + 0.03,
            lamp_r + 0.02,
            np.linalg.norm(rack.extents[:2]) / 2 * rack_scale,
            np.linalg.norm(big[:2]) / 2,
        ]
    )
    half = np.array(THIN_AREA) / 2
    order = np.argsort(-radii)  # the largest first: rejection sampling finds room for it
    where = np.zeros((4, 2))
    for attempt in range(20):  # a few fresh draws when the first ones leave no room
        try:
            where[order] = _place(rng, radii[order], -half, half, [])
            break
        except RuntimeError:
            if attempt == 19:
                raise
    # The stool: a seat on three or four thin legs splayed out to the floor.
    (x, y), legs = where[0], int(rng.integers(3, 5))
    doc.cylinder("stool_seat", [x, y, seat_z - 0.015], seat_r, 0.03, wood)
    for i in range(legs):
        a = 2 * np.pi * i / legs + rng.uniform(0, 0.3)
        top = [x + 0.6 * seat_r * np.cos(a), y + 0.6 * seat_r * np.sin(a), seat_z - 0.03]
        foot = [x + splay * np.cos(a), y + splay * np.sin(a), 0.011]
        doc.bodies.append(
            f'<geom name="stool_leg{i}" type="capsule" fromto="{_v3(top)} {_v3(foot)}" size="0.011" material="{metal}"/>'
        )
    # The floor lamp: a base disc, a thin pole and an open shade at its top.
    (x, y), pole_h = where[1], rng.uniform(1.35, 1.6)
    doc.cylinder("lamp_base", [x, y, 0.0125], rng.uniform(0.12, 0.15), 0.025, metal)
    doc.cylinder("lamp_pole", [x, y, 0.025 + pole_h / 2], rng.uniform(0.008, 0.012), pole_h, metal)
    cone = _mesh_asset(
        doc,
        folder,
        "lamp_shade",
        _shade(lamp_r, lamp_r * rng.uniform(0.55, 0.7), rng.uniform(0.22, 0.28)),
        [1, 1, 1],
    )
    _chair_mesh_body(doc, "lamp_shade", cone, [x, y, 0.025 + pole_h - 0.12], 0.0, shade)
    # The wire rack on the floor.
    asset = _mesh_asset(doc, folder, "wire_rack", rack, [rack_scale] * 3)
    _chair_mesh_body(doc, "wire_rack", asset, [*where[2], 0.0], rng.uniform(-np.pi, np.pi), metal)
    # The large plain surface, and the glossy bowl on the low table or on the stool.
    (x, y), (bx, by, bz) = where[3], big
    bowl = _mesh_asset(
        doc, folder, "bowl", meshes.bowl(radius=rng.uniform(0.08, 0.11), height=0.06), [1, 1, 1]
    )
    bowl_at = [*where[0], seat_z]
    if large == "cabinet":
        doc.box("cabinet", [x, y, bz / 2], big, surface)
    elif large == "screen":
        yaw = rng.uniform(-0.6, 0.6)
        doc.bodies.append(
            f'<body name="screen" pos="{x:.4f} {y:.4f} 0" euler="0 0 {yaw:.4f}">'
            f'<geom name="screen_panel" type="box" pos="0 0 {0.06 + bz / 2:.4f}" size="{bx / 2:.4f} {by / 2:.4f} {bz / 2:.4f}" material="{surface}"/>'
            f'<geom name="screen_foot0" type="box" pos="{-bx / 2 + 0.05:.4f} 0 0.03" size="0.025 0.15 0.03" material="{metal}"/>'
            f'<geom name="screen_foot1" type="box" pos="{bx / 2 - 0.05:.4f} 0 0.03" size="0.025 0.15 0.03" material="{metal}"/>'
            "</body>"
        )
    else:
        doc.box("low_table_top", [x, y, bz - 0.015], [bx, by, 0.03], surface)
        for i, (a, b) in enumerate([(-1, -1), (-1, 1), (1, -1), (1, 1)]):
            doc.cylinder(
                f"low_table_leg{i}",
                [x + a * (bx / 2 - 0.04), y + b * (by / 2 - 0.04), (bz - 0.03) / 2],
                0.012,
                bz - 0.03,
                metal,
            )
        bowl_at = [x + rng.uniform(-0.1, 0.1) * bx, y, bz]
    _chair_mesh_body(doc, "bowl", bowl, bowl_at, 0.0, glossy)
    path = folder / f"{name}.xml"
    path.write_text(
        doc.xml(
            _lights(rng, specular=0.6),
            f'<geom name="floor" type="plane" size="0 0 0.05" material="{floor}"/>',
        )
    )
    return path


HOLDOUT_WRITERS: dict[str, Callable[[Path, int], Path]] = {
    "tabletop": write_tabletop,
    "alcove_room": write_alcove_room,
    "shelf_wall": write_shelf_wall,
    "thin_objects": write_thin_objects,
}


def write_holdout_scene(kind: str, folder: Path, seed: int = 0) -> Path:
    """Write the hold-out scene `kind` (a key of HOLDOUT_WRITERS: "tabletop", "alcove_room",
    "shelf_wall", "thin_objects") with `seed` into `folder` (one scene per folder: the scenes share
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


def _folder(folder: Path) -> Path:
    folder = Path(folder)
    for sidecar in (folder / "scene.json", *folder.glob("*.json")):
        if sidecar.is_file():
            raise ValueError(
                f"folder: got {str(folder)!r}, which holds {sidecar.name}; expected a folder without "
                "a sidecar JSON (load_scene would read it instead of deriving the metadata)"
            )
    folder.mkdir(parents=True, exist_ok=True)
    return folder


def main(argv: list[str] | None = None) -> None:
    args = sys.argv[1:] if argv is None else argv
    if not args:
        raise SystemExit("usage: python -m sim_bridge.holdout_scenes OUT_DIR [SEED ...]")
    seeds = tuple(int(s) for s in args[1:]) or (0, 1)
    for path in write_holdout_scenes(Path(args[0]), seeds):
        print(path)


if __name__ == "__main__":
    main()
