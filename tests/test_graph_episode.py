"""A whole episode over the node graph: five node processes, the runner, the wire, the maps it
saves, the report."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from rosbags.rosbag2 import Reader
from rosbags.typesys import Stores, get_typestore

from area3d_bringup.runner import EpisodeConfig, run_episode
from area3d_eval.report import write_report
from sim_bridge.scenes import load_scene
from sim_bridge.validity import check_pose

# Poses of the same view over the graph and in process: a view chosen differently is centimetres
# and degrees away; the same view differs by the quaternion round trips (about 1e-7).
POSE_TOLERANCE = 1e-4
# the planner waits for each request's frame as long as it takes (on a busy machine a frame may
# take more than the default 5 s, and a plan without it would choose other views)
SMALL_CAMERA = {
    "sim_bridge": {"width": 320, "height": 240},
    "planner": {"width": 320, "height": 240, "sync_timeout_s": 120.0},
}


@pytest.fixture(scope="module")
def episode(tmp_path_factory: pytest.TempPathFactory) -> Path:
    config = EpisodeConfig(
        scene="single_object",
        policy="area3d",
        budget=7,
        seed=0,
        out_dir=tmp_path_factory.mktemp("runs"),
        run_name="episode",
        overrides=SMALL_CAMERA,
    )
    return run_episode(config)


def test_the_episode_captures_exactly_the_budget_initial_views_first(episode):
    data = json.loads((episode / "episode.json").read_text())
    scene = load_scene("single_object")
    kinds = [v["kind"] for v in data["views"]]
    assert kinds == ["initial"] * 4 + ["planned"] * 3
    assert len(list((episode / "frames").glob("*.npz"))) == 7
    for view, T0 in zip(data["views"][:4], scene.initial_views, strict=True):
        np.testing.assert_allclose(np.array(view["T_world_cam"]), T0, atol=1e-6)
    stamps = [v["stamp_ns"] for v in data["views"]]
    assert stamps == sorted(stamps) and len(set(stamps)) == 7


def test_planned_views_are_valid_new_poses_the_camera_accepted(episode):
    data = json.loads((episode / "episode.json").read_text())
    scene = load_scene("single_object")
    poses = [np.array(v["T_world_cam"]) for v in data["views"]]
    for T in poses[4:]:
        assert check_pose(scene, T).ok
        assert min(np.linalg.norm(T[:3, 3] - P[:3, 3]) for P in poses[:4]) > 0.05
    with np.load(episode / "frames" / "0006.npz") as frame:
        assert frame["rgb"].shape == (240, 320, 3) and frame["depth"].dtype == np.float32
        assert np.isfinite(frame["depth"]).any()
        np.testing.assert_allclose(frame["T_world_cam"], poses[6])


def test_the_in_process_path_chooses_the_views_the_graph_chose(episode, tmp_path):
    """Same scene, preset, seed and parameters: the same views, in the same order (the graph's
    poses went through quaternions and the scene file's rounding: a tight tolerance, not ==)."""
    from area3d_bringup.inprocess import run_inprocess_episode
    from area3d_eval.rundir import read_episode

    graph = read_episode(episode)
    in_process = read_episode(
        run_inprocess_episode("single_object", "area3d", 0, tmp_path, 7, overrides=SMALL_CAMERA)
    )
    assert in_process.kinds() == graph.kinds()
    np.testing.assert_allclose(in_process.poses(), graph.poses(), atol=POSE_TOLERANCE)
    # both say where the semantic regions came from: the heuristic analyser, used as asked
    used = {"backend": "heuristic", "fallback_used": None, "error": ""}
    assert graph.semantics == used and in_process.semantics == used


def test_a_mission_resumed_from_the_map_the_graph_saved_chooses_the_next_view_of_one_not_stopped(
    episode, tmp_path
):
    """At its end the episode saved the graph's maps over the services (maps/). The planner's,
    loaded into a planner given one view more, answers with the view that the same mission with
    that budget, never stopped, takes next (the in-process path: it chooses the graph's views,
    the test above). The volume and the live mesh were saved beside it."""
    import yaml

    import area3d_planner.node as planner_node
    from area3d_bringup.inprocess import run_inprocess_episode
    from area3d_eval.open3d_loader import import_open3d
    from area3d_eval.rundir import read_episode
    from area3d_msgs_py import mapfile
    from area3d_msgs_py.parameters import parameter_values
    from area3d_planner import map_io
    from area3d_planner.requests import PlanRequest
    from area3d_planner.server import NextBestViewServer

    graph = read_episode(episode)
    maps = episode / "maps"
    given = yaml.safe_load((episode / "params.yaml").read_text())["/**/planner"]["ros__parameters"]
    config = planner_node.config_from_parameters(
        parameter_values(planner_node.PARAMS, {**given, "budget": 8})
    )
    resumed = NextBestViewServer(config)
    map_io.restore(resumed, map_io.read(resumed, maps / "planner.a3map"))
    last = graph.views[-1]
    plan = resumed.plan_views(PlanRequest(np.asarray(last["T_world_cam"]), last["stamp_ns"], 1))
    assert plan.reason == "" and len(plan.poses) == 1
    never_stopped = read_episode(
        run_inprocess_episode("single_object", "area3d", 0, tmp_path, 8, overrides=SMALL_CAMERA)
    )
    np.testing.assert_allclose(plan.poses[0], never_stopped.poses()[-1], atol=POSE_TOLERANCE)

    volume = mapfile.read_map(maps / "reconstruction.a3map", "reconstruction")
    assert volume.header["frames"] == len(graph.views) and volume.header["blocks"] > 0
    mesh = import_open3d().io.read_triangle_mesh(str(maps / "mesh.ply"))
    vertices = np.asarray(mesh.vertices)
    assert len(mesh.triangles) > 1000 and mesh.has_vertex_colors()
    assert np.all(vertices >= np.asarray(given["roi_min"]) - 1e-6)
    assert np.all(vertices <= np.asarray(given["roi_max"]) + 1e-6)


def test_the_planner_published_the_latched_grid_before_and_after(episode):
    with (
        np.load(episode / "grid_initial.npz") as before,
        np.load(episode / "grid_final.npz") as after,
    ):
        for name in ("x", "y", "z", "uncertainty", "geometric", "semantic", "occupancy"):
            assert name in before and name in after
        assert np.all(np.isfinite(after["uncertainty"]))
        # more views observed more of the scene: more occupied voxels are known afterwards
        assert np.sum(after["occupancy"] > 0) > np.sum(before["occupancy"] > 0)


def test_the_episode_bag_holds_the_camera_stream_and_every_output_of_the_graph(episode):
    """Read back with the mcap library alone (no ROS, no project code): ROS 2 CDR with the
    message definitions, and per topic as many messages as episode.json says were recorded."""
    from mcap.reader import make_reader

    (mcap_file,) = (episode / "bag").glob("*.mcap")
    counts: dict[str, int] = {}
    schemas: dict[str, tuple[str, str, str]] = {}
    with mcap_file.open("rb") as stream:
        for schema, channel, _message in make_reader(stream).iter_messages():
            counts[channel.topic] = counts.get(channel.topic, 0) + 1
            schemas[channel.topic] = (
                channel.message_encoding,
                schema.encoding,
                schema.name,
                schema.data.decode(),
            )
    recorded = json.loads((episode / "episode.json").read_text())["recorded"]
    assert counts == recorded
    views = 7
    for topic in (
        "/area3d/camera/goal_pose",
        "/area3d/camera/color/image_raw",
        "/area3d/camera/depth/image_raw",
        "/area3d/camera/camera_info",
        "/area3d/camera/pose",
        "/area3d/camera/status",
        "/tf",
        "/area3d/perception/depth",
        "/area3d/perception/confidence",
        "/area3d/perception/weight",
    ):
        assert counts[topic] == views, topic
    assert counts["/tf_static"] >= 1
    assert counts["/area3d/semantics/regions"] >= 1
    assert counts["/area3d/semantics/weight"] == 4  # one per initial view
    assert counts["/area3d/semantics/uncertainty"] == 4
    # a grid after every fusion, except while the next frame already waits: the 4 initial views
    # arrive in a burst, so at least the last of them and every planned view
    assert counts["/area3d/planner/uncertainty_grid"] >= views - 4 + 1
    assert counts["/area3d/planner/next_views"] >= 1 and counts["/area3d/planner/status"] >= views
    encoding, schema_encoding, name, text = schemas["/area3d/planner/uncertainty_grid"]
    assert (encoding, schema_encoding, name) == ("cdr", "ros2msg", "sensor_msgs/msg/PointCloud2")
    assert "PointField[] fields" in text and "MSG: sensor_msgs/PointField" in text
    assert schemas["/tf"][2] == "tf2_msgs/msg/TFMessage"
    assert "storage_identifier: mcap" in (episode / "bag" / "metadata.yaml").read_text()
    # and rosbags (what `ros2 bag` tooling builds on) decodes it
    with Reader(episode / "bag") as reader:
        color = next(c for c in reader.connections if c.topic.endswith("color/image_raw"))
        raw = [raw for _, _, raw in reader.messages([color])][-1]
        image = get_typestore(Stores.ROS2_JAZZY).deserialize_cdr(raw, color.msgtype)
    assert image.encoding == "rgb8" and image.width == 320


def test_evaluation_and_report_of_the_episode(episode):
    md, html = write_report([episode], episode / "report")
    metrics = json.loads((episode / "metrics.json").read_text())
    curve = metrics["curve"]
    assert [point["num_views"] for point in curve][-1] == 7
    assert (
        metrics["final"]["completion"] >= curve[0]["completion"] - 1e-3
    )  # views never hurt coverage
    assert 0.5 < metrics["final"]["completion"] <= 1.0
    text = html.read_text()
    assert "single_object" in text and "area3d" in text
    for image in (episode / "report" / "figures").glob("*.png"):
        assert image.name in md.read_text()


def test_a_node_dying_mid_episode_is_named_and_the_episode_resumes(tmp_path, child_pids, cmdline):
    base = [
        sys.executable,
        "-m",
        "area3d_bringup.cli",
        "run",
        "--scene",
        "single_object",
        "--budget",
        "9",
        "--out",
        str(tmp_path),
        "--no-evaluate",
        "--no-record",
        "-p",
        "sim_bridge.width=320",
        "-p",
        "sim_bridge.height=240",
        "-p",
        "planner.width=320",
        "-p",
        "planner.height=240",
    ]
    runner = subprocess.Popen(base, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 120
        frames: list[Path] = []
        while time.monotonic() < deadline and len(frames) < 5 and runner.poll() is None:
            frames = list(tmp_path.glob("*/frames/[0-9][0-9][0-9][0-9].npz"))
            time.sleep(0.05)
        assert len(frames) >= 5, "the episode did not get going"
        planner = [p for p in child_pids(runner.pid) if "area3d_planner.node" in cmdline(p)]
        assert len(planner) == 1
        os.kill(planner[0], signal.SIGKILL)
        _, err = runner.communicate(timeout=60)
    finally:
        if runner.poll() is None:
            runner.kill()
    assert runner.returncode != 0
    assert "planner" in err and "--resume" in err
    run_dir = next(tmp_path.iterdir())
    kept = json.loads((run_dir / "episode.json").read_text())["views"]
    assert 5 <= len(kept) < 9 and len(list((run_dir / "frames").glob("*.npz"))) == len(kept)

    resumed = subprocess.run(
        [*base, "--resume", str(run_dir)], capture_output=True, text=True, timeout=180
    )
    assert resumed.returncode == 0, resumed.stderr[-2000:]
    views = json.loads((run_dir / "episode.json").read_text())["views"]
    assert len(views) == 9
    assert [v["T_world_cam"] for v in views[: len(kept)]] == [v["T_world_cam"] for v in kept]


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--policy", "best_one"], "policy: got 'best_one'"),
        (["--scene", "no_such_scene"], "no_such_scene"),
        (["--mode", "sideways"], "mode: got 'sideways'"),
        (["--budget", "2"], "budget: got 2"),
        (["--domain-id", "999"], "ROS_DOMAIN_ID: got 999"),  # it left an empty run directory
    ],
)
def test_bad_episode_arguments_are_rejected_with_a_clear_message(tmp_path, args, message):
    result = subprocess.run(
        [sys.executable, "-m", "area3d_bringup.cli", "run", "--out", str(tmp_path), *args],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 2
    assert message in result.stderr
    assert "Traceback" not in result.stderr
    assert not any(tmp_path.iterdir()), "a rejected run must not leave a run directory"


def test_an_unreadable_scene_file_is_named(tmp_path):
    bad = tmp_path / "broken.xml"
    bad.write_text("<mujoco><worldbody><geom type='box'")
    result = subprocess.run(
        [
            sys.executable,
            "-m",
            "area3d_bringup.cli",
            "run",
            "--scene",
            str(bad),
            "--out",
            str(tmp_path / "runs"),
        ],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 2
    assert "broken.xml" in result.stderr and "Traceback" not in result.stderr


def test_a_camera_with_lens_distortion_is_mapped_and_kept_as_the_pinhole_camera_k(tmp_path):
    """The simulated camera sends raw images of a barrel lens (k1 -0.3) with d in its camera
    info; perception and semantics undistort them, and the run directory keeps each frame
    undistorted into k, so that its depth, back-projected with k, lies on the scene's surfaces
    (the raw frame, read as a pinhole camera's, lies centimetres off them at the edges)."""
    from scipy.spatial import cKDTree

    from area3d_msgs_py.backproject import backproject
    from area3d_msgs_py.lens import distortion

    d = [-0.3, 0.1, 0.0, 0.0, 0.0]
    overrides = {
        **SMALL_CAMERA,
        "sim_bridge": {**SMALL_CAMERA["sim_bridge"], "lens_d": d, "depth_noise": False},
    }
    config = EpisodeConfig(
        scene="single_object", policy="area3d", budget=5, seed=0, out_dir=tmp_path,
        run_name="lens", overrides=overrides,
    )  # fmt: skip
    run = run_episode(config)
    log = (run / "nodes.log").read_text()
    assert "left camera: distortion_model 'plumb_bob'" in log and "undistorted into k" in log
    # the scene's solid surfaces (the floor plane is none: its points lie metres off, in both)
    surface = cKDTree(load_scene("single_object").scene_mesh().sample(400_000, seed=0))
    for path in sorted((run / "frames").glob("*.npz")):
        with np.load(path) as frame:
            depth, K, T = frame["depth"], frame["K"], frame["T_world_cam"]
        off = np.median(surface.query(backproject(depth, K, T)[0])[0])
        raw = distortion(K, depth.shape[1], depth.shape[0], d).depth(depth)
        raw_off = np.median(surface.query(backproject(raw, K, T)[0])[0])
        # measured: 1.2-1.5 mm kept, 5.7-12.5 mm raw
        assert off < 0.003 and raw_off > 3 * off, (path.name, off, raw_off)
