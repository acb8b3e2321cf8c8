"""Topic benchmark: two rclpy processes on this machine, publish-to-receive latency and throughput.

The publisher process stamps each message with its wall clock just before ``publish`` (so
serialisation, DDS transfer and deserialisation are all inside the figure); this process receives
with a normal subscription on a single-threaded executor and subtracts the stamp from its clock
on arrival. Both use the middleware setup of the graph (`middleware.configure`: Fast DDS with a
32 MB shared-memory segment) and the graph's frame QoS (reliable, volatile, keep-last).
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import rclpy
from rclpy.executors import SingleThreadedExecutor

from area3d_msgs_py import middleware, msgs, qos

REPO_ROOT = Path(__file__).resolve().parents[1]
# p95 publish-to-receive targets (README, "Benchmarks"): a 640x480 32FC1 depth frame < 10 ms,
# the smaller rgb8 frame too; the 16 MB cloud (the largest sample the graph may carry) < 100 ms.
P95_TARGET_MS = {"rgb8": 10.0, "32FC1": 10.0, "cloud": 100.0}
LATENCY_PERIOD_S = {"rgb8": 0.02, "32FC1": 0.02, "cloud": 0.25}

PUBLISHER = """
import sys, time, numpy as np, rclpy
from area3d_msgs_py import codecs, middleware, msgs, qos
case, n_latency, n_burst, period = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), float(sys.argv[4])
middleware.configure()
rclpy.init()
node = rclpy.create_node("bench_publisher")
rng = np.random.default_rng(0)
if case == "cloud":
    cloud = np.zeros(1_000_000, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("uncertainty", "<f4")])
    for name in cloud.dtype.names:
        cloud[name] = rng.random(cloud.size, dtype=np.float32)
    msg = codecs.pointcloud_to_msg(cloud, 0, "world")
    pub = node.create_publisher(msgs.PointCloud2, "bench/data", qos.frames())
elif case == "rgb8":
    msg = codecs.image_to_msg(rng.integers(0, 256, (480, 640, 3), dtype=np.uint8), "rgb8", 0, "cam")
    pub = node.create_publisher(msgs.Image, "bench/data", qos.frames())
else:
    msg = codecs.image_to_msg(rng.random((480, 640), dtype=np.float32) * 5, "32FC1", 0, "cam")
    pub = node.create_publisher(msgs.Image, "bench/data", qos.frames())
done = node.create_publisher(msgs.String, "bench/done", qos.latched())
deadline = time.monotonic() + 30
while pub.get_subscription_count() < 1 and time.monotonic() < deadline:
    time.sleep(0.02)
time.sleep(0.5)
for phase, count, pause in (("latency", n_latency, period), ("burst", n_burst, 0.0)):
    msg.header.frame_id = phase
    for _ in range(count):
        msg.header.stamp = codecs.ns_to_stamp(time.time_ns())
        pub.publish(msg)
        if pause:
            time.sleep(pause)
    time.sleep(1.0)
done.publish(msgs.String(data="done"))
time.sleep(2.0)
"""


def _measure(case: str, samples: int, timeout_s: float) -> dict:
    context = rclpy.Context()
    rclpy.init(context=context)
    node = rclpy.create_node("bench_receiver", context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    msg_type = msgs.PointCloud2 if case == "cloud" else msgs.Image
    latencies: list[float] = []
    burst: list[tuple[int, int]] = []  # (arrival ns, bytes)
    finished: list[bool] = []

    def on_data(msg) -> None:
        now = time.time_ns()
        if msg.header.frame_id == "latency":
            sent = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
            latencies.append((now - sent) / 1e6)
        else:
            burst.append((now, len(msg.data)))

    node.create_subscription(msg_type, "bench/data", on_data, qos.frames())
    node.create_subscription(
        msgs.String, "bench/done", lambda m: finished.append(True), qos.latched()
    )
    env = dict(os.environ, PYTHONPATH=str(REPO_ROOT))
    args = [case, str(samples), str(samples), str(LATENCY_PERIOD_S[case])]
    proc = subprocess.Popen([sys.executable, "-c", textwrap.dedent(PUBLISHER), *args], env=env)
    deadline = time.monotonic() + timeout_s
    try:
        while not finished and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.05)
    finally:
        proc.terminate()
        proc.wait(timeout=10)
        executor.shutdown()
        node.destroy_node()
        context.try_shutdown()
    lat = np.array(latencies) if latencies else np.array([np.nan])
    result = {
        "sent": samples,
        "received": len(latencies),
        "p50_ms": float(np.percentile(lat, 50)),
        "p95_ms": float(np.percentile(lat, 95)),
        "burst_received": len(burst),
    }
    if len(burst) >= 2:
        seconds = (burst[-1][0] - burst[0][0]) / 1e9
        payload = sum(b for _, b in burst[1:])
        result["mb_per_s"] = payload / 1e6 / seconds
        result["msgs_per_s"] = (len(burst) - 1) / seconds
    else:
        result["mb_per_s"] = result["msgs_per_s"] = float("nan")
    return result


def measure_topics(samples: int = 200, cloud_samples: int = 20) -> dict:
    """Latency p50/p95 and throughput for 640x480 rgb8, 640x480 32FC1, 1M-point PointCloud2.

    Returns ``{"rgb8": {...}, "32FC1": {...}, "cloud": {...}}`` with keys sent, received, p50_ms,
    p95_ms, burst_received, mb_per_s, msgs_per_s, target_p95_ms.
    """
    middleware.configure()
    results = {
        "rgb8": _measure("rgb8", samples, 60 + samples * 0.1),
        "32FC1": _measure("32FC1", samples, 60 + samples * 0.1),
        "cloud": _measure("cloud", cloud_samples, 60 + cloud_samples * 2.0),
    }
    for key, result in results.items():
        result["target_p95_ms"] = P95_TARGET_MS[key]
    return results
