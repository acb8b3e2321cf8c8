"""ROS 2 message definitions as rosbag2 and Foxglove carry them (schema encoding `ros2msg`).

A definition is the type's `.msg` text followed by the text of every message type it uses, each
after a line of 80 `=` and a `MSG: pkg/Name` line, depth first, each type once: what `ros2 bag`
writes into an MCAP file and what Foxglove's `@foxglove/rosmsg` parses. The `.msg` files come from
the interface packages' `share/<pkg>/msg/` folders: the ROS wheels install them under the Python
environment's prefix, a sourced ROS 2 under each prefix of `AMENT_PREFIX_PATH`.

    >>> "MSG: std_msgs/Header" in message_definition("sensor_msgs/msg/Image")
    True
"""

from __future__ import annotations

import os
import re
import sys
from functools import lru_cache
from pathlib import Path

from area3d_msgs_py.errors import InputError

SEPARATOR = "=" * 80
# the built-in field types of the ROS 2 interface definition language
PRIMITIVES = frozenset(
    {
        "bool", "byte", "char", "float32", "float64", "int8", "uint8", "int16", "uint16",
        "int32", "uint32", "int64", "uint64", "string", "wstring",
    }
)  # fmt: skip
_ARRAY = re.compile(r"\[[^\]]*\]$")  # name[], name[3], name[<=3]
_BOUND = re.compile(r"<=\d+$")  # string<=10


def share_dirs() -> list[Path]:
    """Where interface packages keep their `share/<pkg>/msg` files, searched in this order: each
    prefix of AMENT_PREFIX_PATH (a sourced ROS 2 or a colcon workspace), then this Python
    environment's prefix (the ROS wheels)."""
    prefixes = [p for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]
    prefixes += [sys.prefix, sys.base_prefix]
    out: list[Path] = []
    for prefix in prefixes:
        share = Path(prefix) / "share"
        if share.is_dir() and share not in out:
            out.append(share)
    return out


def split_type_name(type_name: str) -> tuple[str, str]:
    """("sensor_msgs", "Image") from "sensor_msgs/msg/Image" or "sensor_msgs/Image"."""
    parts = type_name.split("/")
    if len(parts) == 3 and parts[1] == "msg" and all(parts):
        return parts[0], parts[2]
    if len(parts) == 2 and all(parts):
        return parts[0], parts[1]
    raise InputError("type_name", type_name, "a message type such as 'sensor_msgs/msg/Image'")


@lru_cache(maxsize=512)
def msg_text(type_name: str) -> str:
    """The `.msg` text of one message type, as its package installed it."""
    package, name = split_type_name(type_name)
    searched = share_dirs()
    for share in searched:
        path = share / package / "msg" / f"{name}.msg"
        if path.is_file():
            return path.read_text()
    raise InputError(
        "type_name",
        type_name,
        f"a message whose {package}/msg/{name}.msg is installed under one of "
        f"{[str(s) for s in searched]} (install or source the package that defines it)",
    )


def field_types(text: str, package: str) -> list[str]:
    """The message types (`pkg/Name`) that the fields of a `.msg` text use, in order: arrays and
    bounded strings reduced to their element type, built-in types and constants left out, a type
    without a package taken from `package`."""
    out: list[str] = []
    for line in text.splitlines():
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        field_type = line.split()[0]
        field_type = _BOUND.sub("", _ARRAY.sub("", field_type))
        if field_type in PRIMITIVES:
            continue
        if "/" not in field_type:
            field_type = f"{package}/{field_type}"
        pkg, name = split_type_name(field_type)
        out.append(f"{pkg}/{name}")
    return out


@lru_cache(maxsize=256)
def message_definition(type_name: str) -> str:
    """The full `ros2msg` definition of a message type: its own text, then every type it depends
    on (depth first, each once) after a separator and a `MSG: pkg/Name` line."""
    package, name = split_type_name(type_name)
    root = f"{package}/{name}"
    parts = [msg_text(root).rstrip("\n")]
    seen = {root}
    stack = list(reversed(field_types(parts[0], package)))
    while stack:
        dependency = stack.pop()
        if dependency in seen:
            continue
        seen.add(dependency)
        text = msg_text(dependency).rstrip("\n")
        parts.append(f"{SEPARATOR}\nMSG: {dependency}\n{text}")
        stack.extend(reversed(field_types(text, dependency.split("/")[0])))
    return "\n".join(parts) + "\n"
