"""`area3d bench map-truth`: a run's frames fused again into a planner of its own parameters, and
the share of the region's ground-truth surface its map holds free, unknown and occupied."""

from __future__ import annotations

import json

import numpy as np
import pytest

from area3d_bench.map_truth import OUT_FILE, map_shares, run_bench, surface_voxels
from area3d_eval.rundir import write_episode, write_frame
from area3d_msgs_py.grid import GridSpec


def test_surface_voxels_are_those_holding_a_point_inside_the_region_once_each():
    spec = GridSpec.from_bounds(np.zeros(3), np.ones(3), 0.25)
    points = np.array(
        [[0.1, 0.1, 0.1], [0.2, 0.2, 0.2], [0.6, 0.1, 0.1], [0.9, 0.9, 0.9], [2.0, 0.1, 0.1]]
    )
    got = surface_voxels(spec, points, np.zeros(3), np.array([0.7, 0.7, 0.7]))
    want, _ = spec.flat_index(points[[0, 2]])  # the second shares the first's voxel
    np.testing.assert_array_equal(got, np.sort(want))


def test_map_shares_count_each_voxel_by_what_the_map_holds_and_refuse_an_empty_surface():
    occupancy = np.array([-1, 0, 1, 1, 0, -1], np.int8)
    shares = map_shares(occupancy, np.array([0, 1, 2, 3]))
    assert shares == {"free": 0.25, "unknown": 0.25, "occupied": 0.5}
    with pytest.raises(ValueError, match="surface voxels"):
        map_shares(occupancy, np.array([], np.int64))


def test_a_run_is_replayed_with_its_own_parameters_and_a_guess_at_confidence_zero_carves_nothing(
    tmp_path,
):
    """Views of single_object with perception's depth 5 cm behind the surface: at a confidence
    the rays carve through the real surface; at confidence 0 (a refused match) they carve
    nothing, so no surface voxel is free; under `uniform_confidence` (the `no_ff` ablation,
    which reads every depth as certain) the same frames carve again. The camera's own depth
    holds the surface occupied far more than any of them, and free far less."""
    from area3d_bringup.launch_description import planner_region
    from area3d_perception.sensor_model import rgbd_confidence
    from sim_bridge.render import RgbdRenderer
    from sim_bridge.scenes import load_scene

    scene = load_scene("single_object")
    poses = np.asarray(scene.initial_views)
    region = planner_region(scene)
    with RgbdRenderer(scene, 96, 72) as renderer:
        shots = [renderer.render(T) for T in poses]
        K = renderer.K
    runs = {
        "right": (0.0, 1.0, {}),
        "behind": (0.05, 1.0, {}),
        "refused": (0.05, 0.0, {}),
        "refused_no_ff": (0.05, 0.0, {"uniform_confidence": True}),
    }
    for name, (offset, scale, planner) in runs.items():
        run = tmp_path / name
        views = [
            {"index": i, "kind": "initial", "T_world_cam": T.tolist()} for i, T in enumerate(poses)
        ]
        write_episode(
            run,
            {"scene": "single_object", "policy": name, "seed": 0, "views": views,
             "depth_source": "estimated", "config": {"planner": {**region, **planner}}},
        )  # fmt: skip
        for i, ((rgb, depth), T) in enumerate(zip(shots, poses, strict=True)):
            confidence = rgbd_confidence(depth, K) * np.float32(scale)
            estimated = depth + np.float32(offset)
            write_frame(run, i, rgb, depth, K, T, 0, estimated, confidence, confidence)
    result = run_bench(tmp_path, num_surface_points=4000)
    assert json.loads((tmp_path / OUT_FILE).read_text()) == json.loads(json.dumps(result))
    assert not result["errors"]
    got = {row["policy"]: row for row in result["runs"]}
    for row in got.values():
        assert row["free"] + row["unknown"] + row["occupied"] == pytest.approx(1.0)
        assert row["surface_voxels"] > 100
    assert got["refused"]["free"] == 0.0
    assert got["behind"]["free"] > 0.5
    assert got["refused_no_ff"]["free"] == pytest.approx(got["behind"]["free"])
    # the camera's own depth carves a little through the surface too (rays that end just behind
    # a voxel the surface crosses at a corner), far less than depth behind the surface
    assert got["right"]["free"] < got["behind"]["free"] / 3
    assert got["right"]["occupied"] > 2 * got["behind"]["occupied"]
