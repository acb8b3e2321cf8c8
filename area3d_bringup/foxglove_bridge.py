"""Foxglove live view: every topic of the graph on a Foxglove WebSocket, with no ROS 2 install.

A node of its own (`foxglove_bridge`) looks up the graph's topics every `discovery_period_s`
(any node's topics, /tf and /tf_static included, not only AREA3D's) and advertises each on a
Foxglove WebSocket server (`foxglove-sdk`) as a channel with message encoding `cdr` and schema
encoding `ros2msg` (the message definition with its dependencies, `area3d_msgs_py/msgdef.py`).
It subscribes a topic only while a client is subscribed to its channel, with `raw=True`, and
hands the CDR bytes it receives to the server unchanged: nothing is decoded or encoded.

A slow or vanished client never slows the graph: the node's callback only queues the bytes for
each client, each client's queue holds at most `backlog` messages (the oldest is dropped
beyond), and the server writes to the sockets on threads of its own. With no client subscribed
the node holds no subscription at all, so the graph's publishers do no work for it.

    area3d launch --foxglove            # ws://127.0.0.1:8765, open it in Foxglove
    python -m area3d_bringup.foxglove_bridge --ros-args -p port:=8766 -p address:=0.0.0.0
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import foxglove
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from area3d_bringup.launch_description import NodeSpec
from area3d_msgs_py import msgs, topics
from area3d_msgs_py.errors import InputError
from area3d_msgs_py.lifecycle import exit_process, run_node
from area3d_msgs_py.msgdef import message_definition
from area3d_msgs_py.parameters import Param, declare_parameters, report_unknown_parameters
from area3d_msgs_py.status import StatusPublisher

NODE_NAME = topics.FOXGLOVE_BRIDGE
MODULE = "area3d_bringup.foxglove_bridge"
DEFAULT_PORT = 8765  # Foxglove's default
DEFAULT_ADDRESS = "127.0.0.1"  # this machine only unless told otherwise
# Messages queued per client: foxglove-sdk's default (1024) could hold 1.2 GB of 640x480 depth
# images for a client that stops reading; 16 hold 20 MB, and a client that keeps up never has
# more than a few queued.
DEFAULT_BACKLOG = 16
# A reader of ours keeps this many messages per topic; the callback only queues bytes, so a
# deeper queue would only delay what a viewer sees.
READER_DEPTH = 10
# How often the readers follow the clients' subscriptions, seconds (a new subscription waits at
# most this long for its first message).
FOLLOW_PERIOD_S = 0.1

PARAMS = (
    Param("port", DEFAULT_PORT, "TCP port of the Foxglove WebSocket (0: any free port)", range=(0, 65535)),
    Param(
        "address",
        DEFAULT_ADDRESS,
        "address the WebSocket listens on (127.0.0.1: this machine only; 0.0.0.0: every interface)",
    ),
    Param(
        "backlog",
        DEFAULT_BACKLOG,
        "messages queued per client at most; beyond it the oldest is dropped",
        range=(1, 1024),
    ),
    Param(
        "discovery_period_s",
        0.5,
        "how often the graph's topics are looked up, seconds",
        range=(0.05, 60.0),
    ),
)  # fmt: skip


def url(address: str, port: int) -> str:
    """The WebSocket URL a Foxglove client opens."""
    return f"ws://{'localhost' if address in ('127.0.0.1', '::1') else address}:{port}"


def reader_qos(publishers: Sequence[Any]) -> QoSProfile:
    """A reader that matches every publisher of a topic and gets what a late joiner can get:
    transient local when all publishers keep their last messages (a latched grid, /tf_static),
    reliable when all are reliable, keep-last READER_DEPTH."""
    profiles = [info.qos_profile for info in publishers]
    latched = bool(profiles) and all(
        p.durability == DurabilityPolicy.TRANSIENT_LOCAL for p in profiles
    )
    reliable = all(p.reliability == ReliabilityPolicy.RELIABLE for p in profiles)
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=READER_DEPTH,
        reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE,
    )


@dataclass
class Forwarded:
    """One topic on the WebSocket: its channel, the reader while a client wants it, counters."""

    topic: str
    type_name: str
    msg_type: type
    channel: foxglove.Channel
    subscription: Any = None
    messages: int = 0
    bytes: int = 0


class FoxgloveBridgeNode(Node):
    """Advertises the graph's topics on a Foxglove WebSocket and forwards their CDR as-is."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(NODE_NAME, **kwargs)
        p = declare_parameters(self, PARAMS)
        report_unknown_parameters(self)
        self.topics: dict[str, Forwarded] = {}  # by topic, each forwarded while a client wants it
        self.skipped: set[tuple[str, str]] = set()  # (topic, type) that cannot be forwarded
        self.live = foxglove.Context()  # channels of this server only
        try:
            self.server = foxglove.start_server(
                name="area3d",
                host=p["address"],
                port=p["port"],
                context=self.live,
                message_backlog_size=p["backlog"],
            )
        except Exception as exc:  # the SDK raises a bare RuntimeError for a port in use
            raise InputError(
                "port",
                f"{p['address']}:{p['port']}",
                f"an address and TCP port free for the Foxglove WebSocket ({exc}); "
                "pick another with --foxglove PORT",
            ) from None
        self.url = url(p["address"], self.server.port)
        self.callback_cpu_ns = 0
        self.status = StatusPublisher(self, topics.FOXGLOVE_STATUS, self._status)
        self.create_timer(p["discovery_period_s"], self.discover)
        self.create_timer(FOLLOW_PERIOD_S, self.follow_clients)
        self.get_logger().info(f"Foxglove live view on {self.url} (open it in Foxglove)")

    # -- the graph's topics -> channels (executor thread) --------------------------------------
    def discover(self) -> None:
        """Advertise topics that gained a publisher; withdraw those that have none left."""
        listed = dict(self.get_topic_names_and_types())
        for topic, types in listed.items():
            if topic in self.topics or not types or not self.count_publishers(topic):
                continue
            self._advertise(topic, types[0])
        for topic in [t for t in self.topics if t not in listed or not self.count_publishers(t)]:
            self._withdraw(topic)

    def _advertise(self, topic: str, type_name: str) -> None:
        if (topic, type_name) in self.skipped:
            return
        try:
            definition = message_definition(type_name)
            msg_type = msgs.get(type_name)
        except InputError as exc:
            self.skipped.add((topic, type_name))
            self.get_logger().warning(f"{topic} is not forwarded: {exc}")
            return
        schema = foxglove.Schema(name=type_name, encoding="ros2msg", data=definition.encode())
        channel = foxglove.Channel(topic, schema=schema, message_encoding="cdr", context=self.live)
        self.topics[topic] = Forwarded(topic, type_name, msg_type, channel)
        self.get_logger().debug(f"advertised {topic} ({type_name}) as channel {channel.id()}")

    def _withdraw(self, topic: str) -> None:
        forwarded = self.topics.pop(topic)
        self.get_logger().info(f"{topic} has no publisher left: channel withdrawn")
        if forwarded.subscription is not None:
            self.destroy_subscription(forwarded.subscription)
        forwarded.channel.close()

    # -- clients' subscriptions -> readers ------------------------------------------------------
    def follow_clients(self) -> None:
        """Hold a reader on each topic that a client is subscribed to, and on no other.

        Polled on the executor rather than told by a server listener: no Python runs on the
        server's threads, which only write to the sockets."""
        for topic, forwarded in self.topics.items():
            wanted = forwarded.channel.has_sinks()
            if wanted and forwarded.subscription is None:
                forwarded.subscription = self.create_subscription(
                    forwarded.msg_type,
                    topic,
                    self._forwarder(forwarded),
                    reader_qos(self.get_publishers_info_by_topic(topic)),
                    raw=True,
                )
            elif not wanted and forwarded.subscription is not None:
                self.destroy_subscription(forwarded.subscription)
                forwarded.subscription = None

    def _forwarder(self, forwarded: Forwarded):
        log = forwarded.channel.log

        def forward(data: bytes) -> None:
            t0 = time.thread_time_ns()
            log(data, log_time=time.time_ns())
            self.callback_cpu_ns += time.thread_time_ns() - t0
            forwarded.messages += 1
            forwarded.bytes += len(data)

        return forward

    def _status(self) -> dict:
        return {
            "node": NODE_NAME,
            "url": self.url,
            "topics_advertised": len(self.topics),
            "topics_forwarded": sorted(t for t, f in self.topics.items() if f.subscription),
            "messages_forwarded": sum(f.messages for f in self.topics.values()),
            "bytes_forwarded": sum(f.bytes for f in self.topics.values()),
            # CPU time of the callbacks handing messages to the server (the server's own threads
            # copy them to each client's socket)
            "callback_cpu_s": round(self.callback_cpu_ns / 1e9, 6),
            "not_forwarded": sorted(topic for topic, _ in self.skipped),
        }

    def destroy_node(self) -> None:
        self.server.stop()
        super().destroy_node()


def bridge_spec(port: int = DEFAULT_PORT, address: str = DEFAULT_ADDRESS) -> NodeSpec:
    """The bridge as one more node process of a launch (`area3d launch|run --foxglove`)."""
    return NodeSpec(NODE_NAME, MODULE, {"port": int(port), "address": address})


def main(args: Sequence[str] | None = None) -> int:
    return run_node(FoxgloveBridgeNode, NODE_NAME, args)


if __name__ == "__main__":
    exit_process(main())
