"""A scene to reconstruct: a MuJoCo MJCF file plus what the agent needs to know about it
(workspace, region of interest, initial and held-out views, the level's gamma and tau)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import mujoco
import numpy as np
import trimesh

from sim_bridge.geoms import clip_to_box, geom_meshes
from sim_bridge.validity import valid_positions

# Paper, Sec. 4 (setting): |O_0| = 4 at object level, 15 at scene level.
INITIAL_VIEWS = {"object": 4, "room": 15}
# Paper, Sec. 3.3: global weight gamma = 0.01 (object level), 0.005 (scene level).
GAMMA = {"object": 0.01, "room": 0.005}
# F-score / completion distance threshold, metres: 1 cm for tabletop objects, 5 cm for rooms.
TAU = {"object": 0.01, "room": 0.05}


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
