"""Node transport on rclpy (a sourced ROS 2 Jazzy).

Our messages are rosbags dataclasses; they cross into rclpy as CDR bytes: publishers accept
serialised bytes, subscriptions are created with ``raw=True``, and services convert with
``rclpy.serialization``. Subscriptions and timers share one mutually exclusive callback group (one
callback at a time, like the DDS backend); services and clients use a reentrant group so a handler
may block while subscriptions keep running on a multi-threaded executor.

Not exercised by this package's tests (they run without ROS 2).
"""

from __future__ import annotations

import threading
import traceback
from collections.abc import Callable
from typing import Any

from area3d_msgs_py import msgs
from area3d_msgs_py.errors import InputError
from area3d_msgs_py.log import Logger

EXECUTOR_THREADS = 4


def _qos(latched: bool, depth: int):
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=1 if latched else depth,
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE,
    )


def _ros_class(type_name: str):
    from rosidl_runtime_py.utilities import get_interface

    return get_interface(type_name)


class RclpyPublisher:
    def __init__(self, publisher, type_name: str, topic: str) -> None:
        self._publisher = publisher
        self.type_name = type_name
        self.topic = topic

    def publish(self, msg: Any) -> None:
        if getattr(type(msg), "__msgtype__", None) != self.type_name:
            raise InputError(
                "msg", type(msg).__name__, f"a {self.type_name} for topic {self.topic}"
            )
        self._publisher.publish(msgs.serialize(msg, self.type_name))

    def publish_cdr(self, cdr: bytes) -> None:
        self._publisher.publish(bytes(cdr))

    def get_subscription_count(self) -> int:
        return self._publisher.get_subscription_count()


class RclpyClient:
    def __init__(self, node, srv_type: str, name: str, group) -> None:
        request_type, response_type = msgs.service_types(srv_type)
        self._srv_class = _ros_class(srv_type)
        self._client = node.create_client(self._srv_class, name, callback_group=group)
        self._request_type = request_type
        self._response_type = response_type
        self.name = name

    def wait_for_service(self, timeout_s: float = 5.0) -> bool:
        return self._client.wait_for_service(timeout_sec=timeout_s)

    def service_is_ready(self) -> bool:
        return self._client.service_is_ready()

    def call(self, request: Any, timeout_s: float = 10.0) -> Any:
        from rclpy.serialization import deserialize_message, serialize_message

        ros_request = deserialize_message(
            msgs.serialize(request, self._request_type), self._srv_class.Request
        )
        future = self._client.call_async(ros_request)
        done = threading.Event()
        future.add_done_callback(lambda _: done.set())
        if not done.wait(timeout_s):
            self._client.remove_pending_request(future)
            raise TimeoutError(f"service {self.name}: no response within {timeout_s} s")
        return msgs.deserialize(serialize_message(future.result()), self._response_type)


class RclpyTransport:
    """rclpy node plus a multi-threaded executor spinning it."""

    def __init__(self, node_name: str, logger: Logger, parameters: dict[str, Any]) -> None:
        import rclpy
        from rclpy.callback_groups import MutuallyExclusiveCallbackGroup, ReentrantCallbackGroup
        from rclpy.executors import MultiThreadedExecutor

        if not rclpy.ok():
            rclpy.init(args=None)
        self._rclpy = rclpy
        self.logger = logger
        self.node = rclpy.create_node(node_name)
        self._callbacks = MutuallyExclusiveCallbackGroup()
        self._services = ReentrantCallbackGroup()
        self._executor = MultiThreadedExecutor(num_threads=EXECUTOR_THREADS)
        self._executor.add_node(self.node)
        self._entities: list[Any] = []

    def _guard(self, fn: Callable, what: str) -> Callable:
        def call(*args):
            try:
                return fn(*args)
            except Exception:
                self.logger.error(f"exception in {what}:\n{traceback.format_exc()}")
                return None

        return call

    def create_publisher(
        self, type_name: str, topic: str, latched: bool, depth: int
    ) -> RclpyPublisher:
        msgs.get(type_name)
        pub = self.node.create_publisher(_ros_class(type_name), topic, _qos(latched, depth))
        return RclpyPublisher(pub, type_name, topic)

    def create_subscription(self, type_name, topic, callback, latched, depth, raw=False):
        msgs.get(type_name)
        guarded = self._guard(callback, f"subscription {topic}")

        def on_bytes(data: bytes) -> None:
            guarded(data if raw else msgs.deserialize(data, type_name))

        sub = self.node.create_subscription(
            _ros_class(type_name),
            topic,
            on_bytes,
            _qos(latched, depth),
            callback_group=self._callbacks,
            raw=True,
        )
        self._entities.append(sub)
        return sub

    def create_service(self, srv_type: str, name: str, handler: Callable[[Any], Any]):
        from rclpy.serialization import deserialize_message, serialize_message

        request_type, response_type = msgs.service_types(srv_type)
        srv_class = _ros_class(srv_type)

        def on_request(ros_request, ros_response):
            try:
                request = msgs.deserialize(serialize_message(ros_request), request_type)
                response = handler(request)
                return deserialize_message(
                    msgs.serialize(response, response_type), srv_class.Response
                )
            except Exception:
                self.logger.error(f"exception in service {name}:\n{traceback.format_exc()}")
                return ros_response

        service = self.node.create_service(
            srv_class, name, on_request, callback_group=self._services
        )
        self._entities.append(service)
        return service

    def create_client(self, srv_type: str, name: str) -> RclpyClient:
        return RclpyClient(self.node, srv_type, name, self._services)

    def create_timer(self, period_s: float, callback: Callable[[], None]):
        if not period_s > 0:
            raise InputError("period_s", period_s, "a positive number of seconds")
        return self.node.create_timer(
            period_s, self._guard(callback, "timer"), callback_group=self._callbacks
        )

    def wake(self) -> None:
        self._executor.wake()

    def spin_once(self, timeout_s: float) -> None:
        self._executor.spin_once(timeout_sec=timeout_s)

    def shutdown(self) -> None:
        self._executor.shutdown()
        self.node.destroy_node()
