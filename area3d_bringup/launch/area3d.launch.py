"""`ros2 launch area3d_bringup area3d.launch.py [params_file:=FILE]`: the AREA3D graph under ROS 2."""

from pathlib import Path

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

# (package, executable, node name): the same graph `area3d launch` starts.
NODES = (
    ("sim_bridge", "sim_bridge_node", "sim_bridge"),
    ("area3d_perception", "perception_node", "perception"),
    ("area3d_semantics", "semantics_node", "semantics"),
    ("area3d_planner", "planner_node", "planner"),
)


def generate_launch_description() -> LaunchDescription:
    default_params = str(
        Path(get_package_share_directory("area3d_bringup")) / "config" / "area3d.yaml"
    )
    params_file = LaunchConfiguration("params_file")
    nodes = [
        Node(
            package=package,
            executable=executable,
            name=name,
            parameters=[params_file],
            output="screen",
            emulate_tty=True,
        )
        for package, executable, name in NODES
    ]
    return LaunchDescription(
        [
            DeclareLaunchArgument(
                "params_file",
                default_value=default_params,
                description="ROS 2 parameter YAML for every AREA3D node",
            ),
            *nodes,
        ]
    )
