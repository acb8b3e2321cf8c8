"""The live view as a Foxglove user gets it: Foxglove's own client (npm: @foxglove/ws-protocol,
@foxglove/rosmsg, @foxglove/rosmsg2-serialization, locked in tests/foxglove_client) connects to
`area3d run --foxglove PORT` and decodes what the graph publishes from the CDR the bridge forwards
as-is; its pixels, poses and grids are what the run saved. A client that stops reading, or
vanishes, does not slow the graph or the other clients."""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from area3d_bringup.foxglove_bridge import DEFAULT_BACKLOG
from area3d_msgs_py import codecs, msgs, qos
from area3d_msgs_py.probe import Probe

REPO_ROOT = Path(__file__).resolve().parents[1]
CLIENT_DIR = REPO_ROOT / "tests" / "foxglove_client"
TIMEOUT_S = 300.0  # a whole episode on a loaded 2-core machine
NODE = shutil.which("node")

pytestmark = pytest.mark.skipif(
    NODE is None, reason="Node.js is not installed: Foxglove's client runs on it"
)

GRID_FIELDS = ["x", "y", "z", "uncertainty", "geometric", "semantic", "occupancy", "hard"]
TOPICS = {
    "/area3d/camera/color/image_raw": "sensor_msgs/msg/Image",
    "/area3d/camera/depth/image_raw": "sensor_msgs/msg/Image",
    "/area3d/perception/depth": "sensor_msgs/msg/Image",
    "/area3d/perception/confidence": "sensor_msgs/msg/Image",
    "/area3d/planner/uncertainty_grid": "sensor_msgs/msg/PointCloud2",
    "/area3d/planner/next_views": "nav_msgs/msg/Path",
    "/area3d/planner/view_markers": "visualization_msgs/msg/MarkerArray",
    "/area3d/planner/hard_regions": "area3d_interfaces/msg/HardRegionArray",
    "/area3d/planner/hard_region_markers": "visualization_msgs/msg/MarkerArray",
    "/area3d/reconstruction/mesh": "visualization_msgs/msg/Marker",
    "/diagnostics": "diagnostic_msgs/msg/DiagnosticArray",
    "/tf": "tf2_msgs/msg/TFMessage",
    "/tf_static": "tf2_msgs/msg/TFMessage",
}


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


PLAN_TOPICS = ["/area3d/planner/next_views", "/area3d/planner/view_markers"]


def client(
    port: int, topics: list[str], count: int, timeout_s: float, stay: bool = False, stdout=None
) -> subprocess.Popen:
    """Foxglove's client on `topics`: it exits 0 once each gave `count` messages (with `stay`:
    at SIGTERM, if they had by then), printing one JSON line per message to a pipe, or to the
    file `stdout` (a pipe nobody reads while the client runs blocks it once 64 KB are written:
    it then stops reading its socket, and the bridge drops what it cannot send)."""
    if not (CLIENT_DIR / "node_modules" / "@foxglove" / "ws-protocol").is_dir():
        pytest.fail(
            f"Foxglove's client is not installed: run `make install` (npm ci in {CLIENT_DIR})"
        )
    return subprocess.Popen(
        [
            NODE,
            str(CLIENT_DIR / "client.mjs"),
            *("--url", f"ws://localhost:{port}", "--topics", ",".join(topics)),
            *("--count", str(count), "--timeout", str(timeout_s), "--stay", str(int(stay))),
        ],
        stdout=subprocess.PIPE if stdout is None else stdout,
        stderr=subprocess.PIPE,
        text=True,
    )


def lines(text: str) -> list[dict]:
    return [json.loads(line) for line in text.splitlines() if line.startswith("{")]


def test_foxglove_client_decodes_a_running_episode_from_the_forwarded_cdr(tmp_path):
    port = free_port()
    run = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "area3d_bringup.cli",
            "run",
            *("--scene", "single_object", "--budget", "9", "--out", str(tmp_path)),
            *("--no-evaluate", "--no-record", "--depth-source", "estimated"),
            *("-p", "sim_bridge.width=320", "-p", "sim_bridge.height=240"),
            *("-p", "planner.width=320", "-p", "planner.height=240"),
            *("--foxglove", str(port)),
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    # the viewer watches the whole episode, then is told to stop; a second client watches the
    # plans alone (the bridge drops the oldest of what a client's 16-message queue holds: the
    # viewer's is shared by every image and grid, the plans' never fills)
    viewer_log, plans_log = tmp_path / "viewer.jsonl", tmp_path / "plans.jsonl"
    with viewer_log.open("w") as log, plans_log.open("w") as plans_out:
        viewer = client(port, list(TOPICS), count=1, timeout_s=2 * TIMEOUT_S, stay=True, stdout=log)
        plans = client(
            port, PLAN_TOPICS, count=1, timeout_s=2 * TIMEOUT_S, stay=True, stdout=plans_out
        )
    try:
        run_out, run_err = run.communicate(timeout=TIMEOUT_S)
        for watcher in (viewer, plans):
            watcher.send_signal(signal.SIGTERM)
        _, err = viewer.communicate(timeout=60)
        _, plans_err = plans.communicate(timeout=60)
        out = viewer_log.read_text()
    finally:
        for process in (viewer, plans, run):
            if process.poll() is None:
                process.kill()
    events = lines(out)
    assert viewer.returncode == 0, f"client: {events[-1:]} {err[-2000:]}\nrun: {run_err[-3000:]}"
    assert plans.returncode == 0, plans_err[-2000:]
    assert run.returncode == 0, run_err[-3000:]
    assert f"Foxglove live view on ws://localhost:{port}" in run_err
    run_dir = next(p for p in tmp_path.iterdir() if p.is_dir())
    assert "[foxglove_bridge]" in (run_dir / "nodes.log").read_text()
    assert events[0] == {"connected": f"ws://localhost:{port}", "protocol": "foxglove.sdk.v1"}

    advertised = {e["advertised"]: e for e in events if "advertised" in e}
    for topic, type_name in TOPICS.items():
        assert advertised[topic]["schemaName"] == type_name
        assert (advertised[topic]["encoding"], advertised[topic]["schemaEncoding"]) == (
            "cdr",
            "ros2msg",
        )
    # topics of nodes the bridge knows nothing about are forwarded too (ROS's own /rosout)
    assert advertised["/rosout"]["schemaName"] == "rcl_interfaces/msg/Log"

    episode = json.loads((run_dir / "episode.json").read_text())
    frames = {}
    for path in sorted((run_dir / "frames").glob("*.npz")):
        with np.load(path) as frame:
            frames[int(frame["stamp_ns"])] = {k: frame[k] for k in frame.files}
    assert len(frames) == 9
    received: dict[str, list[dict]] = {}
    for e in events:
        if "topic" in e:
            received.setdefault(e["topic"], []).append(e["summary"])

    # colour and depth: the pixels of the frames the run saved, decoded by Foxglove's reader
    for color in received["/area3d/camera/color/image_raw"]:
        saved = frames[int(color["stamp_ns"])]
        assert (color["encoding"], color["width"], color["height"]) == ("rgb8", 320, 240)
        assert color["sum"] == int(saved["rgb"].astype(np.int64).sum())
    for topic, key in (
        ("/area3d/camera/depth/image_raw", "depth"),
        ("/area3d/perception/depth", "estimated_depth"),
        ("/area3d/perception/confidence", "confidence"),
    ):
        for image in received[topic]:
            expected = frames[int(image["stamp_ns"])][key].astype(np.float64)
            finite = np.isfinite(expected)
            assert (image["encoding"], image["width"], image["height"]) == ("32FC1", 320, 240)
            assert image["finite"] == int(finite.sum()), topic
            assert image["sum"] == pytest.approx(expected[finite].sum(), rel=1e-9), topic
            assert image["min"] == pytest.approx(expected[finite].min()), topic
    for confidence in received["/area3d/perception/confidence"]:
        assert 0.0 <= confidence["min"] and confidence["max"] <= 1.0

    # the grid: its fields, uncertainties >= 0 (geometric in [0, 1]), voxels around the region
    planner = yaml.safe_load((run_dir / "params.yaml").read_text())["/**/planner"]
    roi_min = np.array(planner["ros__parameters"]["roi_min"])
    roi_max = np.array(planner["ros__parameters"]["roi_max"])
    for grid in received["/area3d/planner/uncertainty_grid"]:
        assert grid["names"] == GRID_FIELDS and grid["points"] > 0
        assert grid["frame_id"] == "world"
        assert grid["fields"]["uncertainty"]["min"] >= 0.0
        geometric = grid["fields"]["geometric"]
        assert 0.0 <= geometric["min"] <= geometric["max"] <= 1.0
        low = [grid["fields"][axis]["min"] for axis in "xyz"]
        high = [grid["fields"][axis]["max"] for axis in "xyz"]
        assert np.all(np.array(low) >= roi_min - 0.25) and np.all(np.array(high) <= roi_max + 0.25)

    # the mesh: triangles with a colour per corner, in world, inside the region (and its margin)
    for mesh in received["/area3d/reconstruction/mesh"]:
        assert (mesh["frame_id"], mesh["ns"], mesh["type"]) == ("world", "reconstruction", 11)
        if mesh["points"]:
            assert mesh["points"] % 3 == 0 and mesh["colors"] == mesh["points"]
            assert 0.0 <= mesh["color_range"][0] <= mesh["color_range"][1] <= 1.0
            assert np.all(np.array(mesh["min"]) >= roi_min - 0.01)
            assert np.all(np.array(mesh["max"]) <= roi_max + 0.01)
    assert any(mesh["points"] for mesh in received["/area3d/reconstruction/mesh"])

    # the planned views: every view the camera was sent to is the first pose of a decoded plan
    planned_events = [e for e in lines(plans_log.read_text()) if "topic" in e]
    for topic in PLAN_TOPICS:  # the viewer got them too, as many as its queue kept
        assert received[topic], topic
        received[topic] = [e["summary"] for e in planned_events if e["topic"] == topic]
    paths = received["/area3d/planner/next_views"]
    for path in paths:
        assert path["frame_id"] == "world"
        for pose in path["poses"]:
            assert np.linalg.norm(pose[3:]) == pytest.approx(1.0, abs=1e-9)
    firsts = [codecs.pose_to_matrix(_pose_msg(p["poses"][0])) for p in paths if p["poses"]]
    planned = [np.array(v["T_world_cam"]) for v in episode["views"] if v["kind"] == "planned"]
    assert len(planned) == 5
    for T in planned:
        assert any(np.allclose(T, first, atol=1e-6) for first in firsts)
    # and their frustums: one LINE_LIST per view of the plan, the apex at the view's centre
    by_stamp = {p["stamp_ns"]: p for p in paths}
    for markers in received["/area3d/planner/view_markers"]:
        path = by_stamp[markers["stamp_ns"]]
        lines_ = [m for m in markers["markers"] if m["type"] == 5]
        assert len(lines_) == len(path["poses"])
        for marker, pose in zip(lines_, path["poses"], strict=True):
            assert len(marker["points"]) == 16 and marker["frame_id"] == "world"
            assert marker["points"][0] == pytest.approx(pose[:3])

    # diagnostics: every node's facts with its level
    statuses = [s for d in received["/diagnostics"] for s in d["status"]]
    names = {
        "sim_bridge: status", "perception: status", "semantics: status", "planner: status",
        "reconstruction: status", "foxglove_bridge: status",
    }  # fmt: skip
    assert names <= {s["name"] for s in statuses}
    assert all(s["level"] in (0, 1, 2) for s in statuses)
    assert all(
        "rejected.total" in s["values"] for s in statuses if s["name"] != "foxglove_bridge: status"
    )
    bridge = [s["values"] for s in statuses if s["name"] == "foxglove_bridge: status"]
    assert int(bridge[-1]["messages_forwarded"]) > 0
    planner_facts = [s["values"] for s in statuses if s["name"] == "planner: status"]
    assert all("hard_regions" in v and "workers.fusion" in v for v in planner_facts)

    # TF: the camera's link at every capture, its optical frame under it (latched)
    transforms = [t for m in received["/tf"] for t in m["transforms"]]
    links = [t for t in transforms if (t["parent"], t["child"]) == ("world", "camera_link")]
    assert len(links) >= 1
    for link in links:
        assert np.linalg.norm(link["rotation"]) == pytest.approx(1.0, abs=1e-9)
    static = [t for m in received["/tf_static"] for t in m["transforms"]]
    assert ("camera_link", "camera_optical_frame") in {(t["parent"], t["child"]) for t in static}

    # hard regions: every region set holds exactly the hard voxels of the grid of its stamp,
    # largest first, and its boxes are drawn where the regions are
    # (a semantic map fused for an earlier frame publishes the grid again with that frame's stamp,
    # so a stamp can come with more than one grid: the regions are those of one of them)
    hard_sums: dict[str, set] = {}
    for grid in received["/area3d/planner/uncertainty_grid"]:
        hard_sums.setdefault(grid["stamp_ns"], set()).add(grid["fields"]["hard"]["sum"])
    paired = 0
    for regions in received["/area3d/planner/hard_regions"]:
        assert regions["frame_id"] == "world"
        counts = [r["voxel_count"] for r in regions["regions"]]
        assert counts == sorted(counts, reverse=True) and all(n >= 1 for n in counts)
        for region in regions["regions"]:
            assert all(e > 0 for e in region["extent"]) and region["direction_count"] >= 3
            assert 0.0 < region["mean_uncertainty"] <= 2.01  # G + S sqrt(G) + gamma
        sums = hard_sums.get(regions["stamp_ns"])
        if sums is not None and len(counts) < 100:  # under the published cap
            assert sum(counts) in sums
            paired += 1
    assert paired >= 1, "no hard-region message with the grid of its stamp"
    region_sets: dict[str, list] = {}
    for regions in received["/area3d/planner/hard_regions"]:
        region_sets.setdefault(regions["stamp_ns"], []).append(regions["regions"])

    def drawn(cubes: list, regions: list) -> bool:
        return len(cubes) == len(regions) and all(
            cube["position"] == pytest.approx(region["centroid"])
            and cube["scale"] == pytest.approx(region["extent"])
            for cube, region in zip(cubes, regions, strict=True)
        )

    boxes_paired = 0
    for boxes in received["/area3d/planner/hard_region_markers"]:
        assert boxes["markers"][0]["action"] == 3  # DELETEALL
        cubes = [m for m in boxes["markers"] if m["type"] == 1]
        assert all(m["ns"] == "hard_regions" and m["frame_id"] == "world" for m in cubes)
        if boxes["stamp_ns"] in region_sets:
            assert any(drawn(cubes, regions) for regions in region_sets[boxes["stamp_ns"]])
            boxes_paired += 1
    assert boxes_paired >= 1


def _pose_msg(values: list[float]):
    x, y, z, qx, qy, qz, qw = values
    return msgs.Pose(
        position=msgs.Point(x=x, y=y, z=z), orientation=msgs.Quaternion(x=qx, y=qy, z=qz, w=qw)
    )


def _rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return 0.0


def test_a_client_that_stops_reading_or_vanishes_never_slows_the_graph():
    """640x480 depth images (1.2 MB) at 20 Hz through the bridge: one Foxglove client is stopped
    (SIGSTOP: it reads nothing more) after its first images, later killed. The graph's own reader
    gets every image, publishing never blocks, the bridge's memory stays bounded by its backlog,
    and a second client keeps receiving fresh images all along."""
    port = free_port()
    topic = "/area3d/perception/depth"
    bridge = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "area3d_bringup.foxglove_bridge",
            *("--ros-args", "-p", f"port:={port}"),
        ],
        env=dict(os.environ, PYTHONPATH=str(REPO_ROOT)),
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    stalled = healthy = None
    try:
        with Probe("stall_test") as probe:
            graph_reader = probe.listen(msgs.Image, topic, qos.graph_frames())
            pub = probe.publisher(msgs.Image, topic, qos.graph_frames())
            image = np.random.default_rng(0).random((480, 640), dtype=np.float32)
            assert image.nbytes == 1_228_800
            stop = threading.Event()
            publish_s: list[float] = []
            sent = [0]

            def publish_loop() -> None:
                while not stop.is_set():
                    msg = codecs.image_to_msg(
                        image, "32FC1", time.time_ns(), "camera_optical_frame"
                    )
                    t0 = time.perf_counter()
                    pub.publish(msg)
                    publish_s.append(time.perf_counter() - t0)
                    sent[0] += 1
                    time.sleep(0.05)

            publisher = threading.Thread(target=publish_loop, daemon=True)
            publisher.start()
            stalled = client(port, [topic], count=1, timeout_s=TIMEOUT_S, stay=True)
            # wait for its first image, then stop the process: it reads nothing from now on
            line = ""
            while '"topic"' not in line:
                line = stalled.stdout.readline()
                assert line or stalled.poll() is None, "the client ended before its first image"
            os.kill(stalled.pid, signal.SIGSTOP)
            sent_at_stop = sent[0]
            rss_at_stop = _rss_mb(bridge.pid)
            # 200 more images (240 MB) while the client is stopped; a second client meanwhile
            assert probe.wait_for(lambda: sent[0] >= sent_at_stop + 100, TIMEOUT_S)
            healthy = client(port, [topic], count=20, timeout_s=TIMEOUT_S)
            out, _ = healthy.communicate(timeout=TIMEOUT_S + 30)
            assert healthy.returncode == 0, out[-2000:]
            stamps = [int(e["summary"]["stamp_ns"]) for e in lines(out) if "topic" in e]
            assert len(stamps) >= 20
            assert probe.wait_for(lambda: sent[0] >= sent_at_stop + 200, TIMEOUT_S)
            rss_stalled = _rss_mb(bridge.pid)
            os.kill(stalled.pid, signal.SIGKILL)  # the stopped client vanishes
            stalled.wait(timeout=60)
            after_kill = sent[0]
            assert probe.wait_for(lambda: sent[0] >= after_kill + 40, TIMEOUT_S)
            stop.set()
            publisher.join(timeout=30)
            total = sent[0]
            assert probe.wait_for(lambda: len(graph_reader) >= total, TIMEOUT_S), (
                f"the graph's reader got {len(graph_reader)} of {total} images"
            )
        assert bridge.poll() is None, "the bridge died"
        # a publish is a hand-over to the middleware: it never waited for the stopped client
        assert max(publish_s) < 5.0, max(publish_s)
        # the stopped client's queue is bounded: 200 images (240 MB) did not pile up in the bridge
        growth = rss_stalled - rss_at_stop
        assert growth < DEFAULT_BACKLOG * 1.2 * 3 + 50, f"bridge memory grew {growth:.0f} MB"
    finally:
        for process in (stalled, healthy):
            if process is not None and process.poll() is None:
                os.kill(process.pid, signal.SIGKILL)
                process.wait(timeout=60)
        bridge.send_signal(signal.SIGINT)
        try:
            bridge.communicate(timeout=60)
        except subprocess.TimeoutExpired:
            bridge.kill()
