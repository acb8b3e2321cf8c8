"""The node API every AREA3D node is written against: rclpy when ROS 2 is sourced, else Cyclone DDS.

    node = Node("planner", {"budget": 25})
    budget = node.declare_parameter("budget", 25)
    pub = node.create_publisher("nav_msgs/msg/Path", "/area3d/planner/next_views")
    node.create_subscription("sensor_msgs/msg/Image", "/area3d/perception/depth", on_depth)
    node.spin()

Messages are the rosbags dataclasses of ``area3d_msgs_py.msgs`` with either transport.
"""

from __future__ import annotations

import signal
import sys
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any

from area3d_msgs_py.dds_config import domain_id_from_env
from area3d_msgs_py.errors import InputError
from area3d_msgs_py.log import Logger
from area3d_msgs_py.parameters import load_parameter_file, parse_ros_args

__all__ = ["Node", "run_node", "load_parameter_file", "rclpy_available"]

BACKENDS = ("auto", "dds", "rclpy")
SPIN_SLICE_S = 0.1  # how often spin() looks at the shutdown flag and signals


def rclpy_available() -> bool:
    """True when ``import rclpy`` works (a sourced ROS 2)."""
    try:
        import rclpy  # noqa: F401
    except ImportError:
        return False
    return True


class Node:
    """A ROS 2 node on rclpy or on Cyclone DDS with ROS 2 wire conventions.

    ``parameters``: values from the parameter file / ``-p`` overrides (``declare_parameter`` returns
    them, else the default); ``remaps``: topic and service name remappings ``{"/from": "/to"}``.
    """

    def __init__(
        self,
        name: str,
        parameters: dict[str, Any] | None = None,
        backend: str = "auto",
        remaps: dict[str, str] | None = None,
        log_level: str = "INFO",
    ) -> None:
        if not isinstance(name, str) or not name or not name.replace("_", "a").isalnum():
            raise InputError("name", name, "a ROS node name (letters, digits, underscores)")
        if backend not in BACKENDS:
            raise InputError("backend", backend, f"one of {BACKENDS}")
        if backend == "auto":
            backend = "rclpy" if rclpy_available() else "dds"
        self.name = name
        self.backend = backend
        self._parameters = dict(parameters or {})
        self._declared: dict[str, Any] = {}
        self._remaps = dict(remaps or {})
        self._logger = Logger(name, log_level)
        self._shutdown = threading.Event()
        if backend == "dds":
            from area3d_msgs_py.dds_transport import DdsTransport

            self._transport = DdsTransport(name, self._logger, domain_id_from_env())
        else:
            from area3d_msgs_py.rclpy_transport import RclpyTransport

            self._transport = RclpyTransport(name, self._logger, self._parameters)

    # parameters ---------------------------------------------------------------------------
    def declare_parameter(self, name: str, default: Any) -> Any:
        """The value given at start (parameter file or ``-p``), else ``default``.

        An int given for a float default is widened to float, as ROS 2 YAML users expect.
        """
        value = self._parameters.get(name, default)
        if isinstance(default, float) and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        self._declared[name] = value
        return value

    def get_parameter(self, name: str) -> Any:
        if name not in self._declared:
            raise InputError(
                "parameter", name, f"one of the declared parameters {sorted(self._declared)}"
            )
        return self._declared[name]

    @property
    def parameters(self) -> dict[str, Any]:
        """Declared parameters and their values."""
        return dict(self._declared)

    # entities -----------------------------------------------------------------------------
    def get_logger(self) -> Logger:
        return self._logger

    def resolve(self, name: str) -> str:
        """Apply remappings; relative names become absolute (``foo`` -> ``/foo``)."""
        full = name if name.startswith("/") else "/" + name
        return self._remaps.get(full, self._remaps.get(name, full))

    def create_publisher(self, type_name: str, topic: str, latched: bool = False, depth: int = 10):
        """Publisher with ``publish(msg)``; ``latched`` = transient-local keep-last 1."""
        return self._transport.create_publisher(type_name, self.resolve(topic), latched, depth)

    def create_subscription(
        self,
        type_name: str,
        topic: str,
        callback: Callable[[Any], None],
        latched: bool = False,
        depth: int = 10,
    ):
        """``callback(msg)`` runs on the spin thread, one at a time."""
        return self._transport.create_subscription(
            type_name, self.resolve(topic), callback, latched, depth
        )

    def create_service(self, srv_type_name: str, name: str, handler: Callable[[Any], Any]):
        """``handler(request) -> response`` runs on a worker thread and may block."""
        return self._transport.create_service(srv_type_name, self.resolve(name), handler)

    def create_client(self, srv_type_name: str, name: str):
        """Client with ``wait_for_service(timeout_s) -> bool`` and ``call(request, timeout_s)``."""
        return self._transport.create_client(srv_type_name, self.resolve(name))

    def create_timer(self, period_s: float, callback: Callable[[], None]):
        """``callback()`` every ``period_s`` seconds on the spin thread."""
        return self._transport.create_timer(period_s, callback)

    def now_ns(self) -> int:
        """Wall-clock time in nanoseconds since the Unix epoch (ROS system time)."""
        return time.time_ns()

    # executor ------------------------------------------------------------------------------
    def spin_once(self, timeout_s: float = 0.1) -> None:
        """Run whatever callbacks are ready, waiting at most ``timeout_s`` for one."""
        if not self._shutdown.is_set():
            self._transport.spin_once(timeout_s)

    def spin(self) -> None:
        """Run callbacks until ``shutdown()``, SIGINT or SIGTERM."""
        restore = self._install_signal_handlers()
        try:
            while not self._shutdown.is_set():
                self._transport.spin_once(SPIN_SLICE_S)
        finally:
            restore()

    def request_shutdown(self) -> None:
        """Make ``spin()`` return (safe from any thread and from signal handlers)."""
        self._shutdown.set()
        self._transport.wake()

    def shutdown(self) -> None:
        """Stop spinning and release every entity; safe to call twice."""
        self.request_shutdown()
        self._transport.shutdown()

    @property
    def is_shutdown(self) -> bool:
        return self._shutdown.is_set()

    def _install_signal_handlers(self) -> Callable[[], None]:
        if threading.current_thread() is not threading.main_thread():
            return lambda: None
        previous = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}

        def on_signal(signum, frame):
            self._logger.info(f"received {signal.Signals(signum).name}, shutting down")
            self._shutdown.set()

        for sig in previous:
            signal.signal(sig, on_signal)

        def restore() -> None:
            for sig, handler in previous.items():
                signal.signal(sig, handler)

        return restore

    def __enter__(self) -> Node:
        return self

    def __exit__(self, *exc) -> None:
        self.shutdown()


def run_node(
    factory: Callable[[Node], object], argv: Sequence[str] | None = None, name: str | None = None
) -> int:
    """Entry point of a node process: parse ``--ros-args``, build the node, spin, shut down.

    ``argv``: ``[node_name] [--ros-args --params-file F -p k:=v -r __node:=NAME --log-level L]``
    (``sys.argv[1:]`` when None); the node name is the ``__node`` remap, else the first plain
    argument, else ``name``. ``factory(node)`` wires the node (and may keep state).
    """
    argv = list(sys.argv[1:] if argv is None else argv)
    args = parse_ros_args(argv)
    node_name = (
        args.node_name
        or (args.other[0] if args.other else None)
        or name
        or _default_node_name(factory)
    )
    if not node_name:
        raise InputError(
            "node name", None, "'-r __node:=NAME', a first argument or run_node(name=...)"
        )
    node = Node(
        node_name,
        args.parameters(node_name),
        remaps=args.remaps,
        log_level=args.log_level or "INFO",
    )
    # Handle SIGINT/SIGTERM from now on, so one that arrives while the factory wires the node
    # also ends the process cleanly.
    restore = node._install_signal_handlers()
    try:
        factory(node)
        node.spin()
    finally:
        node.shutdown()
        restore()
    return 0


def _default_node_name(factory: Callable) -> str | None:
    explicit = getattr(factory, "NODE_NAME", None)
    if explicit:
        return explicit
    stem = getattr(factory, "__name__", "")
    stem = stem.removesuffix("Node")
    snake = "".join("_" + c.lower() if c.isupper() else c for c in stem).lstrip("_")
    return snake or None
