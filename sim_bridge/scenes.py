"""Scenes: a MuJoCo MJCF file plus what the agent needs to know about it (workspace, ROI, views).

Bundled scenes live in `sim_bridge/scenes/<name>/scene.xml` with a sidecar `scene.json`; any other
MJCF file works too, with the metadata derived from its geometry when no sidecar is found.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import mujoco
import numpy as np
import trimesh

from area3d_msgs_py.camera_pose import look_at
from sim_bridge.geoms import clip_to_box, geom_meshes, ground_planes, solid_geom_ids
from sim_bridge.validity import valid_positions

SCENES_DIR = Path(__file__).resolve().parent / "scenes"

# Paper, Sec. 4 (setting): |O_0| = 4 at object level, 15 at scene level.
INITIAL_VIEWS = {"object": 4, "room": 15}
# Paper, Sec. 3.3: global weight gamma = 0.01 (object level), 0.005 (scene level).
GAMMA = {"object": 0.01, "room": 0.005}
# F-score / completion distance threshold, metres: 1 cm for tabletop objects, 5 cm for rooms.
TAU = {"object": 0.01, "room": 0.05}
# Metadata of a scene without a sidecar (`derive_scene`); metres unless stated. The rules are in
# sim_bridge/README.md ("Bring your own MJCF").
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
# Derived views keep at least this distance from every surface (more than the pose check asks).
DERIVED_VIEW_CLEARANCE = {"object": 0.1, "room": 0.4}
# Initial views of a derived object scene span this arc on its open side (-y without walls),
# degrees: the far side stays unseen.
DERIVED_ARC_DEG = 90.0
# Room views look this far down, degrees, along the heading with the most free space ahead.
ROOM_VIEW_PITCH_DEG = (20.0, 12.0, 30.0)
ROOM_VIEW_YAWS = 24  # headings tried per room view
NUM_ROOM_EVAL_VIEWS = 20
ROOM_EVAL_HEIGHTS = (1.0, 1.4, 1.8)  # above the floor, clipped to the workspace
ROOM_VIEW_SEPARATION = 0.5  # metres between a held-out room view and every initial one


@dataclass
class Scene:
    """A scene to reconstruct. Poses are (4, 4) T_world_cam of the optical frame; bounds in metres."""

    name: str
    level: Literal["object", "room"]
    mjcf_path: Path
    workspace_min: np.ndarray
    workspace_max: np.ndarray
    roi_min: np.ndarray
    roi_max: np.ndarray
    initial_views: np.ndarray
    eval_views: np.ndarray
    gamma: float
    tau: float
    _cache: dict = field(default_factory=dict, repr=False, compare=False)

    def model(self) -> tuple[mujoco.MjModel, mujoco.MjData]:
        """The compiled model and its data after mj_forward (cached)."""
        if "model" not in self._cache:
            model = mujoco.MjModel.from_xml_path(str(self.mjcf_path))
            data = mujoco.MjData(model)
            mujoco.mj_forward(model, data)
            self._cache["model"] = (model, data)
        return self._cache["model"]

    def scene_mesh(self) -> trimesh.Trimesh:
        """World-frame surface of every solid geom in the scene (cached)."""
        if "scene_mesh" not in self._cache:
            self._cache["scene_mesh"] = trimesh.util.concatenate(geom_meshes(*self.model()))
        return self._cache["scene_mesh"]

    def ground_truth_mesh(self) -> trimesh.Trimesh:
        """World-frame surface of the region to reconstruct: scene geometry clipped to the ROI box."""
        if "gt" not in self._cache:
            self._cache["gt"] = clip_to_box(self.scene_mesh(), self.roi_min, self.roi_max)
        return self._cache["gt"].copy()

    def valid_positions(self, points: np.ndarray, clearance: float) -> np.ndarray:
        """(N,) bool: camera centres inside the workspace and clear of geometry
        (`sim_bridge.validity.valid_positions`); what a planner given this scene may check."""
        return valid_positions(self, points, clearance)


def list_scenes() -> list[str]:
    """Names of the bundled scenes."""
    return sorted(p.parent.name for p in SCENES_DIR.glob("*/scene.xml"))


def load_scene(name_or_path: str | Path) -> Scene:
    """A bundled scene by name, or any MJCF file by path (metadata from a sidecar JSON or derived)."""
    text = str(name_or_path)
    bundled = SCENES_DIR / text / "scene.xml"
    if "/" not in text and not text.endswith(".xml") and bundled.is_file():
        path = bundled
    else:
        path = Path(text).expanduser()
        if not path.is_file():
            raise ValueError(
                f"scene: got {text!r}, expected one of {list_scenes()} or an existing MJCF file path"
            )
    path = path.resolve()
    for sidecar in (path.with_suffix(".json"), path.parent / "scene.json"):
        if sidecar.is_file():
            return _from_sidecar(path, json.loads(sidecar.read_text()))
    return derive_scene(path)


def _from_sidecar(path: Path, meta: dict) -> Scene:
    level = meta.get("level", "object")
    return Scene(
        name=meta.get("name", path.stem),
        level=level,
        mjcf_path=path,
        workspace_min=np.asarray(meta["workspace_min"], dtype=np.float64),
        workspace_max=np.asarray(meta["workspace_max"], dtype=np.float64),
        roi_min=np.asarray(meta["roi_min"], dtype=np.float64),
        roi_max=np.asarray(meta["roi_max"], dtype=np.float64),
        initial_views=np.asarray(meta["initial_views"], dtype=np.float64).reshape(-1, 4, 4),
        eval_views=np.asarray(meta["eval_views"], dtype=np.float64).reshape(-1, 4, 4),
        gamma=float(meta.get("gamma", GAMMA[level])),
        tau=float(meta.get("tau", TAU[level])),
    )


def scene_to_json(scene: Scene) -> str:
    """The sidecar JSON text of `scene` (what `load_scene` reads back)."""
    meta = {
        "name": scene.name,
        "level": scene.level,
        "gamma": scene.gamma,
        "tau": scene.tau,
        "workspace_min": np.round(scene.workspace_min, 6).tolist(),
        "workspace_max": np.round(scene.workspace_max, 6).tolist(),
        "roi_min": np.round(scene.roi_min, 6).tolist(),
        "roi_max": np.round(scene.roi_max, 6).tolist(),
        "initial_views": np.round(scene.initial_views, 7).tolist(),
        "eval_views": np.round(scene.eval_views, 7).tolist(),
    }
    return json.dumps(meta, indent=1)


def derive_scene(path: Path, name: str | None = None) -> Scene:
    """Metadata for an MJCF file that has none, from its geometry (rules in sim_bridge/README.md).

    Fills every `Scene` field: `level` ("room" when walls enclose the scene on 3 or 4 sides or its
    footprint, walls beside it left out, is large, else "object"), `roi_min/max` (object level: the
    objects on the highest large support surface plus a rim of that surface, up to the faces of
    the walls beside them; room level: the interior inside the walls), workspace (object level: the
    ROI grown by a margin, above the support, in front of the walls; room level: the interior
    shrunk by a margin, at robot heights), `initial_views` (4 on an arc on the open side / 15
    spread inside the room) and `eval_views` (rings all around or over the open side / spread
    inside the room), every view clear of geometry, plus `gamma` and `tau` of the level.
    """
    scene = Scene(
        name=name or path.stem,
        level="object",
        mjcf_path=path,
        workspace_min=np.zeros(3),
        workspace_max=np.ones(3),
        roi_min=np.zeros(3),
        roi_max=np.ones(3),
        initial_views=np.zeros((0, 4, 4)),
        eval_views=np.zeros((0, 4, 4)),
        gamma=GAMMA["object"],
        tau=TAU["object"],
    )
    try:
        model, data = scene.model()
    except ValueError as err:  # MuJoCo's XML / compile errors do not name the file
        raise ValueError(
            f"scene file {str(path)!r}: MuJoCo could not load it: {err}".strip()
        ) from err
    if len(solid_geom_ids(model)) == 0:
        raise ValueError(
            f"scene file {str(path)!r}: no solid geoms, expected at least one visible geom that is not a plane"
        )
    layout = scene_layout(*geometry_boxes(model, data))
    level = layout["level"]
    scene.level = level
    scene.gamma, scene.tau = GAMMA[level], TAU[level]
    scene.roi_min, scene.roi_max = layout["roi_min"], layout["roi_max"]
    scene.workspace_min, scene.workspace_max = layout["workspace_min"], layout["workspace_max"]
    if level == "object":
        scene.initial_views, scene.eval_views = _object_views(scene, layout)
    else:
        scene.initial_views, scene.eval_views = _room_views(scene, layout)
    scene._cache.pop("gt", None)
    return scene


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


def _first_valid(scene: Scene, candidates: np.ndarray, what: str) -> np.ndarray:
    """(V, 3) the first position of each row of `candidates` (V, C, 3) that is clear of geometry."""
    v, c, _ = candidates.shape
    ok = valid_positions(
        scene, candidates.reshape(-1, 3), DERIVED_VIEW_CLEARANCE[scene.level]
    ).reshape(v, c)
    missing = np.flatnonzero(~ok.any(axis=1))
    if len(missing):
        raise ValueError(
            f"scene file {str(scene.mjcf_path)!r}: no free camera position for {what} view "
            f"{int(missing[0])} near {np.round(candidates[missing[0], 0], 3).tolist()}, expected "
            f"space {DERIVED_VIEW_CLEARANCE[scene.level]} m clear of geometry inside the workspace"
        )
    return candidates[np.arange(v), np.argmax(ok, axis=1)]


def _object_views(scene: Scene, layout: dict) -> tuple[np.ndarray, np.ndarray]:
    """Initial views on an arc on the open side, held-out rings all around (beside walls: over
    the open side only); each one the nearest free position to its nominal place on the sphere
    around the ROI."""
    centre = layout["view_centre"]
    half_diag = float(np.linalg.norm(scene.roi_max[:2] - scene.roi_min[:2])) / 2
    height = float(scene.roi_max[2] - scene.roi_min[2])
    reach = max(0.45, 1.1 * half_diag, VIEW_HEIGHT_REACH * height)
    scales = np.array([1.0, 0.9, 1.1, 0.8, 1.2, 0.7, 1.35])
    d_el = np.array([0.0, -8.0, 8.0, 16.0, -16.0, 24.0])
    d_az = np.array([0.0, 6.0, -6.0, 12.0, -12.0])

    def place(az, el, radius, what):
        s, e, a = np.meshgrid(scales, d_el, d_az, indexing="ij")
        s, e, a = s.ravel(), e.ravel(), a.ravel()
        order = np.argsort(np.abs(s - 1) * 4 + np.abs(e) / 8 + np.abs(a) / 6, kind="stable")
        s, e, a = s[order], e[order], a[order]
        az_c = np.deg2rad(az[:, None] + a[None])
        el_c = np.deg2rad(np.clip(el[:, None] + e[None], 5.0, 80.0))
        r = radius * s[None]
        eyes = centre + np.stack(
            [r * np.cos(el_c) * np.cos(az_c), r * np.cos(el_c) * np.sin(az_c), r * np.sin(el_c)], -1
        )
        return np.stack([look_at(p, centre) for p in _first_valid(scene, eyes, what)])

    n0 = INITIAL_VIEWS["object"]
    open_az = layout.get("open_azimuth_deg", -90.0)
    walls = layout.get("walls", [])
    held_el = np.concatenate([np.full(12, 28.0), np.full(6, 55.0)])
    if not walls:
        arc = (-DERIVED_ARC_DEG / 2, DERIVED_ARC_DEG / 2)
        held_az = np.concatenate([np.arange(12) * 30.0 + 10.0, np.arange(6) * 60.0 + 40.0])
    else:
        # Azimuths whose held-out eye stands well in front of every wall, from the back round.
        az = open_az - 179.5 + np.arange(360.0)
        ring = (reach + 0.05) * np.cos(np.deg2rad(held_el.min()))
        eye_xy = centre[:2] + ring * np.stack([np.cos(np.deg2rad(az)), np.sin(np.deg2rad(az))], 1)
        ok = np.ones(len(az), dtype=bool)
        for axis, sign, face in walls:
            ok &= sign * (eye_xy[:, axis] - face) >= 2 * WALL_CAMERA_GAP
        if ok.sum() < 2 * len(held_el):
            raise ValueError(
                f"scene file {str(scene.mjcf_path)!r}: the objects' open side spans "
                f"{int(ok.sum())} degrees, expected room for views in front of the walls"
            )
        # the initial arc: centred on the open direction, at most over the middle half of the
        # open run around it (its ends stay for the agent to find)
        back = np.flatnonzero(~ok[:180])  # az[179] and az[180] are 0.5 degrees either side
        ahead = np.flatnonzero(~ok[180:])
        run = (
            az[back.max() + 1] if len(back) else az[0],
            az[180 + ahead.min() - 1] if len(ahead) else az[-1],
        )
        arc = (
            max(-DERIVED_ARC_DEG / 2, (run[0] - open_az) / 2),
            min(DERIVED_ARC_DEG / 2, (run[1] - open_az) / 2),
        )
        allowed = az[ok]
        held_az = np.concatenate(
            [allowed[((np.arange(n) + 0.5) * len(allowed) / n).astype(int)] for n in (12, 6)]
        )
    initial = place(
        open_az + np.linspace(arc[0], arc[1], n0),
        np.resize(np.array([25.0, 35.0]), n0),
        reach,
        "initial",
    )
    return initial, place(held_az, held_el, reach + 0.05, "held-out")


def _farthest_points(candidates: np.ndarray, taken: np.ndarray, n: int) -> np.ndarray:
    """(n,) indices into `candidates` (C, 3), each the farthest from `taken` (T, 3) and from the
    ones picked before it (greedy farthest-point sampling). With nothing taken, the first pick is
    the candidate nearest the candidates' mean."""
    picked: list[int] = []
    if not len(taken):
        picked.append(int(np.argmin(np.linalg.norm(candidates - candidates.mean(axis=0), axis=1))))
        taken = candidates[picked]
    dist = np.linalg.norm(candidates[:, None] - taken[None], axis=2).min(axis=1)
    while len(picked) < min(n, len(candidates)):
        i = int(np.argmax(dist))
        picked.append(i)
        dist = np.minimum(dist, np.linalg.norm(candidates - candidates[i], axis=1))
    return np.array(picked, dtype=np.int64)


def _room_views(scene: Scene, layout: dict) -> tuple[np.ndarray, np.ndarray]:
    """Initial views spread over the room, held-out views filling the gaps between them at several
    heights; each looks slightly down along its heading with the most free space ahead."""
    lo, hi = scene.workspace_min, scene.workspace_max
    floor_z = layout["floor_z"]
    xs = np.arange(lo[0], hi[0] + 1e-9, 0.25)
    ys = np.arange(lo[1], hi[1] + 1e-9, 0.25)

    def grid(heights):
        z = np.unique(np.clip(floor_z + np.asarray(heights), lo[2], hi[2]))
        return np.stack(np.meshgrid(xs, ys, z, indexing="ij"), -1).reshape(-1, 3)

    def free(points):
        for clearance in (DERIVED_VIEW_CLEARANCE["room"], 0.2, 0.1):
            ok = valid_positions(scene, points, clearance)
            if ok.sum() >= INITIAL_VIEWS["room"]:
                return points[ok]
        raise ValueError(
            f"scene file {str(scene.mjcf_path)!r}: only {int(ok.sum())} free camera positions in "
            f"the room workspace {np.round(lo, 3).tolist()}..{np.round(hi, 3).tolist()}, expected "
            f"at least {INITIAL_VIEWS['room']}"
        )

    start = free(grid([1.5]))
    eyes0 = start[_farthest_points(start, np.zeros((0, 3)), INITIAL_VIEWS["room"])]
    candidates = free(grid(ROOM_EVAL_HEIGHTS))
    near = np.linalg.norm(candidates[:, None] - eyes0[None], axis=2).min(axis=1)
    candidates = candidates[near >= ROOM_VIEW_SEPARATION]
    # Heights count double so that the held-out views spread over them as well as over the floor.
    picked = _farthest_points(candidates * [1, 1, 2], eyes0 * [1, 1, 2], NUM_ROOM_EVAL_VIEWS)
    eyes1 = candidates[picked]
    initial = _open_headings(scene, eyes0, ROOM_VIEW_PITCH_DEG[0], 0.0)
    pitch = np.resize(np.array(ROOM_VIEW_PITCH_DEG[1:]), len(eyes1))
    held_out = _open_headings(scene, eyes1, pitch, 180.0 / ROOM_VIEW_YAWS)
    return initial, held_out


def _open_headings(scene: Scene, eyes: np.ndarray, pitch_deg, yaw0_deg: float) -> np.ndarray:
    """(N, 4, 4) views at `eyes` (N, 3) pitched `pitch_deg` down, each along the heading (of
    ROOM_VIEW_YAWS, from `yaw0_deg`) that sees the most room: the largest mean distance to the
    first surface over a small fan of rays around it; a ray that leaves the model (through a
    doorway) counts as 0. MuJoCo ray casts: the simulator may use geometry, the planner never does."""
    model, data = scene.model()
    yaw = np.deg2rad(yaw0_deg + np.arange(ROOM_VIEW_YAWS) * 360.0 / ROOM_VIEW_YAWS)
    fan_yaw = np.deg2rad(np.array([-30.0, -15.0, 0.0, 15.0, 30.0, -15.0, 0.0, 15.0]))
    fan_pitch = np.deg2rad(np.array([0.0, 0.0, 0.0, 0.0, 0.0, 15.0, 15.0, 15.0]))
    pitch = np.deg2rad(np.broadcast_to(np.asarray(pitch_deg, dtype=np.float64), len(eyes)))
    geomid = np.zeros(1, dtype=np.int32)
    views = []
    for eye, p in zip(eyes, pitch, strict=True):
        ry = (yaw[:, None] + fan_yaw[None]).ravel()
        rp = np.broadcast_to(p + fan_pitch[None], (len(yaw), len(fan_pitch))).ravel()
        dirs = np.stack([np.cos(ry) * np.cos(rp), np.sin(ry) * np.cos(rp), -np.sin(rp)], 1)
        hit = np.array([mujoco.mj_ray(model, data, eye, d, None, 1, -1, geomid) for d in dirs])
        score = np.maximum(hit, 0.0).reshape(len(yaw), len(fan_pitch)).mean(axis=1)
        best = yaw[int(np.argmax(score))]
        heading = np.array([np.cos(best) * np.cos(p), np.sin(best) * np.cos(p), -np.sin(p)])
        views.append(look_at(eye, eye + heading))
    return np.stack(views)
