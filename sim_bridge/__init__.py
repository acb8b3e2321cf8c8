"""MuJoCo scenes and the simulated RGB-D camera node."""

import os

# MuJoCo picks its OpenGL backend when it is first imported: default to headless EGL (works with
# software Mesa as well as GPU drivers); `sim_bridge.render` falls back to OSMesa if EGL fails.
os.environ.setdefault("MUJOCO_GL", "egl")
