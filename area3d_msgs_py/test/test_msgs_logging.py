"""Python `logging` from our modules reaches the node's ROS log (/rosout), with the node's name."""

from __future__ import annotations

import logging
import os
import signal
import subprocess
import sys
from pathlib import Path

import rclpy
from rcl_interfaces.msg import Log

from area3d_msgs_py import qos
from area3d_msgs_py.lifecycle import forward_python_logging
from area3d_msgs_py.probe import Probe

REPO_ROOT = Path(__file__).resolve().parents[2]
TIMEOUT_S = 120.0
ROSOUT_READER = qos.reliable(1000)


def _named(logs: list, name: str) -> list:
    return [log for log in list(logs) if log.name == name]


def test_python_log_records_reach_rosout_under_the_nodes_name_at_their_level():
    context = rclpy.Context()
    rclpy.init(context=context)
    node = rclpy.create_node("py_logging_test", context=context)
    handler = forward_python_logging(node)
    try:
        with Probe("rosout_reader") as probe:
            logs = probe.listen(Log, "/rosout", ROSOUT_READER)
            assert probe.wait_for(lambda: node.count_subscribers("/rosout") >= 1, TIMEOUT_S)
            backends = logging.getLogger("area3d_semantics.backends")
            backends.debug("not at the node's level (INFO)")
            backends.warning("VLM attempt %d/%d failed: %s", 1, 3, "connection refused")
            logging.getLogger("area3d_semantics.parser").info("VLM answer: skipped a line")
            name = "py_logging_test.area3d_semantics.parser"
            assert probe.wait_for(lambda: _named(logs, name), TIMEOUT_S)
            (warning,) = _named(logs, "py_logging_test.area3d_semantics.backends")
            assert warning.level == Log.WARN
            assert warning.msg == "VLM attempt 1/3 failed: connection refused"
            (info,) = _named(logs, name)
            assert info.level == Log.INFO and info.msg == "VLM answer: skipped a line"
    finally:
        logging.getLogger().removeHandler(handler)
        node.destroy_node()
        context.try_shutdown()


NODE = """
import logging, sys
from rclpy.node import Node
from area3d_msgs_py.lifecycle import run_node

class Talker(Node):
    def __init__(self):
        super().__init__("talker")
        log = logging.getLogger("area3d_semantics.backends")
        self.create_timer(0.2, lambda: log.error("backend unreachable"))

sys.exit(run_node(Talker, "talker"))
"""


def test_every_node_run_by_run_node_forwards_python_logging():
    process = subprocess.Popen(
        [sys.executable, "-c", NODE],
        env=dict(os.environ, PYTHONPATH=str(REPO_ROOT)),
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    try:
        with Probe("rosout_reader") as probe:
            logs = probe.listen(Log, "/rosout", ROSOUT_READER)
            name = "talker.area3d_semantics.backends"
            assert probe.wait_for(lambda: _named(logs, name), TIMEOUT_S)
            log = _named(logs, name)[0]
            assert log.level == Log.ERROR and log.msg == "backend unreachable"
    finally:
        process.send_signal(signal.SIGINT)
        out, _ = process.communicate(timeout=60)
    assert process.returncode == 0, out[-2000:]
    assert "backend unreachable" in out  # the node's console log too
