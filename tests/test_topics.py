"""The topic table (`area3d_msgs_py/topics.py`) is what the README documents and what the
mission manager and the camera wait for."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from rclpy.qos import DurabilityPolicy, HistoryPolicy, ReliabilityPolicy

from area3d_msgs_py import topics

README = Path(__file__).resolve().parents[1] / "README.md"

#: who may write a topic (the registry's writers)
WRITERS = (
    topics.SIM_BRIDGE, topics.PERCEPTION, topics.SEMANTICS, topics.PLANNER, topics.RECONSTRUCTION,
    topics.MISSION_MANAGER, topics.FOXGLOVE_BRIDGE, topics.ROBOT, topics.ANYONE,
)  # fmt: skip
#: who the registry lists as a topic's readers, or as a service's server
NODES = (
    topics.SIM_BRIDGE, topics.PERCEPTION, topics.SEMANTICS, topics.PLANNER, topics.RECONSTRUCTION,
    topics.MISSION_MANAGER, topics.FOXGLOVE_BRIDGE,
)  # fmt: skip


def _words(text: str, names: tuple[str, ...]) -> set[str]:
    """The names of `names` that `text` contains as whole words (`perception`, not
    `area3d_perception`)."""
    return {name for name in names if re.search(rf"(?<![\w/]){re.escape(name)}(?![\w/])", text)}


def _readme_table() -> dict[str, dict[str, str]]:
    """The README's table of the graph, one row per name: {"/area3d/...": {"type", "what",
    "writer", "readers"}} from its rows "| `NAME` | `TYPE` | what | WRITER -> READERS |"."""
    rows: dict[str, dict[str, str]] = {}
    for line in README.read_text().splitlines():
        if not line.startswith("| `/"):
            continue
        cells = [cell.strip() for cell in line.strip().strip("|").split("|")]
        assert len(cells) == 4, f"a row of the graph's table has 4 cells: {line}"
        name, type_cell, what, flow = cells
        assert re.fullmatch(r"`/[a-z0-9_/]+`", name), f"one name per row: {name!r}"
        assert re.fullmatch(r"`\w+/(msg|srv)/\w+`", type_cell), f"{name}: type {type_cell!r}"
        assert flow.count(" -> ") == 1, f"{name}: 'writer -> readers', got {flow!r}"
        assert name.strip("`") not in rows, f"{name} has two rows"
        writer, readers = flow.split(" -> ")
        rows[name.strip("`")] = {
            "type": type_cell.strip("`"), "what": what, "writer": writer, "readers": readers,
        }  # fmt: skip
    return rows


def _absolute(name: str) -> str:
    return name if name.startswith("/") else f"/{name}"


def _srv_type_name(service: topics.Service) -> str:
    package, kind = service.srv_type.__module__.split(".")[:2]
    return f"{package}/{kind}/{service.srv_type.__name__}"


def test_the_readme_table_names_exactly_the_registrys_topics_and_services():
    """A topic or service renamed, added or removed in the code or in the README fails here."""
    documented = set(_readme_table())
    registry = {_absolute(t.name) for t in topics.TOPICS} | {
        _absolute(s.name) for s in topics.SERVICES
    }
    assert documented - registry == set(), "in the README, not in area3d_msgs_py/topics.py"
    assert registry - documented == set(), "in area3d_msgs_py/topics.py, not in the README"


@pytest.mark.parametrize("topic", topics.TOPICS, ids=lambda t: t.name)
def test_the_readme_row_of_a_topic_gives_its_type_writer_and_readers(topic):
    row = _readme_table()[_absolute(topic.name)]
    assert row["type"] == topic.type_name
    assert _words(row["writer"], WRITERS) == {topic.writer}, row["writer"]
    assert _words(row["readers"], NODES) == set(topic.readers), row["readers"]
    # "latched" in the README is transient local in the code, and a latest-only transient-local
    # topic is called latched
    if "latched" in row["what"]:
        assert topic.durability == topics.TRANSIENT_LOCAL, topic.name
    if topic.durability == topics.TRANSIENT_LOCAL and topic.depth == 1:
        assert "latched" in row["what"], topic.name


@pytest.mark.parametrize("service", topics.SERVICES, ids=lambda s: s.name)
def test_the_readme_row_of_a_service_gives_its_type_and_server(service):
    row = _readme_table()[_absolute(service.name)]
    assert row["type"] == _srv_type_name(service)
    assert _words(row["readers"], NODES) == {service.server}, row["readers"]


def test_the_graph_nodes_read_what_the_mission_manager_waits_for():
    from area3d_bringup.mission_sync import EXPECTED_READERS, READS

    assert READS == {
        "sim_bridge": ("goal",),
        "perception": ("color", "depth", "info", "pose"),
        "semantics": ("color", "depth"),
        "planner": ("info", "pose"),
        "reconstruction": ("info", "pose"),
    }
    # the graph's readers and the mission manager's own reader of each camera topic
    assert EXPECTED_READERS == {"goal": 1, "color": 3, "depth": 3, "info": 4, "pose": 4}


def test_every_topic_has_a_known_writer_a_ros_type_and_a_reliable_keep_last_qos():
    for topic in topics.TOPICS:
        assert topic.writer in WRITERS, topic.name
        assert set(topic.readers) <= set(NODES), topic.name
        assert re.fullmatch(r"\w+/msg/\w+", topic.type_name), topic.name
        profile = topic.qos()
        assert profile.reliability == ReliabilityPolicy.RELIABLE, topic.name
        assert profile.history == HistoryPolicy.KEEP_LAST and profile.depth >= 1, topic.name
        durability = {
            topics.VOLATILE: DurabilityPolicy.VOLATILE,
            topics.TRANSIENT_LOCAL: DurabilityPolicy.TRANSIENT_LOCAL,
        }[topic.durability]
        assert profile.durability == durability, topic.name
        # a driver's input is read as the node's camera_qos says; every other topic with its own
        best_effort = topic.reader_qos("sensor_data")
        if topic.camera:
            assert best_effort.reliability == ReliabilityPolicy.BEST_EFFORT, topic.name
            assert topic.reader_qos("reliable").reliability == ReliabilityPolicy.RELIABLE
        else:
            assert best_effort == profile, topic.name


def test_the_planner_reads_these_topics_and_drivers_provide_these():
    assert [t.name for t in topics.read_by("planner")] == [
        "area3d/camera/camera_info", "area3d/camera/pose", "/tf", "/tf_static", "area3d/odom",
        "area3d/perception/depth", "area3d/perception/confidence", "area3d/semantics/uncertainty",
    ]  # fmt: skip
    # what a robot's drivers publish is read with the node's camera_qos
    assert {t.name for t in topics.TOPICS if t.camera} == {
        "area3d/camera/color/image_raw", "area3d/camera/depth/image_raw",
        "area3d/camera/camera_info", "area3d/camera/pose", "area3d/camera/right/image_rect",
        "area3d/camera/right/camera_info", "area3d/odom",
    }  # fmt: skip
    assert [(s.name, s.server) for s in topics.SERVICES] == [
        ("area3d/planner/select_views", "planner"), ("area3d/planner/next_best_view", "planner"),
        ("area3d/camera/reset", "sim_bridge"), ("area3d/planner/reset", "planner"),
        ("area3d/planner/save_map", "planner"), ("area3d/planner/load_map", "planner"),
        ("area3d/semantics/reset", "semantics"),
        ("area3d/reconstruction/save_map", "reconstruction"),
        ("area3d/reconstruction/load_map", "reconstruction"),
        ("area3d/reconstruction/export_mesh", "reconstruction"),
        ("area3d/reconstruction/reset", "reconstruction"),
    ]  # fmt: skip
