"""The RViz configuration of the graph: the uncertainty grid as boxes the size of its voxels, the
planned views' frustums and path, the hard regions as boxes, the camera image and TF.

Topic names are relative (`area3d/planner/uncertainty_grid`), so RViz resolves them in its own
namespace: `rviz2 -d area3d.rviz --ros-args -r __ns:=/robot1` shows the graph launched under
/robot1. The grid's box size is the voxel size the planner will use (`PlannerConfig.grid_spec`,
from the level, the region and the voxel budget): 1 cm boxes for an object, 5 cm for a room.
`area3d rviz` writes the configuration for a launch's parameters; the one installed with the
package (`area3d_bringup/rviz/area3d.rviz`) is that of the bundled defaults.
"""

from __future__ import annotations

from dataclasses import fields
from importlib import resources
from pathlib import Path

import yaml

from area3d_msgs_py import topics
from area3d_planner.markers import HARD_REGIONS_NS, VIEWS_NS

GRID_TOPIC = topics.UNCERTAINTY_GRID.name
VIEWS_TOPIC = topics.NEXT_VIEWS.name
MARKERS_TOPIC = topics.VIEW_MARKERS.name
HARD_REGIONS_TOPIC = topics.HARD_REGION_MARKERS.name
MESH_TOPIC = topics.RECONSTRUCTION_MESH.name
MESH_NS = "reconstruction"  # the namespace of the mesh marker (codecs.mesh_marker_cdr's default)
IMAGE_TOPIC = topics.COLOR.name


def installed_config() -> Path:
    """The configuration installed with the package (that of the bundled defaults)."""
    return Path(str(resources.files("area3d_bringup") / "rviz" / "area3d.rviz"))


def grid_voxel_size(planner_parameters: dict) -> float:
    """The voxel size, metres, of the grid a planner with these parameters builds."""
    from area3d_planner.config import PlannerConfig

    names = {f.name for f in fields(PlannerConfig)}
    config = PlannerConfig(**{k: v for k, v in planner_parameters.items() if k in names})
    return float(config.grid_spec().voxel_size)


def _topic(value: str, durability: str, depth: int) -> dict:
    return {
        "Value": value,
        "Depth": depth,
        "Durability Policy": durability,
        "Reliability Policy": "Reliable",
        "History Policy": "Keep Last",
    }


def rviz_config(voxel_size: float, world_frame: str = "world") -> dict:
    """The RViz 2 configuration (a dict; `yaml.safe_dump` writes the .rviz file)."""
    if not voxel_size > 0:
        raise ValueError(f"voxel_size: got {voxel_size}, expected metres > 0")
    displays = [
        {
            "Class": "rviz_default_plugins/Grid",
            "Name": "Grid",
            "Enabled": True,
            "Reference Frame": "<Fixed Frame>",
            "Plane": "XY",
            "Cell Size": 0.5,
            "Plane Cell Count": 20,
        },
        {
            "Class": "rviz_default_plugins/TF",
            "Name": "TF",
            "Enabled": True,
            "Show Names": True,
            "Show Axes": True,
            "Marker Scale": 0.3,
        },
        {
            "Class": "rviz_default_plugins/PointCloud2",
            "Name": "Uncertainty grid",
            "Enabled": True,
            "Topic": _topic(GRID_TOPIC, "Transient Local", 1),
            "Style": "Boxes",
            "Size (m)": float(voxel_size),
            "Alpha": 0.6,
            "Color Transformer": "Intensity",
            "Channel Name": "uncertainty",
            "Use rainbow": True,
            "Invert Rainbow": False,
            "Autocompute Intensity Bounds": True,
            "Position Transformer": "XYZ",
            "Decay Time": 0,
            "Queue Size": 1,
            "Selectable": True,
        },
        {
            "Class": "rviz_default_plugins/MarkerArray",
            "Name": "Planned views",
            "Enabled": True,
            "Topic": _topic(MARKERS_TOPIC, "Transient Local", 10),
            "Namespaces": {VIEWS_NS: True},
        },
        {
            "Class": "rviz_default_plugins/MarkerArray",
            "Name": "Hard regions",
            "Enabled": True,
            "Topic": _topic(HARD_REGIONS_TOPIC, "Transient Local", 10),
            "Namespaces": {HARD_REGIONS_NS: True},
        },
        {
            "Class": "rviz_default_plugins/Marker",
            "Name": "Reconstruction",
            "Enabled": True,
            "Topic": _topic(MESH_TOPIC, "Transient Local", 1),
            "Namespaces": {MESH_NS: True},
        },
        {
            "Class": "rviz_default_plugins/Path",
            "Name": "Next views",
            "Enabled": True,
            "Topic": _topic(VIEWS_TOPIC, "Volatile", 10),
            "Line Style": "Lines",
            "Color": "255; 200; 0",
            "Alpha": 1,
            "Pose Style": "Axes",
            "Pose Axes Length": 0.15,
            "Pose Axes Radius": 0.01,
        },
        {
            "Class": "rviz_default_plugins/Image",
            "Name": "Camera",
            "Enabled": True,
            "Topic": _topic(IMAGE_TOPIC, "Volatile", 5),
            "Normalize Range": True,
        },
    ]
    return {
        "Panels": [
            {"Class": "rviz_common/Displays", "Name": "Displays"},
            {"Class": "rviz_common/Views", "Name": "Views"},
        ],
        "Visualization Manager": {
            "Class": "",
            "Global Options": {
                "Background Color": "48; 48; 48",
                "Fixed Frame": world_frame,
                "Frame Rate": 30,
            },
            "Displays": displays,
            "Tools": [
                {"Class": f"rviz_default_plugins/{tool}"}
                for tool in ("Interact", "MoveCamera", "Select", "Measure")
            ],
            "Views": {
                "Current": {
                    "Class": "rviz_default_plugins/Orbit",
                    "Distance": 4,
                    "Focal Point": {"X": 0, "Y": 0, "Z": 0.5},
                    "Pitch": 0.6,
                    "Yaw": 0.8,
                    "Target Frame": "<Fixed Frame>",
                }
            },
        },
        "Window Geometry": {"Height": 900, "Width": 1400},
    }


def config_text(voxel_size: float, world_frame: str = "world") -> str:
    return (
        "# RViz 2 configuration of the AREA3D graph (written by area3d_bringup/rviz.py; `area3d rviz`\n"
        "# writes one for your launch). Topics are relative: start RViz in the graph's namespace,\n"
        "# e.g. `rviz2 -d area3d.rviz --ros-args -r __ns:=/robot1`.\n"
        + yaml.safe_dump(rviz_config(voxel_size, world_frame), sort_keys=False)
    )


def write_config(path: Path, planner_parameters: dict) -> float:
    """Write the configuration for a planner with these parameters to `path`; its voxel size."""
    voxel = grid_voxel_size(planner_parameters)
    world_frame = planner_parameters.get("world_frame", "world")
    Path(path).write_text(config_text(voxel, world_frame))
    return voxel
