"""Every node of the graph exits on SIGINT within 2 s (ROS 2 convention: Ctrl-C is a clean stop)."""

from __future__ import annotations

import signal
import subprocess
import time
from pathlib import Path

from area3d_bringup.launch_description import build_graph
from area3d_bringup.launcher import Launcher

EXIT_LIMIT_S = 2.0  # issue 13: every node exits within 2 s of SIGINT
# The last line each node logs when it is built (its spin starts right after).
READY_LINE = {
    "sim_bridge": "waiting for",
    "perception": "backend=",
    "semantics": "backend=",
    "planner": "planner ready",
}


def _wait_ready(launcher: Launcher, timeout_s: float = 120.0) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        launcher.check()
        if all(
            any(READY_LINE[name] in line for line in launcher.output[name]) for name in READY_LINE
        ):
            return
        time.sleep(0.05)
    raise AssertionError(f"nodes not ready: { {n: o[-3:] for n, o in launcher.output.items()} }")


def test_each_node_exits_within_two_seconds_of_sigint_with_code_zero(tmp_path: Path):
    specs = build_graph(
        overrides={
            "sim_bridge": {"width": 160, "height": 120},
            "planner": {"width": 160, "height": 120},
        }
    )
    lines: list[str] = []
    launcher = Launcher(specs, tmp_path, log_sink=lines.append)
    launcher.start()
    exit_s: dict[str, float] = {}
    codes: dict[str, int | None] = {}
    try:
        _wait_ready(launcher)
        for name, proc in launcher.processes.items():  # one at a time: each measured alone
            t0 = time.monotonic()
            proc.send_signal(signal.SIGINT)
            try:
                codes[name] = proc.wait(timeout=10 * EXIT_LIMIT_S)
            except subprocess.TimeoutExpired:
                codes[name] = None
            exit_s[name] = time.monotonic() - t0
    finally:
        launcher.stop()
    print("exit after SIGINT, s:", {n: round(t, 3) for n, t in exit_s.items()})
    assert codes == {name: 0 for name in READY_LINE}, (codes, lines[-20:])
    slow = {n: t for n, t in exit_s.items() if t > EXIT_LIMIT_S}
    assert not slow, f"nodes slower than {EXIT_LIMIT_S} s to exit on SIGINT: {slow}"
    assert not any("Traceback" in line for line in lines), lines[-40:]
