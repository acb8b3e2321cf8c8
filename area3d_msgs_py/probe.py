"""A node of one's own beside a graph: it listens, publishes and calls services from the caller's
thread while an executor spins it in the background (tests, benchmarks, scripts).

    with Probe("driver") as probe:
        depths = probe.listen(msgs.Image, "area3d/perception/depth")
        goal = probe.publisher(msgs.PoseStamped, "area3d/camera/goal_pose")
        probe.wait_for_readers(goal, 1, timeout_s=30)
        goal.publish(...)
        probe.wait_for(lambda: depths, timeout_s=30)
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import rclpy
from rclpy.qos import QoSProfile

from area3d_msgs_py import qos, services
from area3d_msgs_py.spinning import GuardedMultiThreadedExecutor, Spinner


class Probe:
    def __init__(
        self, name: str = "probe", domain_id: int | None = None, namespace: str | None = None
    ) -> None:
        self.context = rclpy.Context()
        rclpy.init(context=self.context, domain_id=domain_id)
        self.node = rclpy.create_node(name, context=self.context, namespace=namespace)
        self.executor = GuardedMultiThreadedExecutor(num_threads=2, context=self.context)
        self.executor.add_node(self.node)
        self._spinner = Spinner(self.executor, name=f"{name}-spin")

    def listen(
        self, msg_type: type, topic: str, profile: QoSProfile | None = None, raw: bool = False
    ) -> list:
        """A list that fills with every message received on ``topic``."""
        received: list = []
        self.node.create_subscription(
            msg_type, topic, received.append, profile or qos.frames(), raw=raw
        )
        return received

    def publisher(self, msg_type: type, topic: str, profile: QoSProfile | None = None):
        return self.node.create_publisher(msg_type, topic, profile or qos.frames())

    def wait_for_readers(self, publisher, count: int, timeout_s: float) -> bool:
        return self.wait_for(lambda: publisher.get_subscription_count() >= count, timeout_s)

    @staticmethod
    def wait_for(predicate: Callable[[], Any], timeout_s: float, poll_s: float = 0.02) -> bool:
        deadline = time.monotonic() + timeout_s
        while not predicate():
            if time.monotonic() > deadline:
                return False
            time.sleep(poll_s)
        return True

    def call(self, srv_type: type, name: str, request: Any, timeout_s: float) -> Any:
        """Call a service and wait for the response (TimeoutError when none comes); the request
        is sent again while no reply comes (`services.call`), so the service must take a repeat."""
        client = self.node.create_client(srv_type, name)
        try:
            if not client.wait_for_service(timeout_sec=timeout_s):
                raise TimeoutError(f"service {name} did not appear within {timeout_s} s")
            return services.call(client, request, timeout_s)
        finally:
            self.node.destroy_client(client)

    def close(self) -> None:
        self._spinner.stop(timeout_s=2.0)
        self.node.destroy_node()
        self.context.try_shutdown()

    def __enter__(self) -> Probe:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
