"""A hard region as a numpy row: the array form of area3d_interfaces/msg/HardRegion, without ROS.

The planner's core finds them (`area3d_planner.hard_regions`), the codecs send and read them
(`codecs.hard_regions_to_msg` / `msg_to_hard_regions`), the report reads them back from a saved
grid: all on this one dtype, which imports no message code.
"""

from __future__ import annotations

import numpy as np

#: One hard region per row: centroid and extent in metres, in the array's frame.
HARD_REGION_DTYPE = np.dtype(
    [
        ("centroid", "<f8", (3,)),
        ("extent", "<f8", (3,)),
        ("voxel_count", "<u4"),
        ("direction_count", "<u4"),
        ("mean_uncertainty", "<f4"),
    ]
)
