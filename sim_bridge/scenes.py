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
ENCLOSING_SIDES = 3
# A slab (floor, table top, shelf board, ceiling) is a geom at most this thick.
SLAB_MAX_THICKNESS = 0.12
# A floor or ceiling slab covers at least this share of the footprint.
FLOOR_MIN_SHARE = 0.5
# A support surface (table top) is a slab of at least this area, m^2 (30 x 30 cm); a support is
# "large" when its area is at least this share of the largest slab's.
SUPPORT_MIN_AREA = 0.09
SUPPORT_SHARE = 0.5
# Metres of support surface around the objects that belong to the ROI (the bundled scenes' rim).
ROI_RIM = 0.06
# Workspace of a derived scene: ROI grown by this margin (objects) or the interior shrunk by it
# (rooms: the camera stays off the walls), metres.
DERIVED_MARGIN = {"object": 0.6, "room": 0.3}
# Room cameras stay between these heights above the floor (a mobile robot's reach), and this far
# below the ceiling or the wall tops.
ROOM_CAMERA_HEIGHT = (0.4, 2.0)
ROOM_TOP_CLEARANCE = 0.3
# The room ROI stops this far below the ceiling or the wall tops.
ROOM_ROI_TOP_SLACK = 0.1
# Derived views keep at least this distance from every surface (more than the pose check asks).
DERIVED_VIEW_CLEARANCE = {"object": 0.1, "room": 0.4}
# Initial views of a derived object scene span this arc on the -y side, degrees: the far side
# stays unseen.
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

    Fills every `Scene` field: `level` ("room" when the scene is enclosed by walls or its footprint
    is large, else "object"), `roi_min/max` (object level: the objects on the highest large support
    surface plus a rim of that surface; room level: the interior inside the walls), workspace
    (object level: the ROI grown by a margin, above the support; room level: the interior shrunk by
    a margin, at robot heights), `initial_views` (4 on an arc on the -y side / 15 spread inside the
    room) and `eval_views` (rings all around / spread inside the room), every view clear of
    geometry, plus `gamma` and `tau` of the level.
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
    ids = solid_geom_ids(model)
    if len(ids) == 0:
        raise ValueError(
            f"scene file {str(path)!r}: no solid geoms, expected at least one visible geom that is not a plane"
        )
    boxes = np.array([m.bounds for m in geom_meshes(model, data, ids)])
    planes = [p[2] for p, n in ground_planes(model, data) if n[2] > 0.9]
    layout = scene_layout(boxes[:, 0], boxes[:, 1], max(planes) if planes else None)
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


def scene_layout(lo: np.ndarray, hi: np.ndarray, plane_z: float | None = None) -> dict:
    """Level, ROI and workspace of a scene from its solid geoms' world bounding boxes.

    lo, hi: (G, 3) corners of each geom's axis-aligned box, metres; plane_z: height of the highest
    upward ground plane, if any. Returns {"level", "floor_z", "roi_min", "roi_max",
    "workspace_min", "workspace_max", "view_centre" (3,)} plus "support_z" (object level) or
    "interior_min", "interior_max" (3,) (room level: inside the walls, floor to top).
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
    # Walls: tall, thin across, long along, standing at an edge of the footprint.
    tall = hi[:, 2] - np.maximum(lo[:, 2], floor_z) >= WALL_MIN_HEIGHT
    thin_x = rest & tall & (size[:, 0] <= WALL_MAX_THICKNESS) & (size[:, 1] >= WALL_MIN_LENGTH)
    thin_y = rest & tall & (size[:, 1] <= WALL_MAX_THICKNESS) & (size[:, 0] >= WALL_MIN_LENGTH)
    sides = {
        "west": thin_x & (lo[:, 0] <= f_lo[0] + WALL_EDGE_TOLERANCE),
        "east": thin_x & (hi[:, 0] >= f_hi[0] - WALL_EDGE_TOLERANCE),
        "south": thin_y & (lo[:, 1] <= f_lo[1] + WALL_EDGE_TOLERANCE),
        "north": thin_y & (hi[:, 1] >= f_hi[1] - WALL_EDGE_TOLERANCE),
    }
    enclosed = sum(bool(m.any()) for m in sides.values()) >= ENCLOSING_SIDES
    diagonal = float(np.linalg.norm(f_hi[:2] - f_lo[:2]))
    if enclosed or diagonal > ROOM_DIAGONAL:
        return _room_layout(lo, hi, rest, thin, area, sides, floor_z, f_lo, f_hi)
    return _object_layout(lo, hi, rest, thin, area, floor_z)


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


def _object_layout(lo, hi, rest, thin, area, floor_z) -> dict:
    slab = rest & thin & (area >= SUPPORT_MIN_AREA) & (lo[:, 2] >= floor_z + SLAB_MAX_THICKNESS)
    if slab.any():
        large = slab & (area >= SUPPORT_SHARE * area[slab].max())
        support = int(np.flatnonzero(large)[np.argmax(hi[large, 2])])
        support_z = float(hi[support, 2])
        s_lo, s_hi = lo[support, :2], hi[support, :2]
    else:
        support, support_z = -1, floor_z
        s_lo, s_hi = lo[rest, :2].min(axis=0), hi[rest, :2].max(axis=0)
    centre_xy = (lo[:, :2] + hi[:, :2]) / 2
    on_support = (
        rest
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
    ws_lo = np.array([*(roi_min[:2] - margin), max(floor_z + 0.1, support_z + 0.05)])
    ws_hi = np.array([*(roi_max[:2] + margin), max(roi_max[2] + margin, ws_lo[2] + 0.5)])
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
            [*(roi_lo_xy + roi_hi_xy) / 2, support_z + 0.4 * (top - support_z)]
        ),
    }


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
    """Initial views on an arc on the -y side, held-out rings all around; each one the nearest
    free position to its nominal place on the sphere around the ROI."""
    centre = layout["view_centre"]
    half_diag = float(np.linalg.norm(scene.roi_max[:2] - scene.roi_min[:2])) / 2
    reach = max(0.45, 1.1 * half_diag)
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
    initial = place(
        np.linspace(-90 - DERIVED_ARC_DEG / 2, -90 + DERIVED_ARC_DEG / 2, n0),
        np.resize(np.array([25.0, 35.0]), n0),
        reach,
        "initial",
    )
    az = np.concatenate([np.arange(12) * 30.0 + 10.0, np.arange(6) * 60.0 + 40.0])
    el = np.concatenate([np.full(12, 28.0), np.full(6, 55.0)])
    return initial, place(az, el, reach + 0.05, "held-out")


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
