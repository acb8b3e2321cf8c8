"""Run presets: what `--policy paper` builds is the published method's field and masks; a
camera class (`--camera`) is described alike by every node."""

import numpy as np
import pytest

import area3d_planner.node as planner_node
from area3d_bringup.launch_description import merge
from area3d_bringup.presets import (
    CAMERA_PRESETS,
    PAPER_PIXELS_PER_VOXEL,
    camera_preset,
    episode_specs,
)
from area3d_msgs_py.camera_pose import look_at
from area3d_msgs_py.parameters import parameter_values

K = np.array([[32.0, 0, 32], [0, 32.0, 24], [0, 0, 1]])


def planner_config(policy: str):
    specs = episode_specs("single_object", policy, 0, 10)
    given = next(spec.parameters for spec in specs if spec.name == "planner")
    return planner_node.config_from_parameters(parameter_values(planner_node.PARAMS, given))


def wall_seen_twice(config):
    """The configuration's grid after two frames of a wall across the region of interest, 0.255 m
    in front of the camera, with confidence 0.4 and then 0.8; the wall's voxel on the optical
    axis and one behind the wall, which no frame covered."""
    grid = config.fused_grid()
    T = look_at(np.array([-0.3, 0.0, 0.82]), np.array([0.3, 0.0, 0.82]))
    depth = np.full((48, 64), 0.255, np.float32)
    for conf in (0.4, 0.8):
        grid.integrate_depth(depth, np.full_like(depth, conf), K, T, stride=1)
    wall, hidden = grid.spec.flat_index(np.array([[-0.045, 0.0, 0.82], [0.1, 0.0, 0.82]]))[0]
    return grid, wall, hidden


def test_the_paper_preset_scores_one_minus_the_mean_confidence_and_gamma_on_unobserved_voxels():
    config = planner_config("paper")
    grid, wall, hidden = wall_seen_twice(config)
    occ = grid.occupancy()
    assert occ[wall] == 1 and occ[hidden] == -1
    gamma = config.resolved_gamma()
    U = grid.fused()
    # U_geo = 1 - mean C (0.4 and 0.8: 0.4), no semantic map fused, gamma on top
    assert U[wall] == pytest.approx(1.0 - 0.6 + gamma, abs=1e-6)
    assert U[hidden] == pytest.approx(gamma)  # not covered by any view: gamma only
    # the project's rule on the same frames: the product of the residuals, times achievability
    ours, wall_, _ = wall_seen_twice(planner_config("area3d"))
    assert ours.fused()[wall_] < 0.5 * U[wall]


def test_the_paper_preset_counts_every_visible_voxel_whole_in_a_views_mask():
    paper = planner_config("paper")
    v = paper.planning_context(paper.fused_grid()).visibility
    assert v.pixels_per_voxel == PAPER_PIXELS_PER_VOXEL and not v.range_profile
    assert v.repeat_gain == 1.0 and not v.incidence
    ours = planner_config("area3d")
    area3d = ours.planning_context(ours.fused_grid()).visibility
    assert area3d.pixels_per_voxel > 1.0 and area3d.range_profile and area3d.repeat_gain < 1.0


@pytest.mark.parametrize("camera", sorted(CAMERA_PRESETS))
def test_a_camera_class_is_described_alike_by_the_camera_perception_and_the_planner(camera):
    import area3d_perception.node as perception_node
    import sim_bridge.node as sim_node

    specs = episode_specs("single_object", "area3d", 0, 10, overrides=camera_preset(camera))
    given = {spec.name: spec.parameters for spec in specs}
    sim = parameter_values(sim_node.PARAMS, given["sim_bridge"])
    perception = parameter_values(perception_node.PARAMS, given["perception"])
    planner = planner_node.config_from_parameters(
        parameter_values(planner_node.PARAMS, given["planner"])
    )
    assert sim["max_range"] == perception["sensor.max_range"] == planner.max_range
    assert sim["sensor.min_range"] == perception["sensor.min_range"] == planner.min_range
    for name in ("sigma_a", "sigma_b", "sigma_z0", "reference_focal_px"):
        assert sim[f"sensor.{name}"] == perception[f"sensor.{name}"]
    planner.validate()  # and each node builds its core from them
    perception_node.estimator_from_parameters(perception)
    with pytest.raises(ValueError, match="camera: got 'lidar'"):
        camera_preset("lidar")


@pytest.mark.parametrize("camera, near, far", [("d435", 0.28, 3.0), ("kinect", 0.5, 4.5)])
def test_with_a_cameras_minimum_range_every_view_is_planned_where_the_camera_measures(
    tmp_path, camera, near, far
):
    """The bundled scene's initial views are nearer than a Kinect measures; the planned views
    still see the region, from beyond the minimum range."""
    from area3d_bringup.inprocess import run_inprocess_episode
    from area3d_eval.rundir import iter_frames, read_episode

    small = {"width": 160, "height": 120}
    overrides = merge(camera_preset(camera), {"sim_bridge": small, "planner": small})
    run = run_inprocess_episode("single_object", "area3d", 0, tmp_path, 8, overrides)
    kinds = read_episode(run).kinds()
    assert kinds.count("planned") == 4  # every view planned
    for frame, kind in zip(iter_frames(run), kinds, strict=True):
        finite = frame.depth[np.isfinite(frame.depth)]
        assert not finite.size or (finite.min() >= near and finite.max() <= far)
        if kind == "planned":
            assert finite.size > 0.2 * frame.depth.size  # it measures what it looks at
