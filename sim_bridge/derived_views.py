"""The initial and held-out views of a scene without a sidecar, placed from its layout
(`scene_layout`): clear of geometry, on an arc and rings around the objects' open side, or spread
through a room looking where it is open.
"""

from __future__ import annotations

import mujoco
import numpy as np

from area3d_msgs_py.camera_pose import look_at
from sim_bridge.scene import INITIAL_VIEWS, Scene
from sim_bridge.scene_layout import VIEW_HEIGHT_REACH, WALL_CAMERA_GAP
from sim_bridge.validity import valid_positions

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


def object_views(scene: Scene, layout: dict) -> tuple[np.ndarray, np.ndarray]:
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


def room_views(scene: Scene, layout: dict) -> tuple[np.ndarray, np.ndarray]:
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
