"""Bad input over the wire: nodes reject it with a logged reason and keep serving."""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from area3d_bringup.launch_description import GRAPH_NODES, build_graph
from area3d_bringup.launcher import Launcher
from area3d_msgs_py import codecs, msgs, qos, services
from area3d_msgs_py.probe import Probe
from sim_bridge.render import RgbdRenderer
from sim_bridge.scenes import load_scene

W, H = 160, 120
# Longest a test waits for the graph to do something: generous, a loaded machine is slow (waits
# end as soon as what they wait for is there).
WAIT_S = 120.0


class Graph:
    """Some of the graph's nodes as processes, plus a local node to poke them."""

    def __init__(self, names: tuple[str, ...], workdir: Path, overrides: dict):
        specs = build_graph(
            overrides=overrides, nodes=tuple((n, m) for n, m in GRAPH_NODES if n in names)
        )
        self.lines: list[str] = []
        self.launcher = Launcher(specs, workdir, log_sink=self.lines.append)
        self.probe = Probe("fault_injector")
        self.node = self.probe.node

    def listen(self, msg_type: type, topic: str, profile=None) -> list:
        return self.probe.listen(msg_type, topic, profile)

    def start(self) -> None:
        self.launcher.start()

    def stop(self) -> dict[str, int]:
        # a quiet stop is asked of every node, not a fast one on a loaded machine (the time to
        # stop is tests/test_shutdown.py's)
        codes = self.launcher.stop(grace_s=30.0)
        self.probe.close()
        return codes

    def wait_for(self, predicate, timeout_s: float = WAIT_S) -> bool:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            self.launcher.check()  # a crashed node fails the test here, by name
            if predicate():
                return True
            time.sleep(0.05)
        return False


@pytest.fixture()
def graph_factory(tmp_path: Path) -> Iterator:
    graphs: list[Graph] = []

    def make(names: tuple[str, ...], overrides: dict) -> Graph:
        graph = Graph(names, tmp_path, overrides)
        graphs.append(graph)
        return graph

    yield make
    for graph in graphs:
        codes = graph.stop()
        # after all that bad input, each node still stops quietly on the first SIGINT
        assert all(code == 0 for code in codes.values()), (codes, graph.lines[-20:])
        at = [i for i, line in enumerate(graph.lines) if "Traceback" in line]
        assert not at, "\n".join(graph.lines[max(0, at[0] - 3) : at[0] + 30] if at else [])


def _frame(scene_name: str = "single_object"):
    scene = load_scene(scene_name)
    renderer = RgbdRenderer(scene, width=W, height=H)
    T = scene.initial_views[0]
    rgb, depth = renderer.render(T)
    K = renderer.K
    renderer.close()
    return rgb, depth, K, T


def _publish_frame(
    graph: Graph, pubs: dict, stamp: int, rgb, depth, K, T, depth_encoding: str = "32FC1"
) -> None:
    pubs["info"].publish(codecs.intrinsics_to_camera_info(K, W, H, stamp, "camera_optical_frame"))
    pubs["pose"].publish(
        msgs.PoseStamped(header=codecs.header(stamp, "world"), pose=codecs.matrix_to_pose(T))
    )
    pubs["color"].publish(codecs.image_to_msg(rgb, "rgb8", stamp, "camera_optical_frame"))
    if depth_encoding == "32FC1":
        pubs["depth"].publish(codecs.image_to_msg(depth, "32FC1", stamp, "camera_optical_frame"))
    else:  # a depth topic carrying the wrong encoding
        pubs["depth"].publish(
            codecs.image_to_msg(rgb, depth_encoding, stamp, "camera_optical_frame")
        )


def _publish_until(graph: Graph, pubs: dict, stamp: int, rgb, depth, K, T, predicate) -> bool:
    """The frame, sent again every few seconds until `predicate` holds: our writers see the node's
    readers before its readers may know our writers (discovery runs both ways, and late on a loaded
    machine), and a sample sent in between never reaches them. The node fuses a stamp once: a copy
    after the first arrived is refused as repeated, not fused twice."""
    deadline = time.monotonic() + WAIT_S
    while time.monotonic() < deadline:
        _publish_frame(graph, pubs, stamp, rgb, depth, K, T)
        if graph.wait_for(predicate, timeout_s=min(5.0, max(0.0, deadline - time.monotonic()))):
            return True
    return False


def _camera_publishers(graph: Graph) -> dict:
    return {
        "color": graph.probe.publisher(msgs.Image, "area3d/camera/color/image_raw"),
        "depth": graph.probe.publisher(msgs.Image, "area3d/camera/depth/image_raw"),
        "info": graph.probe.publisher(msgs.CameraInfo, "area3d/camera/camera_info"),
        "pose": graph.probe.publisher(msgs.PoseStamped, "area3d/camera/pose"),
    }


def test_perception_survives_nan_inf_negative_and_mis_sized_depth(graph_factory):
    graph = graph_factory(("perception",), {})
    # transient local, as perception publishes them: an output that goes out before perception's
    # writer has matched our reader (its discovery of this process may finish late) still comes
    out = graph.listen(msgs.Image, "area3d/perception/depth", qos.graph_frames())
    conf = graph.listen(msgs.Image, "area3d/perception/confidence", qos.graph_frames())
    pubs = _camera_publishers(graph)
    graph.start()
    rgb, depth, K, T = _frame()
    assert graph.wait_for(lambda: all(p.get_subscription_count() >= 1 for p in pubs.values()))

    bad = depth.copy()
    bad[:10] = np.inf  # REP 117: no return within range, passed on as such
    bad[10:20] = -1.0
    bad[20:30] = np.nan
    assert _publish_until(
        graph, pubs, 1_000, rgb, bad, K, T, lambda: len(out) >= 1 and len(conf) >= 1
    ), "\n".join(graph.lines[-20:])
    cleaned = codecs.msg_to_image(out[0])
    assert codecs.stamp_to_ns(out[0].header.stamp) == 1_000
    # the rest of the unusable rows: no estimate, or (perception's no_return: regions) most of
    # them, beside the rows without a return and far from any surface, no return as well
    assert np.isposinf(cleaned[:10]).all() and not np.isfinite(cleaned[10:30]).any()
    assert not np.any(np.isneginf(cleaned)) and not np.any(cleaned[np.isfinite(cleaned)] <= 0)
    assert np.all(codecs.msg_to_image(conf[0])[:30] == 0), "no confidence where depth was unusable"

    # A depth image of another size than the color image is refused, with the reason logged.
    small = depth[: H // 2, : W // 2].copy()
    _publish_frame(graph, pubs, 2_000, rgb, small, K, T)
    assert graph.wait_for(
        lambda: any("2000" in line or "size" in line for line in graph.lines if "WARN" in line)
    )
    # ... and the node still processes the next good frame.
    _publish_frame(graph, pubs, 3_000, rgb, depth, K, T)
    assert graph.wait_for(lambda: any(codecs.stamp_to_ns(m.header.stamp) == 3_000 for m in out))
    assert all(codecs.stamp_to_ns(m.header.stamp) != 2_000 for m in out)


def test_planner_answers_early_and_malformed_requests_with_an_empty_plan_and_keeps_serving(
    graph_factory,
):
    graph = graph_factory(
        ("planner",),
        {
            "planner": {
                "width": W,
                "height": H,
                "sync_timeout_s": 1.0,
                "budget": 6,
            }
        },
    )
    client = graph.node.create_client(msgs.GetPlan, "area3d/planner/next_best_view")
    depth_pub = graph.probe.publisher(msgs.Image, "area3d/perception/depth", qos.graph_frames())
    conf_pub = graph.probe.publisher(msgs.Image, "area3d/perception/confidence", qos.graph_frames())
    pubs = _camera_publishers(graph)
    status = graph.listen(msgs.String, "area3d/planner/status")
    graph.start()
    assert graph.wait_for(lambda: client.wait_for_service(timeout_sec=0.1))
    assert graph.wait_for(lambda: depth_pub.get_subscription_count() >= 1)
    assert graph.wait_for(lambda: pubs["pose"].get_subscription_count() >= 1)

    def request(count: float, stamp: int = 0, quaternion=(0.0, 0.0, 0.0, 1.0)):
        req = msgs.GetPlan_Request(
            start=msgs.PoseStamped(
                header=codecs.header(stamp, "world"), pose=codecs.matrix_to_pose(np.eye(4))
            ),
            goal=msgs.PoseStamped(
                header=codecs.header(stamp, "world"), pose=codecs.matrix_to_pose(np.eye(4))
            ),
            tolerance=0.0,
        )
        q = req.start.pose.orientation
        q.x, q.y, q.z, q.w = quaternion
        req.goal.pose.position.x = float(count)
        # asked again while no reply comes: the planner has only just appeared
        return services.call(client, req, WAIT_S).plan.poses

    assert request(1) == []  # before any frame: empty plan, reason in the log
    assert graph.wait_for(lambda: any("no frame fused yet" in line for line in graph.lines))

    # garbage on its inputs: a depth image with an rgb8 encoding, a depth/step mismatch
    rgb, depth, K, T = _frame()
    pubs["pose"].publish(
        msgs.PoseStamped(header=codecs.header(5, "world"), pose=codecs.matrix_to_pose(T))
    )
    pubs["info"].publish(codecs.intrinsics_to_camera_info(K, W, H, 5, "camera_optical_frame"))
    depth_pub.publish(codecs.image_to_msg(rgb, "rgb8", 5, "camera_optical_frame"))
    broken = codecs.image_to_msg(depth, "32FC1", 5, "camera_optical_frame")
    broken.step = 3
    conf_pub.publish(broken)
    for topic in ("area3d/perception/depth", "area3d/perception/confidence"):
        rejected = f"{topic} at stamp 5: rejected"
        assert graph.wait_for(lambda r=rejected: any(r in line for line in graph.lines)), (
            graph.lines[-20:]
        )

    # a real frame, then a proper request: the planner still serves
    stamp = 10
    pubs["pose"].publish(
        msgs.PoseStamped(header=codecs.header(stamp, "world"), pose=codecs.matrix_to_pose(T))
    )
    pubs["info"].publish(codecs.intrinsics_to_camera_info(K, W, H, stamp, "camera_optical_frame"))
    depth_pub.publish(codecs.image_to_msg(depth, "32FC1", stamp, "camera_optical_frame"))
    conf_pub.publish(
        codecs.image_to_msg(
            np.isfinite(depth).astype(np.float32), "32FC1", stamp, "camera_optical_frame"
        )
    )
    assert graph.wait_for(lambda: any('"frames_fused": 1' in m.data for m in status))
    assert request(-3, stamp) == []  # a negative number of views is refused
    assert (
        request(1, stamp, quaternion=(0.0, 0.0, 0.0, 2.0)) != []
    )  # a bad start pose is logged, not fatal
    poses = request(1, stamp)
    assert len(poses) == 1
    graph.launcher.check()


def test_stereo_perception_matches_the_simulated_pair_over_the_wire(graph_factory):
    readers = {f"readers.{k}": ["perception"] for k in ("color", "depth", "camera_info", "pose")}
    graph = graph_factory(
        ("sim_bridge", "perception"),
        {
            "sim_bridge": {"scene": "single_object", "width": 320, "height": 240, **readers},
            # turns sim_bridge.stereo on; 32 disparities at half of 320 px: depth from 0.15 m
            "perception": {"backend": "stereo", "stereo.num_disparities": 32},
        },
    )
    out = graph.listen(msgs.Image, "area3d/perception/depth", qos.graph_frames())
    truth = graph.listen(msgs.Image, "area3d/camera/depth/image_raw")
    goal_pub = graph.probe.publisher(msgs.PoseStamped, "area3d/camera/goal_pose")
    graph.start()
    assert graph.wait_for(lambda: goal_pub.get_subscription_count() >= 1)
    T = load_scene("single_object").initial_views[0]
    stamp = 1_000_000_000

    def of_stamp(messages: list) -> list:
        return [m for m in messages if codecs.stamp_to_ns(m.header.stamp) == stamp]

    def both_arrived() -> bool:
        return bool(of_stamp(out)) and bool(of_stamp(truth))

    deadline = time.monotonic() + WAIT_S
    # The camera waits for perception's readers only: its depth for our (volatile) reader is lost
    # when that reader is matched only after the frame went out. Send the goal again (same stamp,
    # same frame) until both the estimate and the true depth are here.
    while not both_arrived():
        assert time.monotonic() < deadline, "\n".join(graph.lines[-20:])
        goal_pub.publish(
            msgs.PoseStamped(header=codecs.header(stamp, "world"), pose=codecs.matrix_to_pose(T))
        )
        graph.wait_for(both_arrived, 5.0)
    depth = codecs.msg_to_image(of_stamp(out)[0])
    gt = codecs.msg_to_image(of_stamp(truth)[0])
    both = np.isfinite(depth) & np.isfinite(gt)
    assert both.mean() > 0.3  # the right image and its baseline arrived and were matched
    assert np.median(np.abs(depth[both] - gt[both]) / gt[both]) < 0.05  # metric, right sign
