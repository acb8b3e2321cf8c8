"""The perception node as its own process on Cyclone DDS (loopback): frames in, depth + confidence out."""

import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from area3d_msgs_py.node import Node

from area3d_msgs_py import codecs, dds_config, msgs
from area3d_perception.node import (
    COLOR_TOPIC,
    DEPTH_TOPIC,
    INFO_TOPIC,
    OUT_CONFIDENCE_TOPIC,
    OUT_DEPTH_TOPIC,
    POSE_TOPIC,
)

REPO_ROOT = Path(__file__).resolve().parents[2]
DOMAIN_ID = 1 + (os.getpid() + 101) % 200
TIMEOUT_S = 40.0
H, W = 48, 64
K = np.array([[W / 2, 0, W / 2], [0, W / 2, H / 2], [0, 0, 1.0]])


@pytest.fixture()
def loopback():
    with dds_config.loopback_domain(DOMAIN_ID):
        yield


def test_node_process_publishes_depth_and_confidence_with_the_frame_stamp(loopback):
    env = dict(os.environ, PYTHONPATH=str(REPO_ROOT))
    proc = subprocess.Popen(
        [sys.executable, "-m", "area3d_perception.node", "--ros-args", "-p", "backend:=uniform"],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    node = Node("perception_test_driver", backend="dds")
    received: dict[str, list] = {"depth": [], "confidence": []}
    try:
        pubs = {
            "color": node.create_publisher("sensor_msgs/msg/Image", COLOR_TOPIC),
            "depth": node.create_publisher("sensor_msgs/msg/Image", DEPTH_TOPIC),
            "info": node.create_publisher("sensor_msgs/msg/CameraInfo", INFO_TOPIC),
            "pose": node.create_publisher("geometry_msgs/msg/PoseStamped", POSE_TOPIC),
        }
        node.create_subscription("sensor_msgs/msg/Image", OUT_DEPTH_TOPIC, received["depth"].append)
        node.create_subscription(
            "sensor_msgs/msg/Image", OUT_CONFIDENCE_TOPIC, received["confidence"].append
        )
        depth = np.full((H, W), 1.5, np.float32)
        depth[:4] = np.nan
        sent = []
        deadline = time.monotonic() + TIMEOUT_S
        while not (received["depth"] and received["confidence"]) and time.monotonic() < deadline:
            assert proc.poll() is None, proc.communicate()[1]
            stamp = 1_000_000_000 * (len(sent) + 1)
            sent.append(stamp)
            pubs["info"].publish(codecs.intrinsics_to_camera_info(K, W, H, stamp, "cam"))
            pubs["pose"].publish(
                msgs.PoseStamped(
                    header=codecs.header(stamp, "world"), pose=codecs.matrix_to_pose(np.eye(4))
                )
            )
            pubs["color"].publish(
                codecs.image_to_msg(np.zeros((H, W, 3), np.uint8), "rgb8", stamp, "cam")
            )
            pubs["depth"].publish(codecs.image_to_msg(depth, "32FC1", stamp, "cam"))
            end = time.monotonic() + 0.3
            while time.monotonic() < end:
                node.spin_once(0.05)
        assert received["depth"] and received["confidence"], "no output from the perception node"
        out = received["depth"][0]
        assert codecs.stamp_to_ns(out.header.stamp) in sent and out.header.frame_id == "cam"
        np.testing.assert_array_equal(codecs.msg_to_image(out), depth)
        conf = codecs.msg_to_image(received["confidence"][0])
        assert np.all(conf[4:] == 1.0) and np.all(conf[:4] == 0.0)
    finally:
        node.shutdown()
        proc.terminate()
        try:
            proc.communicate(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.communicate()
