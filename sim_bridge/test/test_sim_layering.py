"""The simulator stands on area3d_msgs_py only: none of its modules imports perception, the
planner, semantics, the launcher or the evaluation."""

import pkgutil
import subprocess
import sys
from pathlib import Path

import sim_bridge

REPO_ROOT = Path(__file__).resolve().parents[2]
ABOVE = ("area3d_perception", "area3d_planner", "area3d_semantics", "area3d_bringup", "area3d_eval")
# colcon's setup script is not a module of the package
NOT_YET = ("sim_bridge.setup",)


def test_the_simulator_imports_nothing_above_area3d_msgs_py():
    modules = [
        f"sim_bridge.{m.name}"
        for m in pkgutil.iter_modules(sim_bridge.__path__)
        if f"sim_bridge.{m.name}" not in NOT_YET
    ]
    assert "sim_bridge.camera" in modules and "sim_bridge.noise" in modules
    script = (
        f"import importlib, sys\nfor m in {modules!r}:\n    importlib.import_module(m)\n"
        f"print(sorted({{n.split('.')[0] for n in sys.modules}} & set({ABOVE!r})))"
    )
    out = subprocess.run(
        [sys.executable, "-c", script], cwd=REPO_ROOT, capture_output=True, text=True, timeout=300
    )
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]", f"imported from above: {out.stdout.strip()}"
