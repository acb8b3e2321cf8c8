"""Transport on Cyclone DDS: two OS processes on loopback, services, latching, executor, run_node."""

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest
from area3d_msgs_py.node import Node, load_parameter_file

from area3d_msgs_py import codecs, dds_config, dds_types, msgs
from area3d_msgs_py.parameters import parse_ros_args

REPO_ROOT = Path(__file__).resolve().parents[2]
DOMAIN_ID = 1 + os.getpid() % 200
TIMEOUT_S = 20.0


@pytest.fixture(scope="module", autouse=True)
def loopback():
    with dds_config.loopback_domain(DOMAIN_ID):
        yield


def start(script: str) -> subprocess.Popen:
    env = dict(os.environ, PYTHONPATH=str(REPO_ROOT))
    return subprocess.Popen(
        [sys.executable, "-c", textwrap.dedent(script)],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def stop(proc: subprocess.Popen) -> tuple[str, str]:
    if proc.poll() is None:
        proc.terminate()
    try:
        return proc.communicate(timeout=10)
    except subprocess.TimeoutExpired:
        proc.kill()
        return proc.communicate()


def spin_until(node: Node, done, timeout_s: float = TIMEOUT_S) -> None:
    deadline = time.monotonic() + timeout_s
    while not done() and time.monotonic() < deadline:
        node.spin_once(0.05)


PUBLISHER_SCRIPT = """
    import time, numpy as np
    from area3d_msgs_py import codecs
    from area3d_msgs_py.node import Node
    node = Node("big_publisher", backend="dds")
    rng = np.random.default_rng(7)
    rgb = rng.integers(0, 256, (480, 640, 3), dtype=np.uint8)
    cloud = np.zeros(1_000_000, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("u", "<f4")])
    for name in cloud.dtype.names:
        cloud[name] = rng.standard_normal(cloud.size, dtype=np.float32)
    image_pub = node.create_publisher("sensor_msgs/msg/Image", "/test/image")
    cloud_pub = node.create_publisher("sensor_msgs/msg/PointCloud2", "/test/cloud")
    deadline = time.monotonic() + 20
    while (image_pub.get_subscription_count() < 1 or cloud_pub.get_subscription_count() < 1) and time.monotonic() < deadline:
        time.sleep(0.02)
    image_pub.publish(codecs.image_to_msg(rgb, "rgb8", 123, "cam"))
    cloud_pub.publish(codecs.pointcloud_to_msg(cloud, 456, "world"))
    print("published", flush=True)
    time.sleep(30)
"""


def test_image_and_million_point_cloud_cross_processes_intact():
    node = Node("big_subscriber", backend="dds")
    got = {}
    node.create_subscription(
        "sensor_msgs/msg/Image", "/test/image", lambda m: got.setdefault("image", m)
    )
    node.create_subscription(
        "sensor_msgs/msg/PointCloud2", "/test/cloud", lambda m: got.setdefault("cloud", m)
    )
    proc = start(PUBLISHER_SCRIPT)
    try:
        spin_until(node, lambda: len(got) == 2)
    finally:
        out, err = stop(proc)
        node.shutdown()
    assert len(got) == 2, f"received {sorted(got)}; publisher said {out!r} {err[-2000:]}"
    rng = np.random.default_rng(7)
    rgb = rng.integers(0, 256, (480, 640, 3), dtype=np.uint8)
    assert np.array_equal(codecs.msg_to_image(got["image"]), rgb)
    assert codecs.stamp_to_ns(got["image"].header.stamp) == 123
    cloud = codecs.msg_to_pointcloud(got["cloud"])
    assert cloud.shape == (1_000_000,)
    for name in ("x", "y", "z", "u"):
        assert np.array_equal(cloud[name], rng.standard_normal(1_000_000, dtype=np.float32))
    assert got["cloud"].header.frame_id == "world"


SERVER_SCRIPT = """
    from area3d_msgs_py import msgs
    from area3d_msgs_py.node import Node
    node = Node("plan_server", backend="dds")
    def handle(request):
        poses = [request.start, request.goal] * int(request.tolerance)
        return msgs.GetPlan_Response(plan=msgs.Path(header=request.goal.header, poses=poses))
    node.create_service("nav_msgs/srv/GetPlan", "/test/plan", handle)
    node.spin()
"""


def stamped(x: float, stamp_ns: int):
    T = np.eye(4)
    T[0, 3] = x
    return msgs.PoseStamped(header=codecs.header(stamp_ns, "world"), pose=codecs.matrix_to_pose(T))


def test_service_call_round_trips_and_reply_echoes_the_request_header():
    from cyclonedds.core import Policy, Qos
    from cyclonedds.sub import DataReader

    node = Node("plan_client", backend="dds")
    client = node.create_client("nav_msgs/srv/GetPlan", "/test/plan")
    _, reply_topic = dds_types.dds_service_topics("/test/plan")
    transport = node._transport
    spy = DataReader(
        transport.participant,
        transport.topic(reply_topic, "nav_msgs/srv/GetPlan_Response", True),
        Qos(Policy.Reliability.Reliable(10**9), Policy.History.KeepLast(10)),
    )
    proc = start(SERVER_SCRIPT)
    try:
        assert client.wait_for_service(TIMEOUT_S)
        response = client.call(
            msgs.GetPlan_Request(start=stamped(1.0, 5), goal=stamped(2.0, 9), tolerance=2.0), 10.0
        )
        second = client.call(
            msgs.GetPlan_Request(start=stamped(3.0, 5), goal=stamped(4.0, 9), tolerance=1.0), 10.0
        )
        time.sleep(0.2)
        replies = [s for s in spy.take(10) if s.sample_info.valid_data]
    finally:
        out, err = stop(proc)
        node.shutdown()
    xs = [p.pose.position.x for p in response.plan.poses]
    assert xs == [1.0, 2.0, 1.0, 2.0], err[-2000:]
    assert codecs.stamp_to_ns(response.plan.header.stamp) == 9
    assert [p.pose.position.x for p in second.plan.poses] == [3.0, 4.0]
    headers = [dds_types.split_request_header(s.data)[:2] for s in replies]
    assert headers == [(client.guid, 1), (client.guid, 2)]


def test_call_without_server_times_out():
    node = Node("lonely_client", backend="dds")
    try:
        client = node.create_client("nav_msgs/srv/GetPlan", "/test/nobody")
        assert not client.wait_for_service(0.3)
        with pytest.raises(TimeoutError):
            client.call(
                msgs.GetPlan_Request(start=stamped(0.0, 0), goal=stamped(0.0, 0), tolerance=0.0),
                0.3,
            )
    finally:
        node.shutdown()


LATE_SUBSCRIBER_SCRIPT = """
    import time
    from area3d_msgs_py.node import Node
    node = Node("late_subscriber", backend="dds")
    got = []
    node.create_subscription("std_msgs/msg/String", "/test/latched", lambda m: got.append(m.data), latched=True)
    deadline = time.monotonic() + 20
    while not got and time.monotonic() < deadline:
        node.spin_once(0.05)
    print("GOT:" + "|".join(got), flush=True)
    node.shutdown()
"""


def test_latched_message_published_before_the_subscriber_process_starts_reaches_it():
    node = Node("latcher", backend="dds")
    pub = node.create_publisher("std_msgs/msg/String", "/test/latched", latched=True)
    pub.publish(msgs.String(data="old"))
    pub.publish(msgs.String(data="grid v2"))
    proc = start(LATE_SUBSCRIBER_SCRIPT)
    try:
        out, err = proc.communicate(timeout=TIMEOUT_S + 10)
    finally:
        stop(proc)
        node.shutdown()
    assert "GOT:grid v2\n" in out, err[-2000:]  # keep-last 1: only the newest


def test_callback_exception_is_logged_and_the_node_keeps_running(capfd):
    talker = Node("talker", backend="dds")
    listener = Node("listener", backend="dds")
    got, ticks = [], []

    def on_msg(msg):
        if msg.data == "boom":
            raise RuntimeError("bad message")
        got.append(msg.data)

    listener.create_subscription("std_msgs/msg/String", "/test/chatter", on_msg)
    listener.create_timer(0.05, lambda: ticks.append(time.monotonic()))
    pub = talker.create_publisher("std_msgs/msg/String", "/test/chatter")
    try:
        spin_until(listener, lambda: pub.get_subscription_count() > 0, 10)
        pub.publish(msgs.String(data="boom"))
        pub.publish(msgs.String(data="fine"))
        spin_until(listener, lambda: got and len(ticks) >= 3, 10)
    finally:
        talker.shutdown()
        listener.shutdown()
    assert got == ["fine"]
    assert len(ticks) >= 3 and min(np.diff(ticks)) > 0.03
    err = capfd.readouterr().err
    assert "[ERROR]" in err and "[listener]" in err and "RuntimeError: bad message" in err


def test_publishing_the_wrong_type_is_rejected():
    node = Node("typed", backend="dds")
    try:
        pub = node.create_publisher("std_msgs/msg/String", "/test/typed")
        with pytest.raises(ValueError, match="msg"):
            pub.publish(msgs.Time(sec=0, nanosec=0))
    finally:
        node.shutdown()


def test_parameters_come_from_file_sections_and_overrides(tmp_path):
    params = tmp_path / "params.yaml"
    params.write_text(
        "/**:\n  ros__parameters:\n    gamma: 0.01\n    mode: batch\n"
        "planner:\n  ros__parameters:\n    gamma: 0.005\n    budget: 25\n    grid: {voxel_size: 0.02}\n"
        "perception:\n  ros__parameters:\n    budget: 99\n"
    )
    assert load_parameter_file(params, "planner") == {
        "gamma": 0.005,
        "mode": "batch",
        "budget": 25,
        "grid.voxel_size": 0.02,
    }
    args = parse_ros_args(
        [
            "--ros-args",
            "--params-file",
            str(params),
            "-p",
            "budget:=40",
            "-p",
            "mode:=closed",
            "-r",
            "__node:=planner",
        ]
    )
    assert args.node_name == "planner"
    assert args.parameters("planner") == {
        "gamma": 0.005,
        "mode": "closed",
        "budget": 40,
        "grid.voxel_size": 0.02,
    }
    node = Node("planner", args.parameters("planner"), backend="dds")
    try:
        assert node.declare_parameter("budget", 25) == 40
        assert node.declare_parameter("eta", 0.3) == 0.3
        assert node.declare_parameter("grid.voxel_size", 1) == 0.02
    finally:
        node.shutdown()


RUN_NODE_SCRIPT = """
    import sys
    from area3d_msgs_py import msgs
    from area3d_msgs_py.node import run_node

    class EchoNode:
        def __init__(self, node):
            budget = node.declare_parameter("budget", 25)
            self.pub = node.create_publisher("std_msgs/msg/String", "/test/run_node", latched=True)
            self.pub.publish(msgs.String(data=f"{node.name} budget={budget}"))

    sys.exit(run_node(EchoNode, sys.argv[1:]))
"""


def test_run_node_applies_ros_args_and_exits_cleanly_on_sigterm(tmp_path):
    params = tmp_path / "p.yaml"
    params.write_text("echo:\n  ros__parameters:\n    budget: 30\n")
    node = Node("watcher", backend="dds")
    got = []
    node.create_subscription(
        "std_msgs/msg/String", "/test/run_node", lambda m: got.append(m.data), latched=True
    )
    env = dict(os.environ, PYTHONPATH=str(REPO_ROOT))
    proc = subprocess.Popen(
        [
            sys.executable,
            "-c",
            textwrap.dedent(RUN_NODE_SCRIPT),
            "--ros-args",
            "--params-file",
            str(params),
            "-r",
            "__node:=echo",
            "-p",
            "budget:=31",
        ],
        env=env,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        spin_until(node, lambda: got)
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=10)
    finally:
        stop(proc)
        node.shutdown()
    assert got == ["echo budget=31"], err[-2000:]
    assert proc.returncode == 0, err[-2000:]
