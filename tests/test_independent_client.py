"""Proof by an independent client: the graph started with `area3d launch`, and a separate process
running a plain rclpy node that knows only the documented names (tests/clients/independent_client.py,
no project imports) drives the camera, checks every output and plans closed loop and batch."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

CLIENT = Path(__file__).parent / "clients" / "independent_client.py"
# Around single_object's table-top object, as a user who knows where the object is would place them.
TARGET = [-0.11, -0.15, 0.8]
EYES = [
    [-0.11 + 0.55 * c, -0.15 + 0.55 * s, 1.05]
    for c, s in ((-0.34, -0.94), (0.0, -1.0), (0.34, -0.94), (0.64, -0.77))
]


def test_an_independent_rclpy_client_sees_every_output_and_plans_closed_loop_and_batch(tmp_path):
    graph = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "area3d_bringup.cli",
            "launch",
            "--localhost",
            "-p",
            "sim_bridge.readers.all=[independent_client]",  # its first frames wait for the client
            "-p",
            "sim_bridge.width=320",
            "-p",
            "sim_bridge.height=240",
            "-p",
            "planner.width=320",
            "-p",
            "planner.height=240",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        cwd=tmp_path,
    )
    try:
        client = subprocess.run(
            [sys.executable, str(CLIENT), json.dumps({"target": TARGET, "eyes": EYES})],
            capture_output=True,
            text=True,
            timeout=600,
            env={k: v for k, v in os.environ.items() if k != "PYTHONPATH"},
            cwd=tmp_path,
        )
    finally:
        graph.send_signal(signal.SIGINT)
        try:
            graph_log, _ = graph.communicate(timeout=120)  # generous: a loaded machine
        except subprocess.TimeoutExpired:
            graph.send_signal(signal.SIGUSR1)  # where the launcher hangs, into its log
            time.sleep(2)
            graph.kill()
            graph_log, _ = graph.communicate()
    assert client.returncode == 0, client.stdout[-3000:] + client.stderr[-3000:] + graph_log[-3000:]
    seen = json.loads(client.stdout.strip().splitlines()[-1])
    assert seen["captured"] == 6
    assert len(seen["closed_loop_views"]) == 2 and len(seen["batch_views"]) == 3
    assert seen["grid_points"] > 0
    assert all(count > 0 for count in seen["counts"].values()), seen["counts"]
    assert graph.returncode == 0, graph_log[-3000:]  # Ctrl-C stops every node cleanly
