"""The graph's topics and services, in one table: name, type, QoS, who writes and who reads.

Names are relative (a namespace moves the whole graph; `/tf` and `/tf_static` stay global, as
ROS 2 has them). The nodes, the mission manager (`area3d run`) and the benchmarks take names, types
and QoS from here; sim_bridge's `readers.*` defaults and the mission manager's wait for the
graph's readers follow the `readers` listed here. The README's topic table says the same for a
reader of the docs; the independent test clients (tests/clients) keep their own copies on
purpose, as an outside ROS 2 program would.

QoS: reliable keep-last everywhere; `Topic.qos` gives a topic's profile, with another history
depth where a reader needs a deeper queue than the writer keeps. The camera's stream and the
odometry (`Topic.camera`: what a robot's drivers publish) are volatile, as a driver publishes
them, and a graph node reads them with the QoS its `camera_qos` parameter chooses
(`Topic.reader_qos`: reliable, or best effort for drivers that publish with the sensor-data
profile); the per-frame outputs one graph node computes for another are transient local on both
sides, so a reader whose discovery finishes late still gets the first frames (volatile readers
such as RViz match either way).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from rclpy.qos import QoSProfile

from area3d_msgs_py import msgs, qos

# Graph node names, as they appear in the tables below (area3d_bringup/graph.py starts them).
SIM_BRIDGE, PERCEPTION, SEMANTICS, PLANNER = "sim_bridge", "perception", "semantics", "planner"
RECONSTRUCTION = "reconstruction"
MISSION_MANAGER = "mission_manager"  # `area3d run`, or a robot's own mission manager
ANYONE = "anyone"  # no particular writer: any program may publish it
ROBOT = "robot"  # the robot's own drivers (its odometry, its TF tree)

VOLATILE, TRANSIENT_LOCAL = "volatile", "transient_local"
# The semantic maps of the initial views (15 at room level) can go out in one burst.
SEMANTIC_DEPTH = 64
TF_DEPTH = 100


@dataclass(frozen=True)
class Topic:
    """One topic of the graph. `readers`: the graph nodes that subscribe to it (anyone else may);
    `camera`: an input a robot's drivers provide (the camera's stream, the odometry), read with
    the node's `camera_qos`."""

    name: str  # relative, e.g. "area3d/camera/pose"
    msg_type: Any  # the generated message class
    writer: str
    readers: tuple[str, ...] = ()
    durability: str = VOLATILE
    depth: int = qos.DEFAULT_DEPTH  # history the writer keeps
    camera: bool = False
    description: str = ""

    def qos(self, depth: int | None = None) -> QoSProfile:
        """The topic's QoS, for its writer and its readers; `depth` replaces the history depth
        (a reader that falls behind in bursts keeps more)."""
        depth = self.depth if depth is None else int(depth)
        if self.durability == TRANSIENT_LOCAL:
            return qos.latched(depth)
        return qos.reliable(depth)

    def reader_qos(self, camera_qos: str = "reliable", depth: int | None = None) -> QoSProfile:
        """The profile a graph node subscribes with: the topic's (`qos`), or for a driver's
        input (`camera`) the node's `camera_qos` choice (`qos.camera_input`)."""
        if not self.camera:
            return self.qos(depth)
        return qos.camera_input(camera_qos, self.depth if depth is None else int(depth))

    @property
    def type_name(self) -> str:
        """The ROS type name, e.g. "sensor_msgs/msg/Image"."""
        return msgs.type_name_of(self.msg_type())


@dataclass(frozen=True)
class Service:
    """One service of the graph: its relative name, type and the node that serves it."""

    name: str
    srv_type: Any
    server: str
    description: str = ""


def _camera(name: str, msg_type: Any, readers: tuple[str, ...], description: str) -> Topic:
    return Topic(
        name, msg_type, SIM_BRIDGE, readers, depth=qos.FRAME_DEPTH, camera=True,
        description=description,
    )  # fmt: skip


def _status(node: str) -> Topic:
    return Topic(
        f"area3d/{node}/status",
        msgs.String,
        node,
        depth=qos.FRAME_DEPTH,
        description="JSON status line: counters and rejected inputs, after a change",
    )


# -- the camera (sim_bridge, or a real camera driver) -------------------------------------------
GOAL = Topic(
    "area3d/camera/goal_pose",
    msgs.PoseStamped,
    MISSION_MANAGER,
    (SIM_BRIDGE,),
    depth=qos.FRAME_DEPTH,
    description="where the camera goes next: optical-frame pose in `world`",
)
COLOR = _camera("area3d/camera/color/image_raw", msgs.Image, (PERCEPTION, SEMANTICS), "rgb8 image")
DEPTH = _camera(
    "area3d/camera/depth/image_raw",
    msgs.Image,
    (PERCEPTION, SEMANTICS),
    "32FC1 depth along the optical axis, metres, NaN = no return",
)
CAMERA_INFO = _camera(
    "area3d/camera/camera_info",
    msgs.CameraInfo,
    (PERCEPTION, PLANNER, RECONSTRUCTION),
    "intrinsics",
)
POSE = _camera(
    "area3d/camera/pose",
    msgs.PoseStamped,
    (PERCEPTION, PLANNER, RECONSTRUCTION),
    "optical-frame pose of each captured frame in `world`",
)
# The right camera of a rectified stereo pair, named as a ROS stereo camera names it
# (stereo_image_proc: right/image_rect, right/camera_info); the left image is the colour image.
RIGHT_IMAGE = _camera(
    "area3d/camera/right/image_rect", msgs.Image, (PERCEPTION,), "right image of the stereo pair"
)
RIGHT_CAMERA_INFO = _camera(
    "area3d/camera/right/camera_info",
    msgs.CameraInfo,
    (PERCEPTION,),
    "right camera's intrinsics, P[3] = Tx = -fx B",
)
CAMERA_STATUS = Topic(
    "area3d/camera/status",
    msgs.String,
    SIM_BRIDGE,
    (MISSION_MANAGER,),
    depth=qos.FRAME_DEPTH,
    description="JSON {stamp_ns, ok, reason, rejected} per goal",
)
# TF: sim_bridge's camera (world -> camera_link -> camera_optical_frame), or a robot's tree; read
# by perception and the planner with `pose_source: tf` (/tf_static also with `odometry`)
TF = Topic(
    "/tf",
    msgs.TFMessage,
    SIM_BRIDGE,
    (PERCEPTION, PLANNER, RECONSTRUCTION),
    depth=TF_DEPTH,
    description="world -> camera_link at each captured frame",
)
TF_STATIC = Topic(
    "/tf_static",
    msgs.TFMessage,
    SIM_BRIDGE,
    (PERCEPTION, PLANNER, RECONSTRUCTION),
    durability=TRANSIENT_LOCAL,
    # a robot has several static broadcasters, each latching its own: a reader keeps them all
    # (tf2's static listener: 100)
    depth=TF_DEPTH,
    description="camera_link -> camera_optical_frame (latched)",
)
# A robot's odometry: the camera pose comes from it and the camera's mount with
# `pose_source: odometry` (REP 105: header.frame_id the odometry frame, child_frame_id the body).
ODOMETRY = Topic(
    "area3d/odom",
    msgs.Odometry,
    ROBOT,
    (PERCEPTION, PLANNER, RECONSTRUCTION),
    depth=qos.FRAME_DEPTH,
    camera=True,
    description="nav_msgs/Odometry of the body the camera is mounted on",
)

# -- perception -----------------------------------------------------------------------------
PERCEPTION_DEPTH = Topic(
    "area3d/perception/depth",
    msgs.Image,
    PERCEPTION,
    (PLANNER, RECONSTRUCTION),
    TRANSIENT_LOCAL,
    qos.FRAME_DEPTH,
    description="32FC1 metric depth per frame",
)
PERCEPTION_CONFIDENCE = Topic(
    "area3d/perception/confidence",
    msgs.Image,
    PERCEPTION,
    (PLANNER, SEMANTICS),
    TRANSIENT_LOCAL,
    qos.FRAME_DEPTH,
    description="32FC1 per-pixel confidence in [0, 1]",
)
# What the reconstruction integrates each depth pixel with: the confidence, except where the
# backend has a weight of its own (stereo with the calibrated confidence: the matcher's factors).
PERCEPTION_WEIGHT = Topic(
    "area3d/perception/weight",
    msgs.Image,
    PERCEPTION,
    (RECONSTRUCTION,),
    TRANSIENT_LOCAL,
    qos.FRAME_DEPTH,
    description="32FC1 per-pixel fusion weight in [0, 1]",
)
# The colour of each frame perception answered (its keyframes): what the reconstruction colours
# the surface with, at the rate of perception's outputs rather than the camera's stream.
PERCEPTION_COLOR = Topic(
    "area3d/perception/color",
    msgs.Image,
    PERCEPTION,
    (RECONSTRUCTION,),
    TRANSIENT_LOCAL,
    qos.FRAME_DEPTH,
    description="rgb8 colour of each frame perception answered",
)
PERCEPTION_STATUS = _status(PERCEPTION)

# -- semantics ------------------------------------------------------------------------------
SEMANTIC_REGIONS = Topic(
    "area3d/semantics/regions",
    msgs.String,
    SEMANTICS,
    durability=TRANSIENT_LOCAL,
    depth=1,
    description="JSON of the parsed VLM regions (latched)",
)
SEMANTIC_WEIGHT = Topic(
    "area3d/semantics/weight",
    msgs.Image,
    SEMANTICS,
    durability=TRANSIENT_LOCAL,
    depth=SEMANTIC_DEPTH,
    description="32FC1 weight map W in [0, 1] per frame",
)
SEMANTIC_UNCERTAINTY = Topic(
    "area3d/semantics/uncertainty",
    msgs.Image,
    SEMANTICS,
    (PLANNER,),
    TRANSIENT_LOCAL,
    SEMANTIC_DEPTH,
    description="32FC1 U_sem per frame",
)
SEMANTIC_REQUEST = Topic(
    "area3d/semantics/request",
    msgs.String,
    ANYONE,
    (SEMANTICS,),
    description="any text: query the VLM again",
)
SEMANTICS_STATUS = _status(SEMANTICS)

# -- planner --------------------------------------------------------------------------------
UNCERTAINTY_GRID = Topic(
    "area3d/planner/uncertainty_grid",
    msgs.PointCloud2,
    PLANNER,
    durability=TRANSIENT_LOCAL,
    depth=1,
    description="x, y, z, uncertainty, geometric, semantic, occupancy (latched)",
)
NEXT_VIEWS = Topic(
    "area3d/planner/next_views", msgs.Path, PLANNER, description="the views of the last plan"
)
VIEW_MARKERS = Topic(
    "area3d/planner/view_markers",
    msgs.MarkerArray,
    PLANNER,
    durability=TRANSIENT_LOCAL,
    depth=1,
    description="camera frustums of the last plan's views, coloured by order (latched)",
)
HARD_REGIONS = Topic(
    "area3d/planner/hard_regions",
    msgs.HardRegionArray,
    PLANNER,
    durability=TRANSIENT_LOCAL,
    depth=1,
    description="what no view is expected to resolve, as regions, largest first (latched)",
)
HARD_REGION_MARKERS = Topic(
    "area3d/planner/hard_region_markers",
    msgs.MarkerArray,
    PLANNER,
    durability=TRANSIENT_LOCAL,
    depth=1,
    description="the hard regions as translucent boxes (latched)",
)
PLANNER_STATUS = _status(PLANNER)
SELECT_VIEWS = Service(
    "area3d/planner/select_views",
    msgs.NextBestView,
    PLANNER,
    "count, mode, current pose stamped with the last capture -> success, message, views "
    "(best first, in world_frame), gains",
)
NEXT_BEST_VIEW = Service(
    "area3d/planner/next_best_view",
    msgs.GetPlan,
    PLANNER,
    "start = current pose stamped with the last capture; goal.pose.position.x = views wanted "
    "(for tools with the standard types only)",
)
CAMERA_RESET = Service(
    "area3d/camera/reset",
    msgs.Trigger,
    SIM_BRIDGE,
    "the simulated camera only: start its noise over from noise_seed and hold the next frame "
    "until its readers have matched again, so an episode repeats on a running graph",
)
PLANNER_RESET = Service(
    "area3d/planner/reset",
    msgs.Trigger,
    PLANNER,
    "forget the map, its fused frames and semantic maps and the frames waiting to be fused: the "
    "next episode starts from nothing (the latched grid goes out empty)",
)
PLANNER_SAVE_MAP = Service(
    "area3d/planner/save_map",
    msgs.MapFile,
    PLANNER,
    "path -> the planner's whole map written there (a map file, docs/map_format.md): success, "
    "message, the absolute path, its size",
)
PLANNER_LOAD_MAP = Service(
    "area3d/planner/load_map",
    msgs.MapFile,
    PLANNER,
    "path -> the map file read and put in place of the running map, which a file that does not "
    "fit (another grid, region or format version, truncated) leaves untouched",
)
SEMANTICS_RESET = Service(
    "area3d/semantics/reset",
    msgs.Trigger,
    SEMANTICS,
    "forget the collected views and their analysis: the next num_initial_views frames are "
    "analysed afresh",
)

# -- reconstruction -------------------------------------------------------------------------
RECONSTRUCTION_MESH = Topic(
    "area3d/reconstruction/mesh",
    msgs.Marker,
    RECONSTRUCTION,
    durability=TRANSIENT_LOCAL,
    depth=1,
    description="the coloured TSDF mesh of the fused frames, a TRIANGLE_LIST (latched)",
)
RECONSTRUCTION_STATUS = _status(RECONSTRUCTION)
RECONSTRUCTION_SAVE_MAP = Service(
    "area3d/reconstruction/save_map",
    msgs.MapFile,
    RECONSTRUCTION,
    "path -> the TSDF volume written there (a map file, docs/map_format.md)",
)
RECONSTRUCTION_LOAD_MAP = Service(
    "area3d/reconstruction/load_map",
    msgs.MapFile,
    RECONSTRUCTION,
    "path -> the saved volume in place of the running one (refused, the volume kept, when the "
    "file does not fit)",
)
RECONSTRUCTION_EXPORT_MESH = Service(
    "area3d/reconstruction/export_mesh",
    msgs.MapFile,
    RECONSTRUCTION,
    "path (.ply) -> the current mesh written there as binary PLY with vertex colours",
)
RECONSTRUCTION_RESET = Service(
    "area3d/reconstruction/reset",
    msgs.Trigger,
    RECONSTRUCTION,
    "forget the volume and the frames waiting: the next episode's mesh starts from nothing",
)

# -- every node -----------------------------------------------------------------------------
DIAGNOSTICS = Topic(
    "/diagnostics",
    msgs.DiagnosticArray,
    ANYONE,
    description="each node's status as diagnostic_msgs (1 Hz and after a change)",
)
FOXGLOVE_BRIDGE = "foxglove_bridge"  # `--foxglove`: the live view's node (not in graph.py)
FOXGLOVE_STATUS = _status(FOXGLOVE_BRIDGE)

#: every topic of the graph, camera first
TOPICS: tuple[Topic, ...] = (
    GOAL, COLOR, DEPTH, CAMERA_INFO, POSE, RIGHT_IMAGE, RIGHT_CAMERA_INFO, CAMERA_STATUS, TF,
    TF_STATIC, ODOMETRY, PERCEPTION_DEPTH, PERCEPTION_CONFIDENCE, PERCEPTION_WEIGHT, PERCEPTION_COLOR, PERCEPTION_STATUS, SEMANTIC_REGIONS,
    SEMANTIC_WEIGHT, SEMANTIC_UNCERTAINTY, SEMANTIC_REQUEST, SEMANTICS_STATUS, UNCERTAINTY_GRID,
    NEXT_VIEWS, VIEW_MARKERS, HARD_REGIONS, HARD_REGION_MARKERS, PLANNER_STATUS,
    RECONSTRUCTION_MESH, RECONSTRUCTION_STATUS, DIAGNOSTICS, FOXGLOVE_STATUS,
)  # fmt: skip


#: every service of the graph
SERVICES: tuple[Service, ...] = (
    SELECT_VIEWS, NEXT_BEST_VIEW, CAMERA_RESET, PLANNER_RESET, PLANNER_SAVE_MAP, PLANNER_LOAD_MAP,
    SEMANTICS_RESET, RECONSTRUCTION_SAVE_MAP, RECONSTRUCTION_LOAD_MAP, RECONSTRUCTION_EXPORT_MESH,
    RECONSTRUCTION_RESET,
)  # fmt: skip


def read_by(node: str, topics: tuple[Topic, ...] = TOPICS) -> tuple[Topic, ...]:
    """The topics of `topics` that graph node `node` reads."""
    return tuple(t for t in topics if node in t.readers)
