"""ROS 2 parameter files and ``--ros-args`` command lines."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from area3d_msgs_py.errors import InputError

WILDCARD_SECTION = "/**"


def load_parameter_file(path: str | Path, node_name: str) -> dict[str, Any]:
    """Parameters of ``node_name`` from a ROS 2 parameter YAML file.

    ``/**`` applies to every node, then ``<node_name>`` (or ``/<node_name>``) overrides it; nested
    dictionaries are flattened to dotted names as ROS 2 does (``a: {b: 1}`` -> ``a.b``).
    """
    path = Path(path)
    try:
        document = yaml.safe_load(path.read_text()) or {}
    except FileNotFoundError:
        raise InputError(
            "params_file", str(path), "an existing ROS 2 parameter YAML file"
        ) from None
    if not isinstance(document, dict):
        raise InputError("params_file", str(path), "a mapping 'node_name: {ros__parameters: ...}'")
    result: dict[str, Any] = {}
    for section in (WILDCARD_SECTION, node_name, "/" + node_name):
        body = document.get(section)
        if body is None:
            continue
        if not isinstance(body, dict) or not isinstance(body.get("ros__parameters", {}), dict):
            raise InputError(f"{path.name}:{section}", body, "a mapping with 'ros__parameters'")
        result.update(_flatten(body.get("ros__parameters") or {}))
    return result


def _flatten(values: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    flat: dict[str, Any] = {}
    for key, value in values.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict):
            flat.update(_flatten(value, name + "."))
        else:
            flat[name] = value
    return flat


@dataclass
class RosArgs:
    """What ``--ros-args`` said: node name override, parameter files, parameter overrides, remaps."""

    node_name: str | None = None
    params_files: list[str] = field(default_factory=list)
    overrides: dict[str, Any] = field(default_factory=dict)
    remaps: dict[str, str] = field(default_factory=dict)
    log_level: str | None = None
    other: list[str] = field(default_factory=list)

    def parameters(self, node_name: str) -> dict[str, Any]:
        """Parameters for ``node_name``: files in order, then ``-p`` overrides."""
        params: dict[str, Any] = {}
        for path in self.params_files:
            params.update(load_parameter_file(path, node_name))
        params.update(self.overrides)
        return params


def parse_ros_args(argv: list[str]) -> RosArgs:
    """Parse ``[args] --ros-args --params-file F -p name:=value -r __node:=NAME --log-level L [--]``.

    ``-p`` values are YAML-typed (``-p budget:=25`` is an int, ``-p mode:=batch`` a string).
    """
    args = RosArgs()
    in_ros = False
    it = iter(argv)
    for token in it:
        if token == "--ros-args":
            in_ros = True
            continue
        if token == "--" and in_ros:
            in_ros = False
            continue
        if not in_ros:
            args.other.append(token)
            continue
        if token in ("--params-file", "-p", "--param", "-r", "--remap", "--log-level"):
            value = next(it, None)
            if value is None:
                raise InputError(token, None, "a value after the flag")
            if token == "--params-file":
                args.params_files.append(value)
            elif token in ("-p", "--param"):
                name, sep, text = value.partition(":=")
                if not sep or not name:
                    raise InputError("-p", value, "'name:=value'")
                args.overrides[name] = yaml.safe_load(text) if text else ""
            elif token in ("-r", "--remap"):
                src, sep, dst = value.partition(":=")
                if not sep or not src or not dst:
                    raise InputError("-r", value, "'from:=to'")
                if src in ("__node", "__name"):
                    args.node_name = dst
                else:
                    args.remaps[src] = dst
            else:
                args.log_level = value
        else:
            raise InputError("--ros-args", token, "--params-file, -p, -r or --log-level")
    return args
