"""Declared, typed and described ROS 2 parameters for the graph's nodes.

    PARAMS = (
        Param("budget", 25, "total views, O_0 included (paper: 25 object, 40 room)", range=(1, 1000)),
        Param("policy", "area3d", "next-best-view policy", choices=("area3d", "random")),
        Param("sync_timeout_s", 5.0, "wait for a request's frame", read_only=False, range=(0, 600)),
    )
    values = declare_parameters(node, PARAMS)

Each becomes ``node.declare_parameter(name, default, ParameterDescriptor(...))`` with its type,
description, range and read-only flag; rclpy enforces type, range and read-only on every set, and
the callback installed here refuses values outside ``choices`` or failing ``check`` with a reason.
Keys in the parameter file or ``-p`` that no declaration uses are reported by name.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any

from rcl_interfaces.msg import (
    FloatingPointRange,
    IntegerRange,
    ParameterDescriptor,
    SetParametersResult,
)
from rclpy.node import Node
from rclpy.parameter import Parameter

from area3d_msgs_py.errors import InputError
from area3d_msgs_py.inputs import MAX_STAMP_AHEAD_S
from area3d_msgs_py.param_fields import description_of, is_described
from area3d_msgs_py.qos import CAMERA_QOS_CHOICES

#: declared by rclpy itself on every node
BUILTIN_PARAMETERS = frozenset({"use_sim_time", "start_type_description_service"})


@dataclass(frozen=True)
class Param:
    """One parameter: ``range`` is inclusive (numbers), ``choices`` the allowed strings, ``check``
    returns an error text for a bad value (or None)."""

    name: str
    default: Any
    description: str
    read_only: bool = True
    range: tuple[float, float] | None = None
    choices: tuple[str, ...] | None = None
    check: Callable[[Any], str | None] | None = None  # value -> expectation when refused

    def descriptor(self) -> ParameterDescriptor:
        text = self.description
        if self.choices:
            text += f" (one of: {', '.join(self.choices)})"
        descriptor = ParameterDescriptor(
            name=self.name,
            type=Parameter.Type.from_parameter_value(self.default).value,
            description=text,
            read_only=self.read_only,
        )
        if self.range is not None:
            lo, hi = self.range
            if isinstance(self.default, float):
                descriptor.floating_point_range = [
                    FloatingPointRange(from_value=float(lo), to_value=float(hi), step=0.0)
                ]
            elif isinstance(self.default, int) and not isinstance(self.default, bool):
                descriptor.integer_range = [
                    IntegerRange(from_value=int(lo), to_value=int(hi), step=0)
                ]
        return descriptor

    def problem(self, value: Any) -> str | None:
        """What was expected when ``value`` is refused (beyond rclpy's type and range checks)."""
        if self.choices is not None and value not in self.choices:
            return f"one of {', '.join(self.choices)}"
        if self.check is not None:
            return self.check(value)
        return None


def params_of(
    config: type, prefix: str = "", skip: Iterable[str] = (), read_only: bool = True
) -> tuple[Param, ...]:
    """The parameters of a dataclass whose fields are made with `param_fields.described`: one
    per field (named `prefix` + field name, less those in `skip`), with the field's default,
    description and unit, range, choices and check."""
    params = []
    for f in dataclasses.fields(config):
        if f.name in skip:
            continue
        if not is_described(f):
            raise TypeError(f"{config.__name__}.{f.name}: a parameter needs a described() field")
        default = f.default if f.default is not dataclasses.MISSING else f.default_factory()
        if isinstance(default, tuple) and _all_numbers(default):
            default = tuple(float(v) for v in default)
        meta = f.metadata
        params.append(
            Param(
                prefix + f.name,
                default,
                description_of(f),
                read_only=read_only,
                range=meta.get("range"),
                choices=meta.get("choices"),
                check=meta.get("check"),
            )
        )
    return tuple(params)


# Parameters every node that checks its inputs declares alike (`area3d_msgs_py.inputs`).
MAX_STAMP_AHEAD_PARAM = Param(
    "max_stamp_ahead_s",
    MAX_STAMP_AHEAD_S,
    "inputs stamped further ahead of this node's clock are refused, seconds",
    range=(0.0, 86400.0),
)
WORLD_FRAME_PARAM = Param(
    "world_frame",
    "world",
    "the fixed frame: every camera pose in and every output out is expressed in it (REP 105: "
    "map or odom on a robot)",
)
CAMERA_QOS_PARAM = Param(
    "camera_qos",
    "reliable",
    "QoS of the camera's topics and the odometry: reliable (our camera, a bag) or sensor_data "
    "(best effort: a driver that publishes with the sensor-data profile)",
    choices=CAMERA_QOS_CHOICES,
)
# Pairing of a frame's parts (`area3d_msgs_py.frame_sync.StampSync`).
SYNC_SLOP_PARAM = Param(
    "sync_slop_s",
    0.0,
    "parts of one frame pair when their stamps lie within this of the reference part's (colour "
    "in perception, depth in the planner); 0 = identical stamps only (our camera stamps every "
    "part of a frame alike; a driver that stamps colour and depth apart: 0.01-0.02), seconds",
    range=(0.0, 1.0),
)
CAMERA_RATE_PARAM = Param(
    "camera_rate_hz",
    0.0,
    "the rate the camera's driver streams at: frames missing from the stream (`frames_missed`) "
    "are counted against its period; 0 = the period learnt from the gaps between the stamps "
    "that arrive (right while most frames arrive; a stream that loses most of them reads as a "
    "slower one), Hz",
    range=(0.0, 1000.0),
)
MIN_PAIRING_RATE_PARAM = Param(
    "min_pairing_rate",
    0.8,
    "below this share of frames paired (of the last 100) /diagnostics warns: parts are lost "
    "on the way (best effort) or stamped too far apart (sync_slop_s), a fraction 0-1",
    range=(0.0, 1.0),
)


def declare_parameters(node: Node, params: Iterable[Param]) -> dict[str, Any]:
    """Declare ``params`` on ``node``; returns {name: value at start}.

    A value from the parameter file that is refused raises ``InputError`` naming the parameter,
    the value and what was expected. Ints given for float parameters are widened, as ROS 2 YAML
    users expect (``max_range: 5``).
    """
    params = list(params)
    registry: dict[str, Param] = getattr(node, "_area3d_params", None) or {}
    if not registry:
        node._area3d_params = registry
        node.add_on_set_parameters_callback(lambda changes: _on_set(registry, changes))
    overrides = getattr(node, "_parameter_overrides", {})
    values: dict[str, Any] = {}
    for p in params:
        override = overrides.get(p.name)
        if (
            override is not None
            and isinstance(p.default, float)
            and override.type_ == Parameter.Type.INTEGER
        ):
            overrides[p.name] = Parameter(p.name, Parameter.Type.DOUBLE, float(override.value))
        if override is not None and (
            isinstance(p.default, list | tuple)
            and override.type_ != Parameter.Type.from_parameter_value(p.default)
        ):
            widened = [float(v) for v in override.value] if _all_numbers(override.value) else None
            if widened is not None and isinstance(p.default[0], float):
                overrides[p.name] = Parameter(p.name, Parameter.Type.DOUBLE_ARRAY, widened)
        default = list(p.default) if isinstance(p.default, tuple) else p.default
        try:
            value = node.declare_parameter(p.name, default, p.descriptor()).value
        except Exception as exc:  # rclpy's type / range exceptions
            given = overrides[p.name].value if p.name in overrides else default
            described = p.descriptor().description
            expected = f"{described} ({exc})"
            if _out_of_range(p, given):  # the range, not rclpy's text about it
                expected = f"a value in [{p.range[0]}, {p.range[1]}]: {described}"
            raise InputError(p.name, given, expected) from None
        problem = p.problem(value)
        if problem:
            raise InputError(p.name, value, problem)
        registry[p.name] = p
        values[p.name] = tuple(value) if isinstance(p.default, tuple) else value
    return values


def parameter_values(params: Iterable[Param], given: dict[str, Any]) -> dict[str, Any]:
    """{name: value} as `declare_parameters` gives them to a node started with the parameters
    `given` (defaults for the rest), without a node: what a node's cores are built from, also
    where no node runs (`area3d_bringup.inprocess`). Keys of `given` that no parameter declares
    are ignored; a refused value raises InputError as on a node."""
    values: dict[str, Any] = {}
    for p in params:
        value = given.get(p.name, p.default)
        if isinstance(p.default, float) and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        if isinstance(p.default, list | tuple):
            if p.default and isinstance(p.default[0], float) and _all_numbers(value):
                value = [float(v) for v in value]
            value = tuple(value) if isinstance(p.default, tuple) else list(value)
        if type(value) is not type(p.default) and not (
            isinstance(p.default, list | tuple) and isinstance(value, list | tuple)
        ):
            raise InputError(p.name, value, f"a {type(p.default).__name__}: {p.description}")
        if _out_of_range(p, value):
            lo, hi = p.range
            raise InputError(p.name, value, f"a value in [{lo}, {hi}]: {p.description}")
        problem = p.problem(value)
        if problem:
            raise InputError(p.name, value, problem)
        values[p.name] = value
    return values


def _out_of_range(p: Param, value: Any) -> bool:
    """A number outside the parameter's declared range."""
    if p.range is None or isinstance(value, bool) or not isinstance(value, int | float):
        return False
    return not p.range[0] <= value <= p.range[1]


def _all_numbers(values: Any) -> bool:
    try:
        return all(isinstance(v, int | float) and not isinstance(v, bool) for v in values)
    except TypeError:
        return False


def _on_set(registry: dict[str, Param], changes: list[Parameter]) -> SetParametersResult:
    for change in changes:
        spec = registry.get(change.name)
        if spec is None:
            continue
        problem = spec.problem(change.value)
        if problem:
            reason = str(InputError(change.name, change.value, problem))
            return SetParametersResult(successful=False, reason=reason)
    return SetParametersResult(successful=True)


def unknown_parameters(node: Node) -> list[str]:
    """Names given in the parameter file or ``-p`` for this node that it did not declare."""
    overrides = getattr(node, "_parameter_overrides", {})
    declared = set(node._parameters) | BUILTIN_PARAMETERS
    return sorted(name for name in overrides if name not in declared)


def report_unknown_parameters(node: Node) -> list[str]:
    """Log a warning naming each unknown parameter (a typo in a YAML file is not silent)."""
    unknown = unknown_parameters(node)
    if unknown:
        known = sorted(set(node._parameters) - BUILTIN_PARAMETERS)
        node.get_logger().warning(
            f"unknown parameters for node {node.get_name()!r} ignored: {', '.join(unknown)} "
            f"(declared: {', '.join(known)})"
        )
    return unknown
