"""Message definitions (ros2msg) from the interface packages' .msg files, as rosbag2 writes them."""

from __future__ import annotations

import pytest
from rosbags.typesys import Stores, get_typestore

from area3d_msgs_py.errors import InputError
from area3d_msgs_py.msgdef import SEPARATOR, field_types, message_definition, msg_text

TYPES = (
    "sensor_msgs/msg/Image",
    "sensor_msgs/msg/PointCloud2",
    "nav_msgs/msg/Path",
    "visualization_msgs/msg/MarkerArray",
    "diagnostic_msgs/msg/DiagnosticArray",
    "rcl_interfaces/msg/Log",
)


def _sections(definition: str) -> list[str]:
    return [line for line in definition.splitlines() if line.startswith("MSG: ")]


@pytest.mark.parametrize("type_name", TYPES)
def test_a_definition_lists_every_dependency_once_in_rosbag2s_order(type_name):
    ours = message_definition(type_name)
    theirs, _ = get_typestore(Stores.ROS2_JAZZY).generate_msgdef(type_name, ros_version=2)
    assert _sections(ours) == _sections(theirs)
    assert len(set(_sections(ours))) == len(_sections(ours))
    # each section is the dependency's own .msg text after a separator line
    for section in ours.split(SEPARATOR + "\n")[1:]:
        header, _, text = section.partition("\n")
        assert text.rstrip("\n") == msg_text(header.removeprefix("MSG: ")).rstrip("\n")


def test_the_definition_starts_with_the_types_own_text():
    definition = message_definition("sensor_msgs/msg/PointCloud2")
    assert definition.startswith(
        msg_text("sensor_msgs/PointCloud2").rstrip("\n") + "\n" + SEPARATOR
    )
    assert "MSG: sensor_msgs/PointField" in definition and "PointField[] fields" in definition


def test_field_types_reduce_arrays_and_bounds_and_skip_builtins_and_constants():
    text = """# a comment
int32 FOO=3
string<=8 name
uint8[] data
Point[4] corners
geometry_msgs/Pose[<=2] poses
std_msgs/Header header
float64 x 1.5   # default value
"""
    assert field_types(text, "geometry_msgs") == [
        "geometry_msgs/Point",
        "geometry_msgs/Pose",
        "std_msgs/Header",
    ]


@pytest.mark.parametrize("type_name", ["sensor_msgs/msg/NoSuchMessage", "not a type"])
def test_an_unknown_type_is_refused_naming_it(type_name):
    with pytest.raises(InputError) as err:
        message_definition(type_name)
    assert err.value.field == "type_name" and type_name in str(err.value)
