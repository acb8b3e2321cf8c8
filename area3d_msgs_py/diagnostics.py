"""A node's status as `diagnostic_msgs/DiagnosticArray` on /diagnostics, for the standard ROS 2
tools (rqt_robot_monitor, the diagnostic aggregator, Foxglove's diagnostics panels).

Every fact of the status becomes a key/value (nested keys joined with "."), and the level
follows these rules, checked in this order (README: "Diagnostics"):

- ERROR: the node's backend failed (`backend_error` is set, or a count ending in `_failures`
  rose since the previous period), or one of its worker threads died (a `workers.<name>` fact
  is false).
- WARN: frames were dropped (a count whose key contains `dropped` rose) or inputs were rejected
  (`rejected.total` rose) since the previous period, or the node states a standing warning (each
  line of its `warnings` list: the pairing rate below its threshold, say).
- OK: otherwise.

"Since the previous period" compares with the status of the last heartbeat (once a second), so
a drop turns the status WARN at once and keeps it there until the heartbeat after next (1-2 s),
long enough for a monitor that samples once a second to see it; then it returns to OK.
"""

from __future__ import annotations

import json
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from typing import Any

from area3d_msgs_py import codecs
from area3d_msgs_py.msgs import DiagnosticArray, DiagnosticStatus, KeyValue

DIAGNOSTICS_TOPIC = "/diagnostics"  # absolute: one topic for every node, as ROS 2 tools expect
OK, WARN, ERROR = (int.from_bytes(level, "little") for level in (
    DiagnosticStatus.OK, DiagnosticStatus.WARN, DiagnosticStatus.ERROR
))  # fmt: skip
LEVEL_NAMES = {OK: "OK", WARN: "WARN", ERROR: "ERROR"}


def flatten(status: Mapping[str, Any], prefix: str = "") -> Iterator[tuple[str, Any]]:
    """(dotted key, value) for every fact of a status dict, nested dicts walked depth first."""
    for key, value in status.items():
        name = f"{prefix}{key}"
        if isinstance(value, Mapping) and value:
            yield from flatten(value, f"{name}.")
        else:
            yield name, value


def value_text(value: Any) -> str:
    """A fact as KeyValue text: numbers and strings as they are, None as "", the rest as JSON."""
    if value is None:
        return ""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int | float | str):
        return str(value)
    return json.dumps(value, sort_keys=True)


def _rose(key: str, value: Any, before: Mapping[str, Any]) -> int:
    if isinstance(value, bool) or not isinstance(value, int | float):
        return 0
    previous = before.get(key, 0)
    return int(value - previous) if isinstance(previous, int | float) and value > previous else 0


@dataclass(frozen=True)
class Assessment:
    level: int
    message: str


def assess(status: Mapping[str, Any], baseline: Mapping[str, Any] | None = None) -> Assessment:
    """The level and one-line message of a status, by the rules in this module's docstring.
    `baseline` is the status the counts are compared with (None: the first status, all counts
    compared with zero)."""
    facts = dict(flatten(status))
    before = dict(flatten(baseline or {}))
    errors: list[str] = []
    if facts.get("backend_error"):
        errors.append(f"backend failed: {facts['backend_error']}")
    errors += [
        f"{key} +{n}"
        for key, v in facts.items()
        if key.endswith("_failures") and (n := _rose(key, v, before))
    ]
    errors += [
        f"worker {key.removeprefix('workers.')} died"
        for key, v in facts.items()
        if key.startswith("workers.") and v is False
    ]
    if errors:
        return Assessment(ERROR, "; ".join(errors))
    dropped = {
        key: n for key, v in facts.items() if "dropped" in key and (n := _rose(key, v, before))
    }
    rejected = _rose("rejected.total", facts.get("rejected.total", 0), before)
    warnings = [f"{n} dropped ({key})" for key, n in dropped.items()]
    if rejected:
        fields = {
            key.removeprefix("rejected.by_field."): n
            for key, v in facts.items()
            if key.startswith("rejected.by_field.") and (n := _rose(key, v, before))
        }
        named = sorted(fields.items(), key=lambda kv: -kv[1])[:3]
        which = f" ({', '.join(f'{k} {n}' for k, n in named)})" if named else ""
        warnings.append(f"{rejected} inputs rejected{which}")
    standing = [str(w) for w in status.get("warnings") or ()]
    mismatched = (status.get("rejected") or {}).get("incompatible_qos") or {}
    standing += [
        f"nothing arrives on {t}: its publisher's QoS ({p})" for t, p in mismatched.items()
    ]
    if warnings or standing:
        recent = [", ".join(warnings) + " in the last period"] if warnings else []
        return Assessment(WARN, "; ".join(recent + standing))
    return Assessment(OK, "OK")


def diagnostic_status(
    name: str,
    status: Mapping[str, Any],
    baseline: Mapping[str, Any] | None = None,
    hardware_id: str = "",
) -> DiagnosticStatus:
    """One DiagnosticStatus: the level and message of `assess`, every fact as a KeyValue."""
    assessment = assess(status, baseline)
    return DiagnosticStatus(
        level=assessment.level.to_bytes(1, "little"),
        name=name,
        message=assessment.message,
        hardware_id=hardware_id,
        values=[KeyValue(key=k, value=value_text(v)) for k, v in flatten(status)],
    )


def diagnostic_array(stamp_ns: int, statuses: list[DiagnosticStatus]) -> DiagnosticArray:
    return DiagnosticArray(header=codecs.header(stamp_ns, ""), status=statuses)


def status_name(fully_qualified_node_name: str) -> str:
    """The diagnostic name of a node's status, ROS style: "planner: status", or
    "robot1/planner: status" under a namespace (so two graphs stay apart on /diagnostics)."""
    return f"{fully_qualified_node_name.lstrip('/')}: status"
