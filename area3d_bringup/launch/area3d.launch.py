"""`ros2 launch area3d_bringup area3d.launch.py [params_file:=FILE] [namespace:=NS]`: the AREA3D graph
under a sourced ROS 2 (the same node list as `area3d launch`)."""

from pathlib import Path

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

from area3d_bringup.graph import NODES


def generate_launch_description() -> LaunchDescription:
    default_params = str(
        Path(get_package_share_directory("area3d_bringup")) / "config" / "area3d.yaml"
    )
    params_file = LaunchConfiguration("params_file")
    namespace = LaunchConfiguration("namespace")
    nodes = [
        Node(
            package=node.package,
            executable=node.executable,
            name=node.name,
            namespace=namespace,
            parameters=[params_file],
            output="screen",
            emulate_tty=True,
        )
        for node in NODES
    ]
    return LaunchDescription(
        [
            DeclareLaunchArgument(
                "params_file",
                default_value=default_params,
                description="ROS 2 parameter YAML for every AREA3D node",
            ),
            DeclareLaunchArgument(
                "namespace", default_value="", description="namespace of the whole graph"
            ),
            *nodes,
        ]
    )
