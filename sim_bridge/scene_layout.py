"""What a scene without a sidecar is, read off its geometry: its level (object or room), region
of interest and camera workspace (the rules are in sim_bridge/README.md, "Bring your own MJCF").
Metres unless stated.
"""

from __future__ import annotations

import mujoco
import numpy as np

from sim_bridge.geoms import geom_meshes, ground_planes, solid_geom_ids

# A scene whose footprint (floor excluded) has a longer diagonal than this is a room.
ROOM_DIAGONAL = 2.5
# A wall: a geom at least this tall above the floor, this thin across and this long along.
WALL_MIN_HEIGHT = 1.5
WALL_MAX_THICKNESS = 0.4
WALL_MIN_LENGTH = 1.0
# A wall bounds the footprint on a side when it stands within this distance of that edge.
WALL_EDGE_TOLERANCE = 0.3
# Walls on at least this many of the footprint's four sides enclose a room, whatever its size.
# Walls on fewer sides (a wall, a backdrop, a corner) stand beside an object scene, which is seen
# from its open side: the ROI stops this far before a wall face, the workspace this far.
ENCLOSING_SIDES = 3
WALL_ROI_GAP = 0.01
WALL_CAMERA_GAP = 0.1
# The footprint's sides and the inward normal of a wall on each: (axis, sign) into the scene.
WALL_NORMALS = {"west": (0, 1.0), "east": (0, -1.0), "south": (1, 1.0), "north": (1, -1.0)}
# A slab (floor, table top, shelf board, ceiling) is a geom at most this thick.
SLAB_MAX_THICKNESS = 0.12
# A floor or ceiling slab covers at least this share of the footprint.
FLOOR_MIN_SHARE = 0.5
# A support surface (table top) is a slab of at least this area, m^2 (30 x 30 cm); a support is
# "large" when its area is at least this share of the largest slab's.
SUPPORT_MIN_AREA = 0.09
SUPPORT_SHARE = 0.5
# Large slabs that overlap in plan (by half the smaller one's area) at least this far apart in
# height are the boards of one shelf unit, not a table top: the unit stands on the floor.
SHELF_BOARD_GAP = 0.1
# A slab is no support when something standing beside it on a lower surface rises more than this
# above its top (a stool next to a floor lamp): it is one piece of furniture among others.
SUPPORT_OVERTOP = 0.1
# Metres of support surface around the objects that belong to the ROI (the bundled scenes' rim).
ROI_RIM = 0.06
# Workspace of a derived scene: ROI grown by this margin (objects) or the interior shrunk by it
# (rooms: the camera stays off the walls), metres.
DERIVED_MARGIN = {"object": 0.6, "room": 0.3}
# A tall object region (a shelf unit, a floor lamp): its views stand back this many times its
# height (a 74 degree vertical field of view spans most of it), and its workspace reaches as far.
VIEW_HEIGHT_REACH = 0.75
# Room cameras stay between these heights above the floor (a mobile robot's reach), and this far
# below the ceiling or the wall tops.
ROOM_CAMERA_HEIGHT = (0.4, 2.0)
ROOM_TOP_CLEARANCE = 0.3
# The room ROI stops this far below the ceiling or the wall tops.
ROOM_ROI_TOP_SLACK = 0.1


def geometry_boxes(
    model: mujoco.MjModel, data: mujoco.MjData
) -> tuple[np.ndarray, np.ndarray, float | None]:
    """What `scene_layout` reads of a model (`data` after mj_forward): (lo, hi) (G, 3) world
    bounding boxes of its solid geoms and the height of its highest upward ground plane, if any."""
    boxes = np.array([m.bounds for m in geom_meshes(model, data, solid_geom_ids(model))])
    planes = [p[2] for p, n in ground_planes(model, data) if n[2] > 0.9]
    return boxes[:, 0], boxes[:, 1], max(planes) if planes else None


def scene_layout(lo: np.ndarray, hi: np.ndarray, plane_z: float | None = None) -> dict:
    """Level, ROI and workspace of a scene from its solid geoms' world bounding boxes.

    lo, hi: (G, 3) corners of each geom's axis-aligned box, metres; plane_z: height of the highest
    upward ground plane, if any. Returns {"level", "floor_z", "roi_min", "roi_max",
    "workspace_min", "workspace_max", "view_centre" (3,)} plus, at object level, "support_z",
    "walls" ([(axis, inward sign, face coordinate)] of the walls beside the objects) and
    "open_azimuth_deg" (the side to view them from), or at room level "interior_min",
    "interior_max" (3,) (inside the walls, floor to top).
    """
    lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
    if lo.ndim != 2 or lo.shape[1:] != (3,) or len(lo) == 0 or hi.shape != lo.shape:
        raise ValueError(
            f"lo, hi: got shapes {lo.shape}, {hi.shape}, expected two (G, 3) arrays with G >= 1"
        )
    if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi)) and np.all(hi >= lo)):
        raise ValueError("lo, hi: got non-finite or inverted boxes, expected finite lo <= hi")
    size = hi - lo
    area = size[:, 0] * size[:, 1]
    thin = size[:, 2] <= SLAB_MAX_THICKNESS
    all_lo, all_hi = lo.min(axis=0), hi.max(axis=0)
    footprint = float(np.prod(all_hi[:2] - all_lo[:2]))
    floor_slab = (
        thin & (area >= FLOOR_MIN_SHARE * footprint) & (hi[:, 2] <= all_lo[2] + SLAB_MAX_THICKNESS)
    )
    if len(lo) > 1 and floor_slab.all():  # only slabs: keep the highest as the scene itself
        floor_slab[np.argmax(hi[:, 2])] = False
    floors = [float(hi[floor_slab, 2].max())] if floor_slab.any() else []
    floors += [] if plane_z is None else [float(plane_z)]
    floor_z = max(floors) if floors else float(all_lo[2])
    rest = ~floor_slab
    f_lo, f_hi = lo[rest].min(axis=0), hi[rest].max(axis=0)
    sides = _wall_sides(lo, hi, rest, floor_z, f_lo, f_hi)
    if sum(bool(m.any()) for m in sides.values()) >= ENCLOSING_SIDES:
        return _room_layout(lo, hi, rest, thin, area, sides, floor_z, f_lo, f_hi)
    # Walls on one or two sides stand beside the objects and are not part of them.
    walls = np.logical_or.reduce(list(sides.values()))
    if not (rest & ~walls).any():  # nothing but walls: they are the objects
        walls[:] = False
        sides = {side: walls.copy() for side in sides}
    objects = rest & ~walls
    diagonal = float(np.linalg.norm(hi[objects, :2].max(axis=0) - lo[objects, :2].min(axis=0)))
    if diagonal > ROOM_DIAGONAL:
        return _room_layout(lo, hi, rest, thin, area, sides, floor_z, f_lo, f_hi)
    return _object_layout(lo, hi, objects, thin, area, floor_z, sides)


def _wall_sides(lo, hi, rest, floor_z, f_lo, f_hi) -> dict[str, np.ndarray]:
    """{side: (G,) bool} the walls bounding the footprint [f_lo, f_hi] on its west (-x), east,
    south (-y) and north sides: tall, thin across, long along, standing at that edge. A wall
    near two opposite edges (a backdrop in a shallow scene) bounds the nearer one; a tall panel
    standing in front of another wall of the same side (a shelf's back board) is not a wall."""
    size = hi - lo
    tall = hi[:, 2] - np.maximum(lo[:, 2], floor_z) >= WALL_MIN_HEIGHT
    thin_x = rest & tall & (size[:, 0] <= WALL_MAX_THICKNESS) & (size[:, 1] >= WALL_MIN_LENGTH)
    thin_y = rest & tall & (size[:, 1] <= WALL_MAX_THICKNESS) & (size[:, 0] >= WALL_MIN_LENGTH)
    # distance of each geom's outer face from the footprint's edge on that side
    gap = {
        "west": lo[:, 0] - f_lo[0],
        "east": f_hi[0] - hi[:, 0],
        "south": lo[:, 1] - f_lo[1],
        "north": f_hi[1] - hi[:, 1],
    }
    sides = {
        "west": thin_x & (gap["west"] <= WALL_EDGE_TOLERANCE),
        "east": thin_x & (gap["east"] <= WALL_EDGE_TOLERANCE),
        "south": thin_y & (gap["south"] <= WALL_EDGE_TOLERANCE),
        "north": thin_y & (gap["north"] <= WALL_EDGE_TOLERANCE),
    }
    for a, b in (("west", "east"), ("south", "north")):
        both = sides[a] & sides[b]
        sides[a] &= ~(both & (gap[a] > gap[b]))
        sides[b] &= ~(both & (gap[a] <= gap[b]))
    for side, (axis, sign) in WALL_NORMALS.items():
        ids = np.flatnonzero(sides[side])
        inner = hi[ids, axis] if sign > 0 else -lo[ids, axis]  # inner face, inwards positive
        outer = lo[ids, axis] if sign > 0 else -hi[ids, axis]  # outer face, inwards positive
        in_front = (outer[:, None] >= inner[None] - 0.01) & (ids[:, None] != ids[None])
        sides[side][ids[in_front.any(axis=1)]] = False
    return sides


def _room_layout(lo, hi, rest, thin, area, sides, floor_z, f_lo, f_hi) -> dict:
    inner_lo, inner_hi = f_lo[:2].copy(), f_hi[:2].copy()
    if sides["west"].any():
        inner_lo[0] = hi[sides["west"], 0].max()
    if sides["east"].any():
        inner_hi[0] = lo[sides["east"], 0].min()
    if sides["south"].any():
        inner_lo[1] = hi[sides["south"], 1].max()
    if sides["north"].any():
        inner_hi[1] = lo[sides["north"], 1].min()
    walls = np.logical_or.reduce(list(sides.values()))
    inner_area = float(np.prod(inner_hi - inner_lo))
    ceiling = (
        rest
        & thin
        & (area >= FLOOR_MIN_SHARE * inner_area)
        & (lo[:, 2] >= floor_z + WALL_MIN_HEIGHT)
    )
    if ceiling.any():
        top = float(lo[ceiling, 2].min())
    elif walls.any():
        top = float(hi[walls, 2].max())
    else:
        top = float(f_hi[2])
    margin = DERIVED_MARGIN["room"]
    ws_lo = np.array([*(inner_lo + margin), floor_z + ROOM_CAMERA_HEIGHT[0]])
    ws_hi = np.array(
        [*(inner_hi - margin), min(floor_z + ROOM_CAMERA_HEIGHT[1], top - ROOM_TOP_CLEARANCE)]
    )
    if np.any(ws_hi <= ws_lo):
        raise ValueError(
            f"room interior {np.round(inner_lo, 3).tolist()}..{np.round(inner_hi, 3).tolist()}, "
            f"floor {floor_z:.3f} m, top {top:.3f} m: expected room for a camera "
            f"{margin} m off the walls and {ROOM_CAMERA_HEIGHT[0]} m above the floor"
        )
    return {
        "level": "room",
        "floor_z": floor_z,
        "interior_min": np.array([*inner_lo, floor_z]),
        "interior_max": np.array([*inner_hi, top]),
        "roi_min": np.array([*(inner_lo - 0.01), floor_z - 0.01]),
        "roi_max": np.array([*(inner_hi + 0.01), top - ROOM_ROI_TOP_SLACK]),
        "workspace_min": ws_lo,
        "workspace_max": ws_hi,
        "view_centre": np.array([*((inner_lo + inner_hi) / 2), floor_z + 0.6]),
    }


def _object_layout(lo, hi, pool, thin, area, floor_z, sides) -> dict:
    """Object level: the support surface and the objects on it among the `pool` geoms; the walls
    in `sides` (at most two sides) bound the ROI and the workspace."""
    slab = pool & thin & (area >= SUPPORT_MIN_AREA) & (lo[:, 2] >= floor_z + SLAB_MAX_THICKNESS)
    support, support_z = -1, floor_z
    if slab.any():
        large = slab & (area >= SUPPORT_SHARE * area[slab].max())
        candidates = large & ~_shelf_boards(lo, hi, large) & ~_overtopped(lo, hi, pool, large)
        if candidates.any():
            support = int(np.flatnonzero(candidates)[np.argmax(hi[candidates, 2])])
            support_z = float(hi[support, 2])
    if support >= 0:
        s_lo, s_hi = lo[support, :2], hi[support, :2]
    else:
        s_lo, s_hi = lo[pool, :2].min(axis=0), hi[pool, :2].max(axis=0)
    centre_xy = (lo[:, :2] + hi[:, :2]) / 2
    on_support = (
        pool
        & (lo[:, 2] >= support_z - 0.01)
        & np.all((centre_xy >= s_lo) & (centre_xy <= s_hi), axis=1)
    )
    if support >= 0:
        on_support[support] = False
    if not on_support.any():  # a bare support: reconstruct its top
        objects_lo = np.array([*s_lo, support_z])
        objects_hi = np.array([*s_hi, support_z + 0.05])
    else:
        objects_lo, objects_hi = lo[on_support].min(axis=0), hi[on_support].max(axis=0)
    roi_lo_xy = np.maximum(objects_lo[:2] - ROI_RIM, np.minimum(s_lo, objects_lo[:2]))
    roi_hi_xy = np.minimum(objects_hi[:2] + ROI_RIM, np.maximum(s_hi, objects_hi[:2]))
    roi_min = np.array([*roi_lo_xy, support_z - 0.02])
    roi_max = np.array([*roi_hi_xy, max(objects_hi[2], support_z + 0.03) + 0.02])
    margin = DERIVED_MARGIN["object"]
    side_margin = max(margin, VIEW_HEIGHT_REACH * float(roi_max[2] - roi_min[2]))
    ws_lo = np.array([*(roi_min[:2] - side_margin), max(floor_z + 0.1, support_z + 0.05)])
    ws_hi = np.array([*(roi_max[:2] + side_margin), max(roi_max[2] + margin, ws_lo[2] + 0.5)])
    walls = []
    for side, (axis, sign) in WALL_NORMALS.items():
        if not sides[side].any():
            continue
        face = float(hi[sides[side], axis].max() if sign > 0 else lo[sides[side], axis].min())
        walls.append((axis, sign, face))
        if sign > 0:  # the scene is on the +axis side of this wall
            roi_min[axis] = max(roi_min[axis], face + WALL_ROI_GAP)
            ws_lo[axis] = max(ws_lo[axis], face + WALL_CAMERA_GAP)
        else:
            roi_max[axis] = min(roi_max[axis], face - WALL_ROI_GAP)
            ws_hi[axis] = min(ws_hi[axis], face - WALL_CAMERA_GAP)
    if np.any(roi_max <= roi_min) or np.any(ws_hi <= ws_lo):
        raise ValueError(
            f"objects {np.round(objects_lo, 3).tolist()}..{np.round(objects_hi, 3).tolist()} "
            f"beside walls {[(('x', 'y')[a], round(f, 3)) for a, _, f in walls]}: expected the "
            f"objects and room for a camera {WALL_CAMERA_GAP} m in front of every wall face"
        )
    top = roi_max[2] - 0.02
    return {
        "level": "object",
        "floor_z": floor_z,
        "support_z": support_z,
        "roi_min": roi_min,
        "roi_max": roi_max,
        "workspace_min": ws_lo,
        "workspace_max": ws_hi,
        "view_centre": np.array(
            [*(roi_min[:2] + roi_max[:2]) / 2, support_z + 0.4 * (top - support_z)]
        ),
        "walls": walls,
        "open_azimuth_deg": _open_azimuth(walls),
    }


def _shelf_boards(lo, hi, large) -> np.ndarray:
    """(G,) bool: the `large` slabs that have another large slab above or below them, overlapping
    in plan by at least half the smaller one's area and at least SHELF_BOARD_GAP apart."""
    ids = np.flatnonzero(large)
    overlap = np.prod(
        np.clip(
            np.minimum(hi[ids, None, :2], hi[None, ids, :2])
            - np.maximum(lo[ids, None, :2], lo[None, ids, :2]),
            0.0,
            None,
        ),
        axis=2,
    )
    plan = np.prod(hi[ids, :2] - lo[ids, :2], axis=1)
    apart = np.maximum(lo[ids, None, 2] - hi[None, ids, 2], lo[None, ids, 2] - hi[ids, None, 2])
    stacked = (overlap >= 0.5 * np.minimum(plan[:, None], plan[None])) & (apart >= SHELF_BOARD_GAP)
    out = np.zeros(len(lo), dtype=bool)
    out[ids] = stacked.any(axis=1)
    return out


def _overtopped(lo, hi, pool, large) -> np.ndarray:
    """(G,) bool: the `large` slabs beside which a `pool` geom standing lower (its centre outside
    the slab's plan, its bottom below the slab's top) rises more than SUPPORT_OVERTOP above it."""
    centre = (lo[:, :2] + hi[:, :2]) / 2
    out = np.zeros(len(lo), dtype=bool)
    for i in np.flatnonzero(large):
        beside = pool & ~np.all((centre >= lo[i, :2]) & (centre <= hi[i, :2]), axis=1)
        out[i] = bool(
            np.any(beside & (lo[:, 2] < hi[i, 2] - 0.01) & (hi[:, 2] > hi[i, 2] + SUPPORT_OVERTOP))
        )
    return out


def _open_azimuth(walls: list[tuple[int, float, float]]) -> float:
    """Azimuth (degrees from +x towards +y) of the open side of an object scene beside `walls`
    [(axis, inward sign, face)]: away from the walls (the corner's diagonal for two); -y without
    walls, and along the walls' faces (-y, else -x) between two opposite walls."""
    inward = np.zeros(2)
    for axis, sign, _ in walls:
        inward[axis] += sign
    if np.linalg.norm(inward) < 1e-9:
        axes = {axis for axis, _, _ in walls}
        inward = np.array([-1.0, 0.0]) if axes == {1} else np.array([0.0, -1.0])
    return float(np.degrees(np.arctan2(inward[1], inward[0])))
