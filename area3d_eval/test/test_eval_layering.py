"""The evaluation runs where no ROS 2 is installed: its modules import no rclpy (nor any message
code that would load it)."""

import subprocess
import sys
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[2]
OFFLINE = ("area3d_eval.report", "area3d_eval.evaluate", "area3d_eval.metrics")


def test_the_report_the_evaluation_and_the_metrics_import_no_rclpy():
    script = (
        "import importlib, sys\n"
        f"for name in {OFFLINE!r}:\n"
        "    importlib.import_module(name)\n"
        "print(sorted(n for n in sys.modules if n.split('.')[0] in ('rclpy', 'rosidl_parser')))\n"
        "print(all(name in sys.modules for name in " + repr(OFFLINE) + "))\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", script], cwd=REPO_ROOT, capture_output=True, text=True, timeout=300
    )
    assert out.returncode == 0, out.stderr
    loaded, imported = out.stdout.split("\n")[:2]
    assert imported == "True"
    assert loaded == "[]", f"rclpy modules loaded: {loaded}"
