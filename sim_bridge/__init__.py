"""MuJoCo scenes and the simulated RGB-D camera node."""
