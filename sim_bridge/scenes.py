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

from sim_bridge.geoms import clip_to_box, geom_meshes, ground_planes
from sim_bridge.views import orbit_views

SCENES_DIR = Path(__file__).resolve().parent / "scenes"

# Paper, Sec. 4 (setting): |O_0| = 4 at object level, 15 at scene level.
INITIAL_VIEWS = {"object": 4, "room": 15}
# Paper, Sec. 3.3: global weight gamma = 0.01 (object level), 0.005 (scene level).
GAMMA = {"object": 0.01, "room": 0.005}
# F-score / completion distance threshold, metres: 1 cm for tabletop objects, 5 cm for rooms.
TAU = {"object": 0.01, "room": 0.05}
# A bring-your-own scene whose ROI diagonal is longer than this is treated as a room, metres.
ROOM_DIAGONAL = 2.5
# Workspace of a derived scene = ROI grown by this margin, metres (rooms: the camera stays inside).
DERIVED_MARGIN = {"object": 0.6, "room": 0.0}
# Initial views of a derived scene span this arc, degrees: the far side stays unseen.
DERIVED_ARC_DEG = 90.0


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
        from sim_bridge.validity import valid_positions

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
    try:
        return derive_scene(path)
    except ValueError as err:  # MuJoCo's XML / compile errors do not name the file
        raise ValueError(
            f"scene file {str(path)!r}: MuJoCo could not load it: {err}".strip()
        ) from err


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
    """Metadata for an MJCF file that has none: ROI = bounding box of all solid geoms; workspace =
    ROI grown by a margin (0.6 m for objects; the ROI itself for rooms), kept 0.1 m above any ground
    plane; initial views on a 90 degree arc, eval views on a ring and a higher ring all around."""
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
    model, data = scene.model()
    mesh = scene.scene_mesh()
    lo, hi = mesh.bounds
    level = "room" if np.linalg.norm(hi - lo) > ROOM_DIAGONAL else "object"
    margin = DERIVED_MARGIN[level]
    floor = max([p[2] for p, n in ground_planes(model, data) if n[2] > 0.9], default=-np.inf)
    ws_lo = lo - margin
    ws_hi = hi + margin
    ws_lo[2] = max(ws_lo[2], floor + 0.1)
    ws_hi[2] = max(ws_hi[2], ws_lo[2] + 0.5)
    centre = (lo + hi) / 2
    radius = max(0.6 * float(np.linalg.norm(hi - lo)), 0.4)
    n0 = INITIAL_VIEWS[level]
    initial = orbit_views(
        centre,
        radius,
        np.linspace(-90 - DERIVED_ARC_DEG / 2, -90 + DERIVED_ARC_DEG / 2, n0),
        np.full(n0, 30.0),
    )
    az = np.concatenate([np.arange(12) * 30.0 + 15.0, np.arange(6) * 60.0])
    el = np.concatenate([np.full(12, 25.0), np.full(6, 55.0)])
    scene.level = level
    scene.gamma, scene.tau = GAMMA[level], TAU[level]
    scene.roi_min, scene.roi_max = lo.copy(), hi.copy()
    scene.workspace_min, scene.workspace_max = ws_lo, ws_hi
    scene.initial_views = initial
    scene.eval_views = orbit_views(centre, radius, az, el)
    scene._cache.pop("gt", None)
    return scene
