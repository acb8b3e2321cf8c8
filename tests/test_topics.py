"""The topic table (`area3d_msgs_py/topics.py`) is what the README documents and what the
mission manager and the camera wait for."""

from __future__ import annotations

import re
from pathlib import Path

from area3d_msgs_py import topics

README = Path(__file__).resolve().parents[1] / "README.md"


def _readme_names() -> set[str]:
    """Every topic and service name in the README's table of the graph ("| `/area3d/...` |")."""
    names = set()
    for line in README.read_text().splitlines():
        cell = line.split("|")[1] if line.startswith("| `/") else ""
        names |= set(re.findall(r"`(/[a-z0-9_/]+)`", cell))
    return names


def test_the_readme_documents_exactly_the_topics_of_the_table():
    table = {t.name if t.name.startswith("/") else f"/{t.name}" for t in topics.TOPICS}
    assert _readme_names() == table | {f"/{service.name}" for service in topics.SERVICES}


def test_the_graph_nodes_read_what_the_mission_manager_waits_for():
    from area3d_bringup.mission_manager import EXPECTED_READERS, READS

    assert READS == {
        "sim_bridge": ("goal",),
        "perception": ("color", "depth", "info", "pose"),
        "semantics": ("color", "depth"),
        "planner": ("info", "pose"),
    }
    # the graph's readers and the mission manager's own reader of each camera topic
    assert EXPECTED_READERS == {"goal": 1, "color": 3, "depth": 3, "info": 3, "pose": 3}


def test_every_topic_has_a_writer_a_type_and_a_qos():
    for topic in topics.TOPICS:
        assert topic.writer and topic.qos().depth >= 1, topic.name
        assert topic.msg_type is not None and topic.type_name, topic.name
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
        ("area3d/semantics/reset", "semantics"),
    ]  # fmt: skip
