"""Hold-out scene `scanned_counter`: scanned grocery objects and a power drill (YCB scans,
`scanned_objects.py`) on a kitchen counter against a wall, some of them behind others."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from sim_bridge.holdout_parts import lights, place_apart, scene_folder, seeded_rng, turn_all
from sim_bridge.mjcf import Mjcf, floor_plane
from sim_bridge.scanned_objects import SCANNED_OBJECTS, add_scanned, footprint, place_scanned

# A kitchen counter (metres): a cabinet with a worktop at kitchen height against a 2.4 m wall.
WALL_HEIGHT = 2.4
WALL_THICK = 0.1
COUNTER_LENGTH = (1.2, 1.8)
COUNTER_DEPTH = 0.6
COUNTER_HEIGHT = 0.9  # worktop surface
WORKTOP = 0.03  # worktop slab thickness
FRONT_KEEPOUT = 0.06  # objects stay this far from the worktop's front edge and ends
OBJECTS = (4, 6)  # how many of the scans stand on the counter (inclusive range)


def write_scanned_counter(folder: Path, seed: int = 0) -> Path:
    """Write scanned objects on a kitchen counter into `folder` and return its MJCF path
    (`scanned_counter_s{seed}.xml`).

    A counter 1.2-1.8 m long, 0.6 m deep, its worktop at 0.9 m, stands on a floor plane against a
    2.4 m wall; 4 to 6 of the scanned objects (their mesh and texture files copied into
    `folder`) stand on the worktop at seeded places and headings, apart from each other, with a
    cutting board among them. A seed changes the counter's length, which objects stand where,
    the lighting direction and which way the whole set faces (a quarter turn).
    """
    rng = seeded_rng(seed)
    folder = scene_folder(folder)
    name = f"scanned_counter_s{seed}"
    doc = Mjcf(name)
    floor = doc.material(
        folder, "floor", "checker", (150, 140, 125), (185, 175, 160), repeat=(3, 3)
    )
    wall = doc.material(
        folder, "wall", "noise", (205, 200, 190), (235, 232, 224), repeat=(3, 3), seed=seed
    )
    front = doc.material(folder, "cabinet", "noise", (70, 90, 110), (105, 125, 145), seed=seed + 1)
    wood = doc.material(folder, "wood", "stripes", (150, 110, 70), (190, 150, 100), repeat=(4, 2))
    board = doc.material(folder, "board", "stripes", (185, 150, 105), (215, 185, 140), seed=seed)
    length = rng.uniform(*COUNTER_LENGTH)
    t, d, h = WALL_THICK, COUNTER_DEPTH, COUNTER_HEIGHT
    # The wall's inner face is the plane y = 0; the counter stands in front of it (y < 0).
    doc.box("wall_back", [0, t / 2, WALL_HEIGHT / 2], [length + 1.0, t, WALL_HEIGHT], wall)
    doc.box("cabinet", [0, -d / 2, (h - WORKTOP) / 2], [length, d - 0.02, h - WORKTOP], front)
    doc.box("worktop", [0, -d / 2 - 0.01, h - WORKTOP / 2], [length, d + 0.02, WORKTOP], wood)
    count = int(rng.integers(OBJECTS[0], OBJECTS[1] + 1))
    kinds = [str(k) for k in rng.choice(SCANNED_OBJECTS, count, replace=False)]
    bw, bd = rng.uniform(0.16, 0.24), rng.uniform(0.12, 0.16)
    # The cutting board and the objects, the largest first (each finds a place among the placed).
    items = sorted(
        [("cutting_board", np.hypot(bw, bd) / 2)] + [(k, footprint(k).radius) for k in kinds],
        key=lambda item: -item[1],
    )
    lo = np.array([-length / 2 + FRONT_KEEPOUT, -d + FRONT_KEEPOUT])
    hi = np.array([length / 2 - FRONT_KEEPOUT, -0.01])
    where = place_apart(rng, np.array([r for _, r in items]), lo, hi, [])
    for i, ((kind, _), xy) in enumerate(zip(items, where, strict=True)):
        if kind == "cutting_board":
            doc.box(kind, [*xy, h + 0.01], [bw, bd, 0.02], board)
        else:
            add_scanned(doc, folder, kind)
            place_scanned(doc, f"scan{i}_{kind}", kind, xy, h, rng.uniform(-np.pi, np.pi))
    turn_all(doc, float(rng.integers(4)) * np.pi / 2)  # walls stay axis-aligned boxes
    return doc.write(folder / f"{name}.xml", lights(rng, specular=0.3), floor_plane(floor))
