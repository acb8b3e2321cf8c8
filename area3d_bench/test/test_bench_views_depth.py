"""`area3d bench views-depth`: which runs it reads, the share of right depths in the region, the
means over seeds, and its refusals."""

from __future__ import annotations

import json

import numpy as np
import pytest

from area3d_bench.views_depth import find_runs, right_share, run_bench, summarise
from area3d_eval.rundir import write_episode, write_frame

K = np.array([[50.0, 0.0, 20.0], [0.0, 50.0, 15.0], [0.0, 0.0, 1.0]])


def _frame_pair(rng):
    """A 30x40 view of a wall at 1 m whose left half lies in the region (x < 0), and an estimate
    that is right on a known set of the region's pixels."""
    depth = np.full((30, 40), 1.0, np.float32)
    estimated = depth.copy()
    region = np.zeros_like(depth, bool)
    region[:, :20] = True  # u < 20: x = (u - 20) / 50 < 0
    wrong = region & (rng.random(depth.shape) < 0.3)
    estimated[wrong] += 0.05  # 5 cm off: wrong
    estimated[region & ~wrong & (rng.random(depth.shape) < 0.1)] = np.nan  # no estimate
    estimated[~region] += 0.5  # outside the region: not counted, however wrong
    right = region & ~wrong & np.isfinite(estimated)
    return depth, estimated, right


def test_right_share_counts_the_regions_pixels_within_a_centimetre_and_a_percent():
    depth, estimated, right = _frame_pair(np.random.default_rng(0))
    roi_min, roi_max = np.array([-5.0, -5.0, 0.0]), np.array([-1e-6, 5.0, 5.0])
    got_right, counted = right_share(estimated, depth, K, np.eye(4), roi_min, roi_max)
    assert counted == 30 * 20
    assert got_right == right.sum()
    # 1 cm + 1 % of the camera's depth (not of the estimate's): at 3 m, 3.98 cm off is right and
    # 4.02 cm is not (1 % of the estimate would make both right)
    wall = np.full_like(depth, 3.0)
    for offset, expected in ((0.0398, 600), (0.0402, 0)):
        near = wall + np.float32(offset)
        assert right_share(near, wall, K, np.eye(4), roi_min, roi_max)[0] == expected
    # a pixel without camera depth is not counted
    holes = depth.copy()
    holes[:, :5] = np.nan
    assert right_share(estimated, holes, K, np.eye(4), roi_min, roi_max)[1] == 30 * 15


def test_summarise_takes_means_over_the_seeds_of_each_scene_and_policy():
    rows = [
        {"scene": "a", "policy": "p", "completion": 0.5, "camera_completion": 0.7, "psnr": 20.0,
         "camera_psnr": 24.0, "planned_right": 0.6},
        {"scene": "a", "policy": "p", "completion": 0.7, "camera_completion": 0.9, "psnr": 22.0,
         "camera_psnr": 26.0, "planned_right": None},
        {"scene": "a", "policy": "q", "completion": 0.1, "camera_completion": 0.2, "psnr": None,
         "camera_psnr": None, "planned_right": 0.2},
    ]  # fmt: skip
    s = summarise(rows)
    assert set(s) == {("a", "p"), ("a", "q")}
    assert s[("a", "p")]["seeds"] == 2
    assert s[("a", "p")]["completion"] == pytest.approx(0.6)
    assert s[("a", "p")]["camera_psnr"] == pytest.approx(25.0)
    assert s[("a", "p")]["planned_right"] == pytest.approx(0.6)  # the seed that has it
    assert s[("a", "q")]["psnr"] is None


def _run(root, name, depth_source, frames=True, scene="single_object"):
    run = root / name
    views = [{"index": 0, "kind": "initial", "T_world_cam": np.eye(4).tolist()}]
    write_episode(
        run, {"scene": scene, "policy": "p", "views": views, "depth_source": depth_source}
    )
    if frames:
        rgb = np.zeros((30, 40, 3), np.uint8)
        depth = np.ones((30, 40), np.float32)
        write_frame(run, 0, rgb, depth, K, np.eye(4), estimated_depth=depth, confidence=depth)
    return run


def test_only_runs_recorded_with_estimated_depth_and_frames_are_read(tmp_path):
    estimated = _run(tmp_path / "bench", "a_p_s0", "estimated")
    _run(tmp_path / "bench", "a_p_s1", "sensor")
    _run(tmp_path / "bench", "a_p_s2", "estimated", frames=False)
    assert find_runs(tmp_path) == [estimated]


def test_a_folder_without_such_runs_is_refused_naming_it(tmp_path):
    _run(tmp_path, "a_p_s0", "sensor")
    with pytest.raises(ValueError, match="run root: got .*expected run directories recorded"):
        run_bench(tmp_path)
    with pytest.raises(ValueError, match="run root: got .*expected an existing folder"):
        run_bench(tmp_path / "missing")


def test_a_runs_views_are_rebuilt_from_the_cameras_depth(tmp_path):
    """Runs of single_object whose planned views' estimates are 5 cm behind the camera's depth:
    as run they lose completion, rebuilt from the camera's depth at the same views they do not,
    and none of their planned views' region pixels is right. With the camera's depth as the
    estimate both evaluations agree and every region pixel with a depth is right. A run without
    planned views has no right share; a broken one is reported, not fatal."""
    from area3d_bench.views_depth import OUT_FILE, _as_run
    from area3d_perception.sensor_model import rgbd_confidence
    from sim_bridge.render import RgbdRenderer
    from sim_bridge.scenes import load_scene

    scene = load_scene("single_object")
    poses = np.concatenate([scene.initial_views, scene.eval_views[:2]])
    small = {"eval_width": 64, "eval_height": 48, "num_surface_points": 4000}
    with RgbdRenderer(scene, 96, 72) as renderer:
        shots = [renderer.render(T) for T in poses]
        for name, offset, count in (("same", 0.0, 6), ("behind", 0.05, 6), ("first", 0.0, 4)):
            run = tmp_path / name
            views = [
                {"index": i, "kind": "initial" if i < 4 else "planned", "T_world_cam": T.tolist()}
                for i, T in enumerate(poses[:count])
            ]
            write_episode(
                run,
                {"scene": "single_object", "policy": name, "seed": 0, "views": views,
                 "depth_source": "estimated"},
            )  # fmt: skip
            for i, ((rgb, depth), T) in enumerate(zip(shots[:count], poses[:count], strict=True)):
                estimated = depth + np.float32(offset if i >= 4 else 0.0)
                weight = rgbd_confidence(depth, renderer.K)
                write_frame(run, i, rgb, depth, renderer.K, T, 0, estimated, weight, weight)
    broken = _run(tmp_path, "broken", "estimated", scene="no_such_scene")
    result = run_bench(tmp_path, **small)
    assert json.loads((tmp_path / OUT_FILE).read_text()) == json.loads(json.dumps(result))
    figures = {row["policy"]: row for row in result["runs"]}
    same, behind, first = figures["same"], figures["behind"], figures["first"]
    assert same["scene"] == "single_object" and same["seed"] == 0
    assert same["completion"] == pytest.approx(same["camera_completion"])
    assert same["planned_right"] == 1.0
    assert behind["camera_completion"] == pytest.approx(same["camera_completion"])
    assert behind["completion"] < same["completion"]
    assert behind["planned_right"] == 0.0
    assert first["planned_right"] is None
    assert [e["run"] for e in result["errors"]] == [str(broken)]
    assert set(result["policy_means"]) == {"same", "behind", "first"}
    # the run's own metrics.json is read when it was evaluated from the estimated depth, and
    # only then (nor when other evaluation settings are asked for)
    checkpoints = [6]
    metrics = {"depth_source": "estimated", "final": {"completion": 123.0}}
    (tmp_path / "same" / "metrics.json").write_text(json.dumps(metrics))
    assert _as_run(tmp_path / "same", scene, {}, checkpoints)["completion"] == 123.0
    assert _as_run(tmp_path / "same", scene, small, checkpoints)["completion"] < 1.0
    metrics["depth_source"] = "sensor"
    (tmp_path / "behind" / "metrics.json").write_text(json.dumps(metrics))
    again = _as_run(tmp_path / "behind", scene, {}, checkpoints)
    assert again["completion"] < 1.0  # evaluated again, from the estimated depth


def test_a_policys_mean_is_over_its_scenes_and_only_where_every_scene_has_the_figure():
    from area3d_bench.views_depth import policy_means

    cell = {"seeds": 3, "completion": 0.5, "camera_completion": 0.6, "psnr": 20.0,
            "camera_psnr": 22.0, "planned_right": 0.7}  # fmt: skip
    summary = {("a", "p"): cell, ("b", "p"): {**cell, "completion": 0.9, "psnr": None}}
    means = policy_means(summary)["p"]
    assert means["scenes"] == 2
    assert means["completion"] == pytest.approx(0.7)
    assert means["camera_completion"] == pytest.approx(0.6)
    assert means["psnr"] is None
