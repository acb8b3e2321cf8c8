"""Every test process talks ROS 2 on its own domain with discovery kept on this machine."""

from __future__ import annotations

import os

# Domains 102..221: above the range `area3d run` picks free domains from (1..101), unique per
# pytest process so that parallel or repeated sessions do not see each other.
os.environ["ROS_DOMAIN_ID"] = str(102 + os.getpid() % 120)
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"

from area3d_msgs_py import middleware  # noqa: E402

middleware.configure()
