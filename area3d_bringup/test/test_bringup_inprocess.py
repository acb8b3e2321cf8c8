import numpy as np

from area3d_bringup.inprocess import run_inprocess_episode
from area3d_eval.rundir import frame_files, read_episode, read_frame
from sim_bridge.scenes import load_scene
from sim_bridge.validity import check_pose


def test_an_in_process_episode_writes_the_run_directory_of_area3d_run(tmp_path):
    run_dir = run_inprocess_episode("single_object", "area3d", 0, tmp_path, budget=6)
    episode = read_episode(run_dir)
    scene = load_scene("single_object")
    assert episode.kinds() == ["initial"] * 4 + ["planned"] * 2
    assert episode.level == "object" and episode.budget == 6
    files = frame_files(run_dir)
    assert len(files) == 6
    poses = episode.poses()
    # taken at the pose a goal message carries, as over the graph: a quaternion, within 1e-7
    np.testing.assert_allclose(poses[:4], scene.initial_views, atol=1e-7)
    for path, T in zip(files, poses, strict=True):
        frame = read_frame(path)
        np.testing.assert_allclose(frame.T_world_cam, T)
        # the camera's depth (a view along the table top sees nothing above its horizon, and
        # the camera's noise drops grazing and edge pixels)
        assert np.isfinite(frame.depth).mean() > 0.25
    for T in poses[4:]:
        assert check_pose(scene, T).ok
        # planned views are new places, not a repeat of a captured one
        assert np.min(np.linalg.norm(poses[:4, :3, 3] - T[:3, 3], axis=1)) > 0.05
    assert episode.timings_s["planning"] > 0 and episode.timings_s["perception"] > 0
    assert episode.stopped_early == ""  # the budget was spent


def test_an_in_process_episode_whose_planner_has_no_view_stops_and_says_why(tmp_path):
    """No candidate position in a workspace of a millimetre: the episode ends after the
    initial views and episode.json says why, as the graph's runner words it."""
    tiny = {"workspace_min": [0.0, 0.0, 0.5], "workspace_max": [0.001, 0.001, 0.501]}
    run_dir = run_inprocess_episode(
        "single_object", "area3d", 0, tmp_path, budget=6, overrides={"planner": tiny}
    )
    episode = read_episode(run_dir)
    assert episode.kinds() == ["initial"] * 4
    assert episode.stopped_early.startswith("the planner returned no view with 2 left (workspace:")


def test_an_in_process_episode_refuses_an_unknown_policy_and_a_budget_short_of_o0(tmp_path):
    import pytest

    with pytest.raises(ValueError, match="policy"):
        run_inprocess_episode("single_object", "best", 0, tmp_path, budget=5)
    # it ran the 4 initial views and recorded a budget of 0
    with pytest.raises(ValueError, match=r"budget: got 0, expected .* at least \|O_0\| = 4"):
        run_inprocess_episode("single_object", "area3d", 0, tmp_path, budget=0)


def test_a_scene_given_by_a_relative_path_is_recorded_so_it_is_found_from_anywhere(
    tmp_path, monkeypatch
):
    """`--scene table.xml` from the scene's folder: the run recorded 'table' (in process) or
    'table.xml' (over the graph), which a report or --resume from elsewhere could not load."""
    import shutil

    from sim_bridge.scenes import SCENES_DIR

    mine = tmp_path / "mine"
    shutil.copytree(SCENES_DIR / "single_object", mine)  # with its meshes and textures
    (mine / "scene.xml").rename(mine / "table.xml")
    monkeypatch.chdir(mine)
    run_dir = run_inprocess_episode("table.xml", "uniform", 0, tmp_path / "runs", budget=4)
    assert read_episode(run_dir).scene == str((mine / "table.xml").resolve())
    bundled = run_inprocess_episode("single_object", "uniform", 0, tmp_path / "runs", budget=4)
    assert read_episode(bundled).scene == "single_object"


def test_a_stereo_episode_keeps_the_estimated_depth_for_the_tsdf(tmp_path):
    run_dir = run_inprocess_episode(
        "single_object",
        "area3d",
        0,
        tmp_path,
        budget=4,
        overrides={"perception": {"backend": "stereo"}},
        depth_source="estimated",
    )
    assert read_episode(run_dir).depth_source == "estimated"
    for path in frame_files(run_dir):
        frame = read_frame(path)
        both = np.isfinite(frame.estimated_depth) & np.isfinite(frame.depth)
        assert both.mean() > 0.3  # the simulator's right image was matched
        rel = np.abs(frame.estimated_depth[both] - frame.depth[both]) / frame.depth[both]
        assert np.median(rel) < 0.05  # metric: right baseline, right focal length, right sign
        assert 0.0 < np.median(frame.confidence[both]) <= 1.0
