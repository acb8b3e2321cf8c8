"""The nodes of the AREA3D graph, in start order: one list for `area3d launch`, `area3d run` and
the ROS 2 launch file (`launch/area3d.launch.py`)."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class GraphNode:
    name: str  # ROS node name
    package: str  # ROS package (colcon) and Python package
    executable: str  # console script installed by the package's setup.py
    module: str  # Python module whose `main(args)` runs the node


#: the camera first, then the nodes that read it
NODES: tuple[GraphNode, ...] = (
    GraphNode("sim_bridge", "sim_bridge", "sim_bridge_node", "sim_bridge.node"),
    GraphNode("perception", "area3d_perception", "perception_node", "area3d_perception.node"),
    GraphNode("semantics", "area3d_semantics", "semantics_node", "area3d_semantics.node"),
    GraphNode("planner", "area3d_planner", "planner_node", "area3d_planner.node"),
    GraphNode(
        "reconstruction",
        "area3d_reconstruction",
        "reconstruction_node",
        "area3d_reconstruction.node",
    ),
)

#: (node name, module) pairs, what the launcher starts
GRAPH_NODES: tuple[tuple[str, str], ...] = tuple((n.name, n.module) for n in NODES)
