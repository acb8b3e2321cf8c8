"""The semantics node on a real (loopback) DDS graph: one query with the initial views, regions
JSON, one weight map and one U_sem per frame with the frame's stamp, re-query on request."""

import json
import os
import socket
import time

import numpy as np
import pytest
from area3d_msgs_py.node import Node

from area3d_msgs_py import codecs, dds_config, msgs
from area3d_semantics.node import SemanticsNode
from area3d_semantics.weights import semantic_uncertainty, sigma_from_confidence

DOMAIN_ID = 1 + (os.getpid() + 97) % 200
H, W = 60, 80
TIMEOUT_S = 20.0


@pytest.fixture(scope="module", autouse=True)
def loopback():
    with dds_config.loopback_domain(DOMAIN_ID):
        yield


class Rig:
    """The node under test plus a peer node that feeds frames and records the outputs."""

    def __init__(self, parameters: dict):
        self.sem_node = Node("semantics", parameters, backend="dds")
        self.semantics = SemanticsNode(self.sem_node)
        self.peer = Node("feeder", backend="dds")
        self.regions, self.weights, self.usem = [], {}, {}
        self.peer.create_subscription(
            "std_msgs/msg/String", "/area3d/semantics/regions", self.regions.append, latched=True
        )
        self.peer.create_subscription(
            "sensor_msgs/msg/Image", "/area3d/semantics/weight", self._store(self.weights), depth=64
        )
        self.peer.create_subscription(
            "sensor_msgs/msg/Image",
            "/area3d/semantics/uncertainty",
            self._store(self.usem),
            depth=64,
        )
        self.color = self.peer.create_publisher(
            "sensor_msgs/msg/Image", "/area3d/camera/color/image_raw", depth=64
        )
        self.depth = self.peer.create_publisher(
            "sensor_msgs/msg/Image", "/area3d/camera/depth/image_raw", depth=64
        )
        self.conf = self.peer.create_publisher(
            "sensor_msgs/msg/Image", "/area3d/perception/confidence", depth=64
        )
        self.request = self.peer.create_publisher(
            "std_msgs/msg/String", "/area3d/semantics/request"
        )
        self.spin(lambda: False, 1.5)  # discovery

    @staticmethod
    def _store(into):
        return lambda msg: into.setdefault(codecs.stamp_to_ns(msg.header.stamp), []).append(
            codecs.msg_to_image(msg)
        )

    def spin(self, done, timeout_s=TIMEOUT_S):
        deadline = time.monotonic() + timeout_s
        while not done() and time.monotonic() < deadline:
            self.sem_node.spin_once(0.02)
            self.peer.spin_once(0.02)

    def frame(self, stamp, image, depth, confidence=None):
        self.color.publish(codecs.image_to_msg(image, "rgb8", stamp, "camera_optical_frame"))
        self.depth.publish(codecs.image_to_msg(depth, "32FC1", stamp, "camera_optical_frame"))
        if confidence is not None:
            self.conf.publish(
                codecs.image_to_msg(confidence, "32FC1", stamp, "camera_optical_frame")
            )

    def close(self):
        self.peer.shutdown()
        self.sem_node.shutdown()


def frames(n):
    rng = np.random.default_rng(7)
    out = []
    for k in range(n):
        image = np.full((H, W, 3), 128, np.uint8)
        image[:, : W // 2] = rng.integers(60, 200, (H, W // 2, 3), dtype=np.uint8)
        depth = np.full((H, W), 2.0, np.float32)
        confidence = np.full((H, W), 0.5, np.float32)
        confidence[:, : W // 4] = 0.9
        out.append((1_000_000_000 + k * 1_000_000, image, depth, confidence))
    return out


def closed_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_initial_views_are_analysed_once_and_each_frame_gets_weight_and_usem():
    rig = Rig({"num_initial_views": 3, "backend": "heuristic"})
    try:
        data = frames(4)
        for stamp, image, depth, confidence in data[:3]:
            rig.frame(stamp, image, depth, confidence)
        stamps = [d[0] for d in data[:3]]
        rig.spin(lambda: rig.regions and all(s in rig.usem for s in stamps))
        assert len(rig.regions) == 1
        payload = json.loads(rig.regions[0].data)
        assert payload["prompt_version"] == "v1" and payload["backend"] == "heuristic"
        assert payload["fallback_used"] is None
        assert [img["stamp_ns"] for img in payload["images"]] == stamps
        # The flat grey right half is textureless: the heuristic reports it.
        assert any(
            r["type"] == "TEXTURE" and r["column"] == "right"
            for r in payload["images"][0]["regions"]
        )
        for stamp, _, _, confidence in data[:3]:
            (weight,) = rig.weights[stamp]
            assert weight.shape == (H, W) and weight.max() == pytest.approx(1.0)
            (usem,) = rig.usem[stamp]
            expected = semantic_uncertainty(sigma_from_confidence(confidence), weight, 1.0)
            np.testing.assert_allclose(usem, expected, atol=1e-6)
        # A frame after O_0 triggers no new query.
        rig.frame(*data[3])
        rig.spin(lambda: False, 1.0)
        assert len(rig.regions) == 1 and data[3][0] not in rig.weights
        # A request re-runs the query on everything collected so far.
        rig.request.publish(msgs.String(data="again"))
        rig.spin(lambda: len(rig.regions) >= 2 and data[3][0] in rig.weights)
        again = json.loads(rig.regions[-1].data)
        assert [img["stamp_ns"] for img in again["images"]] == [d[0] for d in data]
    finally:
        rig.close()


def test_unreachable_vlm_falls_back_and_the_node_keeps_running():
    url = f"http://127.0.0.1:{closed_port()}/v1"
    rig = Rig(
        {
            "num_initial_views": 2,
            "backend": "openai",
            "base_url": url,
            "retries": 0,
            "fallback": "zeros",
        }
    )
    try:
        data = frames(2)
        for stamp, image, depth, _ in data:
            rig.frame(stamp, image, depth)  # confidence arrives later
        rig.spin(lambda: rig.regions and all(d[0] in rig.weights for d in data))
        payload = json.loads(rig.regions[0].data)
        assert payload["backend"] == "openai" and payload["fallback_used"] == "zeros"
        assert url in payload["error"]
        assert all(not rig.weights[d[0]][0].any() for d in data)
        stamp, _, _, confidence = data[0]
        rig.conf.publish(codecs.image_to_msg(confidence, "32FC1", stamp, "camera_optical_frame"))
        rig.spin(lambda: stamp in rig.usem)
        # Zero weights: U_sem is sigma normalised.
        sigma = sigma_from_confidence(confidence)
        np.testing.assert_allclose(rig.usem[stamp][0], sigma / sigma.max(), atol=1e-6)
    finally:
        rig.close()
