"""The camera inputs' QoS over the wire (`camera_qos`): with `sensor_data` a node reads drivers that
publish best effort and reliable alike; with `reliable` (the default) a best-effort publisher never
matches, and DDS says so with an incompatible-QoS event, while a reliable one does."""

from __future__ import annotations

import numpy as np
import rclpy
from rclpy.event_handler import PublisherEventCallbacks
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter

from area3d_msgs_py import codecs, msgs, qos, topics
from area3d_msgs_py.probe import Probe
from area3d_msgs_py.spinning import Spinner
from area3d_perception.node import PerceptionNode

WAIT_S = 120.0
H, W = 48, 64
K = np.array([[W / 2, 0, W / 2], [0, W / 2, H / 2], [0, 0, 1.0]])
CHOICES = ("reliable", "sensor_data")
CAMERA = (topics.COLOR, topics.DEPTH, topics.CAMERA_INFO, topics.POSE)


def _frame(stamp: int) -> dict:
    T = np.eye(4)
    T[2, 3] = 1.0
    frame = "camera_optical_frame"
    return {
        topics.COLOR: codecs.image_to_msg(np.zeros((H, W, 3), np.uint8), "bgr8", stamp, frame),
        topics.DEPTH: codecs.image_to_msg(np.full((H, W), 2.0, np.float32), "16UC1", stamp, frame),
        topics.CAMERA_INFO: codecs.intrinsics_to_camera_info(K, W, H, stamp, frame),
        topics.POSE: msgs.PoseStamped(
            header=codecs.header(stamp, "world"), pose=codecs.matrix_to_pose(T)
        ),
    }


def test_camera_inputs_match_the_publishers_their_camera_qos_allows():
    context = rclpy.Context()
    rclpy.init(context=context)
    nodes = {
        choice: PerceptionNode(
            context=context,
            namespace=f"/{choice}",
            parameter_overrides=[Parameter("camera_qos", value=choice)],
        )
        for choice in CHOICES
    }
    executor = SingleThreadedExecutor(context=context)
    for node in nodes.values():
        executor.add_node(node)
    spinner = Spinner(executor)
    probe = Probe("driver")
    try:
        incompatible: dict[tuple, list] = {}
        pubs: dict[tuple, object] = {}
        for choice in CHOICES:
            for kind, profile in (("reliable", qos.frames()), ("best_effort", qos.sensor_data())):
                for topic in CAMERA:
                    key = (choice, kind, topic.name)
                    events = incompatible.setdefault(key, [])
                    pubs[key] = probe.node.create_publisher(
                        topic.msg_type,
                        f"/{choice}/{topic.name}",
                        profile,
                        event_callbacks=PublisherEventCallbacks(incompatible_qos=events.append),
                    )
        # sensor_data reads both kinds; reliable reads the reliable publishers ...
        for key, pub in pubs.items():
            choice, kind, _ = key
            if choice == "sensor_data" or kind == "reliable":
                assert probe.wait_for_readers(pub, 1, WAIT_S), key
        # ... and a best-effort publisher never matches it: DDS reports the incompatible QoS
        for topic in CAMERA:
            key = ("reliable", "best_effort", topic.name)
            assert probe.wait_for(lambda k=key: incompatible[k], WAIT_S), key
            assert pubs[key].get_subscription_count() == 0
            policy = incompatible[key][0].last_policy_kind
            assert "RELIABILITY" in str(policy), policy
        assert not any(incompatible[k] for k in pubs if k[0] == "sensor_data")

        # a whole frame from a best-effort driver (bgr8, 16UC1 millimetres) is processed
        out = probe.listen(msgs.Image, "/sensor_data/area3d/perception/depth", qos.graph_frames())
        for attempt in range(int(WAIT_S)):  # best effort: a frame lost is sent again, anew
            for topic, msg in _frame(1_000 + attempt).items():
                pubs[("sensor_data", "best_effort", topic.name)].publish(msg)
            if probe.wait_for(lambda: out, 1.0):
                break
        assert out, "no frame through from the best-effort driver"
        depth = codecs.msg_to_image(out[0])
        np.testing.assert_allclose(depth[np.isfinite(depth)], 2.0, atol=1e-6)
        assert nodes["reliable"].frames_published == 0
    finally:
        probe.close()
        spinner.stop(10)
        for node in nodes.values():
            node.destroy_node()
        context.try_shutdown()
