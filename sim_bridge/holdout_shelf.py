"""Hold-out scene `shelf_wall`: a bookcase against a wall (for even seeds in a corner with a
kitchen cabinet), books and objects on its boards, some set back behind taller ones."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

from sim_bridge import meshes
from sim_bridge.holdout_parts import (
    OBJECT_GAP,
    bottle_mesh,
    lights,
    place_apart,
    scene_folder,
    seeded_rng,
    turn_all,
)
from sim_bridge.mjcf import Mjcf, floor_plane, mesh_asset, mesh_body

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
        bottle_mesh,
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
        mesh_body(
            doc,
            label,
            mesh_asset(doc, folder, label, mesh, [1, 1, 1]),
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
    rng = seeded_rng(seed)
    folder = scene_folder(folder)
    name = f"shelf_wall_s{seed}"
    doc = Mjcf(name)
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
                where = place_apart(rng, np.array([r for *_, r in shapes]), lo[:2], hi[:2], keepout)
                break
            except RuntimeError:  # no room for all: leave one out
                shapes.pop()
        for (mesh, scale, _), xy in zip(shapes, where if shapes else [], strict=True):
            asset = mesh_asset(doc, folder, f"item{count}", mesh, [scale] * 3)
            yaw = rng.uniform(-np.pi, np.pi)
            mesh_body(doc, f"item{count}", asset, [*xy, lo[2]], yaw, mats[count % 6])
            count += 1
    if not corner:  # a storage box on the floor beside the bookcase
        size = np.array([rng.uniform(0.3, 0.45), rng.uniform(0.25, 0.35), rng.uniform(0.2, 0.35)])
        bx = shelf_x + rng.choice([-1.0, 1.0]) * (width / 2 + rng.uniform(0.1, 0.3) + size[0] / 2)
        by = -0.02 - size[1] / 2 - rng.uniform(0.0, 0.2)
        doc.box("floor_box", [bx, by, size[2] / 2], size, mats[2])
    turn_all(doc, float(rng.integers(4)) * np.pi / 2)
    return doc.write(folder / f"{name}.xml", lights(rng), floor_plane(floor))
