"""Declared parameters: the values a node starts with, with and without a node."""

import re

import pytest
import rclpy
from rclpy.node import Node
from rclpy.parameter import Parameter

from area3d_msgs_py.errors import InputError
from area3d_msgs_py.parameters import Param, declare_parameters, parameter_values

PARAMS = (
    Param("policy", "area3d", "next-best-view policy", choices=("area3d", "random")),
    Param("eta", 0.3, "frustum decay, 1", range=(0.0, 1.0)),
    Param("budget", 25, "total views", range=(1, 1000)),
    Param("roi_min", (-0.3, -0.3, 0.0), "region corner, metres"),
    Param("readers", ("perception",), "node names"),
    Param("noise", True, "add noise"),
)
PARAMS_BY_NAME = {p.name: p for p in PARAMS}


def test_without_a_node_the_values_are_those_a_node_declares():
    given = {"eta": 1, "roi_min": [0, 0, 1], "readers": ["a", "b"], "policy": "random"}
    context = rclpy.Context()
    rclpy.init(context=context)
    try:
        overrides = [Parameter(k, value=v) for k, v in given.items()]
        node = Node("values", context=context, parameter_overrides=overrides)
        declared = declare_parameters(node, PARAMS)
        node.destroy_node()
    finally:
        context.try_shutdown()
    values = parameter_values(PARAMS, given)
    assert values == declared
    assert values["eta"] == 1.0 and isinstance(values["eta"], float)  # an int widened
    assert values["roi_min"] == (0.0, 0.0, 1.0) and values["budget"] == 25  # default kept


@pytest.mark.parametrize(
    ("given", "field"),
    [
        ({"policy": "best"}, "policy"),
        ({"eta": 1.5}, "eta"),
        ({"budget": 0}, "budget"),
        ({"noise": "yes"}, "noise"),
    ],
)
def test_a_refused_value_names_the_parameter(given, field):
    with pytest.raises(InputError, match=field):
        parameter_values(PARAMS, given)


@pytest.mark.parametrize(("name", "value"), [("eta", 1.5), ("budget", 0)])
def test_a_value_out_of_range_names_the_range_on_a_node_as_without_one(name, value):
    expected = f"{name}: got {value}, expected a value in [{PARAMS_BY_NAME[name].range[0]}, "
    with pytest.raises(InputError, match=re.escape(expected)):
        parameter_values(PARAMS, {name: value})
    context = rclpy.Context()
    rclpy.init(context=context)
    try:
        node = Node("ranged", context=context, parameter_overrides=[Parameter(name, value=value)])
        with pytest.raises(InputError, match=re.escape(expected)):
            declare_parameters(node, PARAMS)
        node.destroy_node()
    finally:
        context.try_shutdown()
