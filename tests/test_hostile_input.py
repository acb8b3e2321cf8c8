"""Hostile input over the wire: a separate process (tests/clients/hostile_client.py, plain rclpy,
no project imports) feeds every topic each node subscribes to with malformed messages. Each is
rejected with a log line naming the field, each node's status counts the rejections by topic and
field, and every node keeps serving: a valid frame afterwards is processed and planned from."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from collections import Counter
from pathlib import Path

import numpy as np

from area3d_msgs_py import codecs, msgs, qos
from tests.test_faults import H, W, _camera_publishers, _frame, _publish_frame, graph_factory  # noqa: F401

CLIENT = Path(__file__).parent / "clients" / "hostile_client.py"
# its writers' heartbeat every 50 ms (Fast DDS: 3 s): it waits for acknowledgements between samples
FAST_ACKS = Path(__file__).parent / "clients" / "fast_acks.xml"
# The topics each node reads, as the client names them (absolute, default namespace).
SUBSCRIBED = {
    "sim_bridge": ("/area3d/camera/goal_pose",),
    "perception": (
        "/area3d/camera/color/image_raw",
        "/area3d/camera/depth/image_raw",
        "/area3d/camera/camera_info",
        "/area3d/camera/pose",
    ),
    "semantics": (
        "/area3d/camera/color/image_raw",
        "/area3d/camera/depth/image_raw",
        "/area3d/perception/confidence",
        "/area3d/semantics/request",
    ),
    "planner": (
        "/area3d/camera/camera_info",
        "/area3d/camera/pose",
        "/area3d/perception/depth",
        "/area3d/perception/confidence",
        "/area3d/semantics/uncertainty",
    ),
}
STATUS = {
    "sim_bridge": "area3d/camera/status",
    "perception": "area3d/perception/status",
    "semantics": "area3d/semantics/status",
    "planner": "area3d/planner/status",
}


def _expected(sent: list[dict], node: str) -> tuple[Counter, Counter]:
    """(rejections by topic, by field) the node's status must report for the cases sent."""
    mine = [case for case in sent if case["topic"] in SUBSCRIBED[node]]
    return Counter(c["topic"].lstrip("/") for c in mine), Counter(c["field"] for c in mine)


def _warned(lines: list[str], case: dict) -> bool:
    """A WARN line names the case's topic and field."""
    topic, field = case["topic"].lstrip("/"), case["field"]
    return any(topic in line and f"{field}: got" in line for line in lines if "WARN" in line)


def _last_status(messages: list) -> dict:
    return json.loads(messages[-1].data) if messages else {}


def test_every_node_rejects_a_barrage_of_malformed_messages_by_field_and_keeps_serving(
    graph_factory,  # noqa: F811
):
    graph = graph_factory(
        ("sim_bridge", "perception", "semantics", "planner"),
        {
            "sim_bridge": {"width": W, "height": H},
            "semantics": {"num_initial_views": 1},
            "planner": {"width": W, "height": H, "sync_timeout_s": 30.0},
        },
    )
    status: dict[str, list] = {node: [] for node in STATUS}
    status_readers = [
        graph.node.create_subscription(msgs.String, topic, status[node].append, qos.frames())
        for node, topic in STATUS.items()
    ]
    # transient local, as perception and semantics publish them (a late match still gets them)
    depth_out = graph.listen(msgs.Image, "area3d/perception/depth", qos.graph_frames())
    weights = graph.listen(msgs.Image, "area3d/semantics/weight", qos.graph_frames())
    request = graph.probe.publisher(msgs.String, "area3d/semantics/request")
    pubs = _camera_publishers(graph)
    graph.start()
    # sim_bridge's status comes once per goal: every status must reach us before the barrage
    assert graph.wait_for(lambda: all(r.get_publisher_count() >= 1 for r in status_readers))
    readers = Counter(topic for topics in SUBSCRIBED.values() for topic in topics)
    client = subprocess.run(
        [sys.executable, str(CLIENT), json.dumps({"width": W, "height": H, "readers": readers})],
        capture_output=True,
        text=True,
        timeout=300,
        env=dict(os.environ, FASTRTPS_DEFAULT_PROFILES_FILE=str(FAST_ACKS)),
    )
    assert client.returncode == 0, client.stderr[-2000:]
    sent = json.loads(client.stdout.strip().splitlines()[-1])["sent"]
    assert {case["topic"] for case in sent} >= set(readers) - {"/area3d/semantics/request"}

    for node in ("perception", "semantics", "planner"):
        by_topic, by_field = _expected(sent, node)
        assert graph.wait_for(
            lambda n=node, t=by_topic: (
                _last_status(status[n]).get("rejected", {}).get("by_topic") == dict(t)
            ),
        ), (node, dict(by_topic), _last_status(status[node]), graph.lines[-30:])
        assert _last_status(status[node])["rejected"]["by_field"] == dict(by_field), node
    # sim_bridge's status is per goal: the last refusal carries every rejection so far
    by_topic, by_field = _expected(sent, "sim_bridge")
    assert graph.wait_for(
        lambda: (
            _last_status(status["sim_bridge"]).get("rejected", {}).get("by_field") == dict(by_field)
        ),
    ), (_last_status(status["sim_bridge"]), graph.lines[-30:])
    assert not _last_status(status["sim_bridge"])["ok"]

    # one warning line per case, naming the topic and the field (the lines come over the nodes'
    # output pipes, not with the status: waited for)
    for case in sent:
        assert graph.wait_for(lambda c=case: _warned(graph.lines, c)), (
            case,
            [line for line in graph.lines if "WARN" in line][-40:],
        )

    # ... and every node still serves: a valid frame is processed, re-queried and planned from
    rgb, depth, K, T = _frame()
    stamp = codecs.stamp_to_ns(graph.node.get_clock().now().to_msg())
    _publish_frame(graph, pubs, stamp, rgb, depth, K, T)
    assert graph.wait_for(
        lambda: any(codecs.stamp_to_ns(m.header.stamp) == stamp for m in depth_out)
    ), graph.lines[-30:]
    request.publish(msgs.String(data="again"))
    assert graph.wait_for(
        lambda: any(codecs.stamp_to_ns(m.header.stamp) == stamp for m in weights)
    ), graph.lines[-30:]
    assert graph.wait_for(
        lambda: _last_status(status["planner"]).get("last_fused_stamp_ns") == stamp
    ), (_last_status(status["planner"]), graph.lines[-30:])
    plan_request = msgs.GetPlan_Request()
    plan_request.start.header = codecs.header(stamp, "world")
    plan_request.start.pose = codecs.matrix_to_pose(T)
    plan_request.goal.pose.position.x = float("nan")  # how many views: refused, by its field
    plan = graph.probe.call(msgs.GetPlan, "area3d/planner/next_best_view", plan_request, 120)
    assert len(plan.plan.poses) == 0
    assert graph.wait_for(lambda: any("goal.pose.position.x: got nan" in s for s in graph.lines))
    assert not any("[ERROR]" in line and "[planner]" in line for line in graph.lines)
    plan_request.goal.pose.position.x = 1.0
    plan = graph.probe.call(msgs.GetPlan, "area3d/planner/next_best_view", plan_request, 120)
    assert len(plan.plan.poses) == 1, graph.lines[-30:]
    assert np.isfinite(codecs.pose_to_matrix(plan.plan.poses[0].pose)).all()
    # a goal after the barrage is still captured
    goal = graph.probe.publisher(msgs.PoseStamped, "area3d/camera/goal_pose")
    assert graph.wait_for(lambda: goal.get_subscription_count() >= 1)
    goal.publish(
        msgs.PoseStamped(header=codecs.header(stamp + 1, "world"), pose=codecs.matrix_to_pose(T))
    )
    assert graph.wait_for(
        lambda: any(json.loads(m.data)["stamp_ns"] == stamp + 1 and json.loads(m.data)["ok"]
                    for m in status["sim_bridge"]),
    ), graph.lines[-30:]  # fmt: skip
    # ... through perception into the planner (and nothing is in flight when the graph stops)
    assert graph.wait_for(
        lambda: _last_status(status["planner"]).get("last_fused_stamp_ns") == stamp + 1
    ), (_last_status(status["planner"]), graph.lines[-30:])


def test_bad_poses_and_transforms_are_rejected_by_field_and_frames_without_a_pose_dropped_by_cause(
    graph_factory,  # noqa: F811
):
    """Perception takes the camera pose from TF, the planner from odometry (jumps checked): a
    non-unit quaternion, a NaN, a jump, a stamp from the future, a second parent, a frame its own
    parent are each rejected with a line naming the message's field; a frame whose transform comes
    too late, or never, is dropped and counted by cause, never fused with a wrong pose; and both
    nodes go on with the next valid frame."""
    pose_wait = {"pose_wait_s": 2.0, "pose_max_linear_speed": 10.0, "pose_max_angular_speed": 20.0}
    graph = graph_factory(
        ("perception", "planner"),
        {
            "perception": {"pose_source": "tf", **pose_wait},
            "planner": {
                "width": W, "height": H, "sync_timeout_s": 30.0, "world_frame": "odom",
                "pose_source": "odometry", "camera_mount": "parameters", **pose_wait,
            },
        },
    )  # fmt: skip
    status = {node: [] for node in ("perception", "planner")}
    for node in status:
        graph.node.create_subscription(msgs.String, STATUS[node], status[node].append, qos.frames())
    graph.start()
    readers = {
        "/tf": 1, "/tf_static": 1, "/area3d/odom": 1, "/area3d/camera/camera_info": 2,
        "/area3d/camera/color/image_raw": 1, "/area3d/camera/depth/image_raw": 1,
        "/area3d/perception/depth": 1, "/area3d/perception/confidence": 1,
    }  # fmt: skip
    client = subprocess.run(
        [sys.executable, str(CLIENT), json.dumps({"width": W, "height": H, "readers": readers, "poses": True})],
        capture_output=True,
        text=True,
        timeout=300,
        env=dict(os.environ, FASTRTPS_DEFAULT_PROFILES_FILE=str(FAST_ACKS)),
    )  # fmt: skip
    assert client.returncode == 0, client.stderr[-2000:]
    answer = json.loads(client.stdout.strip().splitlines()[-1])
    sent, drops = answer["sent"], answer["drops"]
    reader_of = {"/tf": "perception", "/tf_static": "perception", "/area3d/odom": "planner"}
    assert {case["topic"] for case in sent} == set(reader_of)
    for node in status:
        mine = [case for case in sent if reader_of[case["topic"]] == node]
        by_topic = Counter(
            c["topic"] if c["topic"] in ("/tf", "/tf_static") else c["topic"].lstrip("/")
            for c in mine
        )
        by_field = Counter(c["field"] for c in mine)

        def settled(n=node, t=by_topic, d=drops[node]):
            last = _last_status(status[n])
            return last.get("rejected", {}).get("by_topic") == dict(t) and (
                last.get("frames_dropped_no_pose") == d
            )

        assert graph.wait_for(settled), (
            node,
            dict(by_topic),
            _last_status(status[node]),
            graph.lines[-30:],
        )
        last = _last_status(status[node])
        assert last["rejected"]["by_field"] == dict(by_field), node
        assert last["frames_waiting_for_pose"] == 0
    assert _last_status(status["perception"])["frames_published"] == 0  # none with a wrong pose
    assert _last_status(status["planner"])["frames_fused"] == 0
    for case in sent:  # one warning line per case, naming the topic and the field
        assert graph.wait_for(lambda c=case: _warned(graph.lines, c)), case
    for node, causes in drops.items():  # each cause logged once, with its reason
        for cause in causes:

            def said(n=node, c=cause):
                return [
                    line
                    for line in graph.lines
                    if f"no camera pose ({c})" in line and f"[{n}]" in line
                ]

            assert graph.wait_for(said), (node, cause, graph.lines[-30:])
            assert len(said()) == 1, (node, cause, graph.lines[-30:])

    # ... and both go on: a valid frame with its transforms is perceived, then fused and planned
    rgb, depth, K, T = _frame()
    pubs = _camera_publishers(graph)
    tf = graph.probe.publisher(msgs.TFMessage, "/tf", qos.reliable(100))
    odometry = graph.probe.publisher(msgs.Odometry, "area3d/odom")
    perceived = graph.listen(msgs.Image, "area3d/perception/depth", qos.graph_frames())
    assert graph.wait_for(
        lambda: tf.get_subscription_count() >= 1 and odometry.get_subscription_count() >= 1
    )
    stamp = codecs.stamp_to_ns(graph.node.get_clock().now().to_msg())
    # the optical frame looking along x of its parent: the client's camera_link -> optical mount
    # and the planner's default mount on the body alike
    mount = codecs.pose_to_matrix(
        msgs.Pose(orientation=msgs.Quaternion(x=-0.5, y=0.5, z=-0.5, w=0.5))
    )
    link = body = T @ np.linalg.inv(mount)
    for t in (stamp - 5_000_000, stamp + 5_000_000):
        tf.publish(codecs.transforms_to_tf_message([("world", "camera_link", t, link)]))
        message = msgs.Odometry(header=codecs.header(t, "odom"), child_frame_id="base_link")
        message.pose.pose = codecs.matrix_to_pose(body)
        odometry.publish(message)
    _publish_frame(graph, pubs, stamp, rgb, depth, K, T)
    assert graph.wait_for(
        lambda: any(codecs.stamp_to_ns(m.header.stamp) == stamp for m in perceived)
    ), graph.lines[-30:]
    assert graph.wait_for(
        lambda: _last_status(status["planner"]).get("last_fused_stamp_ns") == stamp
    ), graph.lines[-30:]
    request = codecs.view_request_to_msg(1, T, stamp, "odom")
    answer = codecs.msg_to_view_answer(
        graph.probe.call(msgs.NextBestView, "area3d/planner/select_views", request, 120)
    )
    assert answer.success and answer.frame_id == "odom" and len(answer.views) == 1, answer.message
