"""Node transport on Cyclone DDS with ROS 2's wire conventions (used when rclpy is not available).

Topics ``/a`` are DDS topics ``rt/a`` with types ``pkg::msg::dds_::Name_``; services use
``rq/<name>Request`` / ``rr/<name>Reply`` with the rmw_cyclonedds request header; payloads are
rosbags CDR. Subscription callbacks and timers run on the thread that spins; service handlers on a
small thread pool (so they may block); client replies are matched on a per-client thread.
"""

from __future__ import annotations

import itertools
import random
import threading
import time
import traceback
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

from cyclonedds.core import (
    GuardCondition,
    InstanceState,
    Policy,
    Qos,
    ReadCondition,
    SampleState,
    ViewState,
    WaitSet,
)
from cyclonedds.domain import DomainParticipant
from cyclonedds.pub import DataWriter
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic

from area3d_msgs_py import msgs
from area3d_msgs_py.dds_types import (
    add_request_header,
    dds_service_topics,
    dds_topic_name,
    split_request_header,
    wire_sample,
    wire_type,
)
from area3d_msgs_py.errors import InputError
from area3d_msgs_py.log import Logger

# ROS 2 rmw_qos_profile_default / services_default: reliable, volatile, keep-last 10.
DEFAULT_DEPTH = 10
# How long a reliable write may block on a full history before failing (rmw_cyclonedds: 100 ms;
# longer here because a 16 MB sample takes tens of milliseconds to leave the writer cache).
MAX_BLOCKING_NS = 1_000_000_000
SERVICE_WORKERS = 4
REPLY_MATCH_WAIT_S = 1.0
TAKE_BATCH = 32
_ANY_STATE = SampleState.Any | ViewState.Any | InstanceState.Any


def make_qos(latched: bool, depth: int) -> Qos:
    """ROS default QoS, or ROS 'latched' (transient-local, keep-last 1) for late joiners."""
    if latched:
        return Qos(
            Policy.Reliability.Reliable(MAX_BLOCKING_NS),
            Policy.Durability.TransientLocal,
            Policy.History.KeepLast(1),
        )
    if not isinstance(depth, int) or depth < 1:
        raise InputError("depth", depth, "an int >= 1 (history depth)")
    return Qos(
        Policy.Reliability.Reliable(MAX_BLOCKING_NS),
        Policy.Durability.Volatile,
        Policy.History.KeepLast(depth),
    )


class DdsPublisher:
    def __init__(self, writer: DataWriter, type_name: str, topic: str) -> None:
        self._writer = writer
        self._cls = writer.data_type
        self.type_name = type_name
        self.topic = topic

    def publish(self, msg: Any) -> None:
        """Send one message (a dataclass of ``type_name``)."""
        if getattr(type(msg), "__msgtype__", None) != self.type_name:
            raise InputError(
                "msg", type(msg).__name__, f"a {self.type_name} for topic {self.topic}"
            )
        self._writer.write(wire_sample(self._cls, msgs.serialize(msg, self.type_name)))

    def publish_cdr(self, cdr: bytes) -> None:
        """Send already serialised CDR bytes of ``type_name``."""
        self._writer.write(wire_sample(self._cls, bytes(cdr)))

    def get_subscription_count(self) -> int:
        return len(self._writer.get_matched_subscriptions())


@dataclass
class _Subscription:
    reader: DataReader
    condition: ReadCondition
    type_name: str
    topic: str
    callback: Callable[[Any], None]
    raw: bool = False

    def get_publisher_count(self) -> int:
        return len(self.reader.get_matched_publications())


@dataclass
class _Service:
    reader: DataReader
    writer: DataWriter
    condition: ReadCondition
    request_type: str
    response_type: str
    name: str
    handler: Callable[[Any], Any]


@dataclass
class _Timer:
    period_ns: int
    next_ns: int
    callback: Callable[[], None]
    cancelled: bool = False

    def cancel(self) -> None:
        self.cancelled = True


class DdsClient:
    """Service client; ``call`` may be used from any thread, including a callback's."""

    def __init__(self, transport: DdsTransport, srv_type: str, name: str) -> None:
        request_type, response_type = msgs.service_types(srv_type)
        rq, rr = dds_service_topics(name)
        self.name = name
        self._request_type = request_type
        self._response_type = response_type
        qos = make_qos(False, DEFAULT_DEPTH)
        self._writer = DataWriter(
            transport.participant, transport.topic(rq, request_type, True), qos
        )
        self._reader = DataReader(
            transport.participant, transport.topic(rr, response_type, True), qos
        )
        self._cls = self._writer.data_type
        # rmw_cyclonedds uses 8 bytes of the client's writer GUID; any id unique on the domain works.
        self.guid = random.getrandbits(64)
        self._seq = itertools.count(1)
        self._pending: dict[int, Future] = {}
        self._lock = threading.Lock()
        self._closed = threading.Event()
        self._waitset = WaitSet(transport.participant)
        self._condition = ReadCondition(self._reader, _ANY_STATE)
        self._waitset.attach(self._condition)
        self._thread = threading.Thread(target=self._receive, name=f"client{name}", daemon=True)
        self._thread.start()

    def wait_for_service(self, timeout_s: float = 5.0) -> bool:
        """True once a server's request reader and reply writer are both matched."""
        deadline = time.monotonic() + timeout_s
        while True:
            if self._writer.get_matched_subscriptions() and self._reader.get_matched_publications():
                return True
            if time.monotonic() >= deadline or self._closed.is_set():
                return False
            time.sleep(0.02)

    def service_is_ready(self) -> bool:
        return self.wait_for_service(0.0)

    def call(self, request: Any, timeout_s: float = 10.0) -> Any:
        """Send ``request`` and wait for its response; raises TimeoutError after ``timeout_s``."""
        if getattr(type(request), "__msgtype__", None) != self._request_type:
            raise InputError("request", type(request).__name__, f"a {self._request_type}")
        seq = next(self._seq)
        future: Future = Future()
        with self._lock:
            self._pending[seq] = future
        try:
            cdr = add_request_header(msgs.serialize(request, self._request_type), self.guid, seq)
            self._writer.write(wire_sample(self._cls, cdr))
            try:
                return future.result(timeout=timeout_s)
            except TimeoutError:
                raise TimeoutError(
                    f"service {self.name}: no response within {timeout_s} s"
                ) from None
        finally:
            with self._lock:
                self._pending.pop(seq, None)

    def _receive(self) -> None:
        while not self._closed.is_set():
            self._waitset.wait(100_000_000)
            if self._closed.is_set():
                return
            for sample in self._reader.take(TAKE_BATCH):
                if not sample.sample_info.valid_data:
                    continue
                guid, seq, body = split_request_header(sample.data)
                if guid != self.guid:
                    continue
                with self._lock:
                    future = self._pending.get(seq)
                if future is None or future.done():
                    continue
                try:
                    future.set_result(msgs.deserialize(body, self._response_type))
                except Exception as exc:  # a malformed reply fails this call, not the thread
                    future.set_exception(exc)

    def close(self) -> None:
        self._closed.set()
        self._thread.join(timeout=1.0)


class DdsTransport:
    """One DDS participant per node, with its entities and an executor."""

    def __init__(self, node_name: str, logger: Logger, domain_id: int) -> None:
        self.node_name = node_name
        self.logger = logger
        self.participant = DomainParticipant(domain_id)
        self._topics: dict[str, Topic] = {}
        self._subscriptions: list[_Subscription] = []
        self._services: list[_Service] = []
        self._clients: list[DdsClient] = []
        self._timers: list[_Timer] = []
        self._publishers: list[DdsPublisher] = []
        self._entity_lock = threading.RLock()
        self._spin_lock = threading.Lock()
        self._waitset = WaitSet(self.participant)
        self._guard = GuardCondition(self.participant)
        self._waitset.attach(self._guard)
        self._pool = ThreadPoolExecutor(SERVICE_WORKERS, thread_name_prefix=f"{node_name}-srv")
        self._closed = False

    def topic(self, dds_name: str, type_name: str, request_header: bool = False) -> Topic:
        with self._entity_lock:
            if dds_name not in self._topics:
                self._topics[dds_name] = Topic(
                    self.participant, dds_name, wire_type(type_name, request_header)
                )
            topic = self._topics[dds_name]
            expected = wire_type(type_name, request_header)
            if topic.data_type is not expected:
                raise InputError(
                    dds_name, type_name, f"the type already used on it ({topic.data_type.__name__})"
                )
            return topic

    def create_publisher(
        self, type_name: str, topic: str, latched: bool, depth: int
    ) -> DdsPublisher:
        msgs.get(type_name)
        qos = make_qos(latched, depth)
        writer = DataWriter(self.participant, self.topic(dds_topic_name(topic), type_name), qos)
        pub = DdsPublisher(writer, type_name, topic)
        self._publishers.append(pub)
        return pub

    def create_subscription(
        self,
        type_name: str,
        topic: str,
        callback: Callable[[Any], None],
        latched: bool,
        depth: int,
        raw: bool = False,
    ) -> _Subscription:
        msgs.get(type_name)
        qos = make_qos(latched, depth)
        reader = DataReader(self.participant, self.topic(dds_topic_name(topic), type_name), qos)
        condition = ReadCondition(reader, _ANY_STATE)
        sub = _Subscription(reader, condition, type_name, topic, callback, raw)
        with self._entity_lock:
            self._subscriptions.append(sub)
            self._waitset.attach(condition)
        return sub

    def create_service(self, srv_type: str, name: str, handler: Callable[[Any], Any]) -> _Service:
        request_type, response_type = msgs.service_types(srv_type)
        rq, rr = dds_service_topics(name)
        qos = make_qos(False, DEFAULT_DEPTH)
        reader = DataReader(self.participant, self.topic(rq, request_type, True), qos)
        writer = DataWriter(self.participant, self.topic(rr, response_type, True), qos)
        condition = ReadCondition(reader, _ANY_STATE)
        service = _Service(reader, writer, condition, request_type, response_type, name, handler)
        with self._entity_lock:
            self._services.append(service)
            self._waitset.attach(condition)
        return service

    def create_client(self, srv_type: str, name: str) -> DdsClient:
        client = DdsClient(self, srv_type, name)
        self._clients.append(client)
        return client

    def create_timer(self, period_s: float, callback: Callable[[], None]) -> _Timer:
        if not period_s > 0:
            raise InputError("period_s", period_s, "a positive number of seconds")
        period_ns = int(period_s * 1e9)
        timer = _Timer(period_ns, time.monotonic_ns() + period_ns, callback)
        with self._entity_lock:
            self._timers.append(timer)
        self._guard.set(True)
        return timer

    def wake(self) -> None:
        """Make a blocked ``spin_once`` return early."""
        if not self._closed:
            self._guard.set(True)

    def spin_once(self, timeout_s: float) -> None:
        """Wait up to ``timeout_s`` (shortened by due timers) and run what is ready."""
        with self._spin_lock:
            now = time.monotonic_ns()
            with self._entity_lock:
                timers = [t for t in self._timers if not t.cancelled]
            wait_ns = int(max(timeout_s, 0.0) * 1e9)
            if timers:
                wait_ns = min(wait_ns, max(0, min(t.next_ns for t in timers) - now))
            if wait_ns > 0:
                self._waitset.wait(wait_ns)
            self._guard.take()
            self._run_timers()
            with self._entity_lock:
                subscriptions = list(self._subscriptions)
                services = list(self._services)
            for sub in subscriptions:
                self._take_subscription(sub)
            for service in services:
                self._take_requests(service)

    def _run_timers(self) -> None:
        now = time.monotonic_ns()
        with self._entity_lock:
            timers = [t for t in self._timers if not t.cancelled]
        for timer in timers:
            if timer.next_ns <= now:
                # Fixed-rate like rclpy; a late timer fires once and skips the missed periods.
                timer.next_ns += timer.period_ns * max(
                    1, (now - timer.next_ns) // timer.period_ns + 1
                )
                self._guarded(timer.callback, (), "timer")

    def _take_subscription(self, sub: _Subscription) -> None:
        for sample in sub.reader.take(TAKE_BATCH):
            if not sample.sample_info.valid_data:
                continue
            if sub.raw:
                self._guarded(sub.callback, (sample.data,), f"subscription {sub.topic}")
                continue
            try:
                msg = msgs.deserialize(sample.data, sub.type_name)
            except Exception:
                self.logger.error(
                    f"dropped an undecodable {sub.type_name} on {sub.topic}:\n{traceback.format_exc()}"
                )
                continue
            self._guarded(sub.callback, (msg,), f"subscription {sub.topic}")

    def _take_requests(self, service: _Service) -> None:
        for sample in service.reader.take(TAKE_BATCH):
            if not sample.sample_info.valid_data:
                continue
            try:
                guid, seq, body = split_request_header(sample.data)
                request = msgs.deserialize(body, service.request_type)
            except Exception:
                self.logger.error(
                    f"dropped an undecodable request on {service.name}:\n{traceback.format_exc()}"
                )
                continue
            self._pool.submit(self._serve, service, guid, seq, request)

    def _serve(self, service: _Service, guid: int, seq: int, request: Any) -> None:
        try:
            response = service.handler(request)
            if getattr(type(response), "__msgtype__", None) != service.response_type:
                raise InputError("response", type(response).__name__, f"a {service.response_type}")
            cdr = add_request_header(msgs.serialize(response, service.response_type), guid, seq)
            # Discovery is not symmetric: a first request can arrive before our reply writer has
            # matched the client's reply reader, and a volatile reply would then be lost.
            deadline = time.monotonic() + REPLY_MATCH_WAIT_S
            while not service.writer.get_matched_subscriptions() and time.monotonic() < deadline:
                time.sleep(0.005)
            service.writer.write(wire_sample(service.writer.data_type, cdr))
        except Exception:
            self.logger.error(f"exception in service {service.name}:\n{traceback.format_exc()}")

    def _guarded(self, fn: Callable, args: tuple, what: str) -> None:
        try:
            fn(*args)
        except Exception:
            self.logger.error(f"exception in {what}:\n{traceback.format_exc()}")

    def shutdown(self) -> None:
        if self._closed:
            return
        self._closed = True
        self._guard.set(True)
        for client in self._clients:
            client.close()
        self._pool.shutdown(wait=True, cancel_futures=True)
        with self._spin_lock:
            self._subscriptions.clear()
            self._services.clear()
            self._timers.clear()
            self._publishers.clear()
            self._topics.clear()
            # Deleting the participant deletes every reader, writer and condition under it (the
            # Python wrappers are kept alive by cyclonedds' entity registry until deleted).
            self.participant.__del__()
