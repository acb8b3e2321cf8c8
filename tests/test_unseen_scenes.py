"""Scenes nobody tuned on: generated MJCF files without metadata run through the whole pipeline."""

import json

import numpy as np
import pytest

from area3d_bringup.inprocess import run_inprocess_episode
from area3d_bringup.launch_description import planner_region
from area3d_eval.rundir import read_episode
from area3d_planner.config import PlannerConfig
from sim_bridge.holdout_scenes import write_holdout_scene
from sim_bridge.scenes import load_scene
from sim_bridge.validity import check_pose


@pytest.mark.parametrize(
    ("kind", "level", "budget"),
    [("tabletop", "object", 7), ("alcove_room", "room", 17), ("shelf_wall", "object", 7)],
)
def test_a_generated_scene_without_metadata_is_planned_with_the_map_alone(
    tmp_path, kind, level, budget
):
    path = write_holdout_scene(kind, tmp_path / kind, seed=1)  # seed 0 is the benchmark's
    scene = load_scene(path)
    region = planner_region(scene)
    config = PlannerConfig(**{k: tuple(v) if isinstance(v, list) else v for k, v in region.items()})
    # the planner is told a box and a level, and its own rule agrees with the level
    assert config.level == level
    assert PlannerConfig(**{**config.__dict__, "level": "auto"}).resolved_level() == level
    assert config.grid_spec().num_voxels <= config.voxel_budget
    run_dir = run_inprocess_episode(str(path), "area3d", 0, tmp_path / "runs", budget=budget)
    episode = read_episode(run_dir)
    assert episode.level == level
    kinds = episode.kinds()
    assert kinds.count("initial") == len(scene.initial_views)
    # every view the planner chose from its map was accepted by the camera: none refused
    assert len(kinds) == budget and kinds.count("planned") == budget - len(scene.initial_views)
    poses = episode.poses()
    for T in poses[kinds.index("planned") :]:
        assert check_pose(scene, T).ok
        assert np.all(T[:3, 3] >= scene.workspace_min) and np.all(T[:3, 3] <= scene.workspace_max)
    assert json.loads((run_dir / "episode.json").read_text())["scene"] == str(path)
    # named by the file's stem, never by its path
    assert run_dir.name == f"{path.stem}_area3d_s0" and episode.scene_name == path.stem
