"""A node as another ROS 2 process sees it: parameters through the parameter services, names under
a namespace and remaps, a quiet exit on SIGINT."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import yaml
from rcl_interfaces.msg import Parameter as ParameterMsg
from rcl_interfaces.msg import ParameterType, ParameterValue
from rcl_interfaces.srv import DescribeParameters, GetParameters, ListParameters, SetParameters

from area3d_msgs_py.probe import Probe

REPO_ROOT = Path(__file__).resolve().parents[1]
TIMEOUT_S = 120.0  # generous: a loaded machine is slow (every wait ends once its condition holds)


def _string(name: str, value: str) -> ParameterMsg:
    return ParameterMsg(
        name=name, value=ParameterValue(type=ParameterType.PARAMETER_STRING, string_value=value)
    )


def _int(name: str, value: int) -> ParameterMsg:
    return ParameterMsg(
        name=name, value=ParameterValue(type=ParameterType.PARAMETER_INTEGER, integer_value=value)
    )


def test_parameters_are_listed_read_and_set_from_another_process_under_a_namespace(tmp_path):
    params = tmp_path / "params.yaml"
    params.write_text(
        yaml.safe_dump(
            {
                "/**/semantics": {
                    "ros__parameters": {"fallback": "zeros", "num_initial_views": 3, "fallbak": "x"}
                }
            }
        )
    )
    node = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "area3d_semantics.node",
            "--ros-args",
            "--params-file",
            str(params),
            "-r",
            "__ns:=/robot1",
            "-r",
            "area3d/semantics/regions:=/elsewhere/regions",
        ],
        env=dict(os.environ, PYTHONPATH=str(REPO_ROOT)),
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    try:
        with Probe("parameter_client") as probe:
            base = "/robot1/semantics"
            listed = probe.call(
                ListParameters, f"{base}/list_parameters", ListParameters.Request(), TIMEOUT_S
            )
            names = set(listed.result.names)
            assert {"backend", "fallback", "requery_scope", "num_initial_views", "lambda"} <= names
            assert "fallbak" not in names

            got = probe.call(
                GetParameters,
                f"{base}/get_parameters",
                GetParameters.Request(names=["fallback", "num_initial_views"]),
                TIMEOUT_S,
            )
            assert got.values[0].string_value == "zeros" and got.values[1].integer_value == 3

            described = probe.call(
                DescribeParameters,
                f"{base}/describe_parameters",
                DescribeParameters.Request(names=["num_initial_views", "requery_scope"]),
                TIMEOUT_S,
            )
            views, scope = described.descriptors
            assert views.read_only and views.description and views.integer_range
            assert not scope.read_only and "one of: all, latest" in scope.description

            request = SetParameters.Request(
                parameters=[
                    _string("requery_scope", "latest"),
                    _string("fallback", "bogus"),
                    _int("num_initial_views", 5),
                ]
            )
            results = probe.call(
                SetParameters, f"{base}/set_parameters", request, TIMEOUT_S
            ).results
            assert results[0].successful
            assert not results[1].successful and "fallback: got 'bogus'" in results[1].reason
            assert not results[2].successful and "read-only" in results[2].reason
            got = probe.call(
                GetParameters,
                f"{base}/get_parameters",
                GetParameters.Request(names=["requery_scope", "fallback", "num_initial_views"]),
                TIMEOUT_S,
            )
            assert [got.values[0].string_value, got.values[1].string_value] == ["latest", "zeros"]
            assert got.values[2].integer_value == 3

            # names: everything under the namespace, the remapped topic where it was sent
            def topics():
                return {name for name, _ in probe.node.get_topic_names_and_types()}

            assert probe.wait_for(lambda: "/elsewhere/regions" in topics(), TIMEOUT_S)
            assert probe.wait_for(lambda: "/robot1/area3d/semantics/weight" in topics(), TIMEOUT_S)
            assert ("semantics", "/robot1") in probe.node.get_node_names_and_namespaces()
            # this node's own topics (the domain may still list nodes of earlier tests a while)
            graph = probe.node
            own = {
                name
                for by_node in (
                    graph.get_publisher_names_and_types_by_node,
                    graph.get_subscriber_names_and_types_by_node,
                )
                for name, _ in by_node("semantics", "/robot1")
            }
            assert {"/elsewhere/regions", "/robot1/area3d/camera/color/image_raw"} <= own
            assert not any(t.startswith("/area3d/") for t in own), own
    finally:
        node.send_signal(signal.SIGINT)
        try:
            output, _ = node.communicate(timeout=60)  # ends at the exit (test_shutdown times it)
        except subprocess.TimeoutExpired:
            node.kill()
            output, _ = node.communicate()
    assert node.returncode == 0, output  # quiet and prompt on SIGINT
    assert "Traceback" not in output
    assert "unknown parameters for node 'semantics' ignored: fallbak" in output
