"""The planner's views and hard regions as `visualization_msgs/MarkerArray`, for RViz and Foxglove.

A planned view is drawn as its camera frustum: a LINE_LIST from the camera centre to the four
corners of the image plane at a display range, and the rectangle joining those corners, coloured
by the view's order (first: yellow, last: violet). Hard regions (boxes the planner reports as not
resolvable by any view) are translucent red CUBEs. Every array starts with a DELETEALL for its
namespace, so views and regions of an earlier plan disappear.

Geometry (pure numpy, no ROS): `frustum_points`; messages: `view_markers`, `hard_region_markers`.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from geometry_msgs.msg import Point, Pose, Quaternion, Vector3
from std_msgs.msg import ColorRGBA
from visualization_msgs.msg import Marker, MarkerArray

from area3d_msgs_py import codecs, msgs
from area3d_msgs_py.errors import InputError
from area3d_planner.cloud import grid_to_cloud
from area3d_planner.hard_regions import cloud_hard_regions

VIEWS_NS = "planned_views"
HARD_REGIONS_NS = "hard_regions"
LINE_WIDTH_FRACTION = 0.02  # line width, as a fraction of the display range
# first and last view's colours (RGB); the views between are interpolated
FIRST_COLOUR = np.array([1.0, 0.85, 0.1])
LAST_COLOUR = np.array([0.45, 0.1, 0.75])
HARD_REGION_COLOUR = ColorRGBA(r=0.9, g=0.15, b=0.15, a=0.35)
# the segments of a frustum, as indices into (apex, 4 corners): 4 edges, then the rectangle
SEGMENTS = np.array([[0, 1], [0, 2], [0, 3], [0, 4], [1, 2], [2, 3], [3, 4], [4, 1]])


def frustum_corners(hfov_deg: float, width: int, height: int, display_range: float) -> np.ndarray:
    """(4, 3) corners of the image plane at depth `display_range`, in the optical frame (z
    forward, x right, y down), clockwise from the top left: square pixels, horizontal field of
    view `hfov_deg` over `width` pixels, `height` pixels high."""
    if not 0.0 < hfov_deg < 180.0:
        raise InputError("hfov_deg", hfov_deg, "a field of view in (0, 180) degrees")
    if width <= 0 or height <= 0:
        raise InputError("width/height", (width, height), "image sizes > 0 pixels")
    if not (np.isfinite(display_range) and display_range > 0):
        raise InputError("display_range", display_range, "a distance > 0 metres")
    half_w = np.tan(np.deg2rad(hfov_deg) / 2)
    half_h = half_w * height / width
    rays = np.array(
        [
            [-half_w, -half_h, 1.0],
            [half_w, -half_h, 1.0],
            [half_w, half_h, 1.0],
            [-half_w, half_h, 1.0],
        ]
    )
    return rays * display_range


def frustum_points(
    T_world_cam: np.ndarray, hfov_deg: float, width: int, height: int, display_range: float
) -> np.ndarray:
    """(16, 3) world points of a frustum's LINE_LIST (8 segments, two points each): the camera
    centre to each image corner at `display_range`, then the image rectangle.
    `T_world_cam`: (4, 4) pose of the optical frame in the world."""
    T = np.asarray(T_world_cam, float)
    if T.shape != (4, 4):
        raise InputError("T_world_cam", T.shape, "a (4, 4) pose matrix")
    local = frustum_corners(hfov_deg, width, height, display_range)
    vertices = np.vstack([T[:3, 3], local @ T[:3, :3].T + T[:3, 3]])
    return vertices[SEGMENTS.reshape(-1)]


def order_colours(n: int) -> np.ndarray:
    """(n, 3) RGB in [0, 1], from FIRST_COLOUR (the first view) to LAST_COLOUR (the last)."""
    t = np.linspace(0.0, 1.0, n)[:, None] if n > 1 else np.zeros((n, 1))
    return (1 - t) * FIRST_COLOUR + t * LAST_COLOUR


def _delete_all(ns: str, frame_id: str, stamp_ns: int) -> Marker:
    return Marker(header=codecs.header(stamp_ns, frame_id), ns=ns, action=Marker.DELETEALL)


def view_markers(
    poses: Sequence[np.ndarray],
    frame_id: str,
    stamp_ns: int,
    hfov_deg: float,
    width: int,
    height: int,
    display_range: float,
) -> MarkerArray:
    """The planned views as frustums: a DELETEALL for the namespace, then one LINE_LIST per view
    (id = its order), coloured by order."""
    markers = [_delete_all(VIEWS_NS, frame_id, stamp_ns)]
    for index, (T, rgb) in enumerate(zip(poses, order_colours(len(poses)), strict=True)):
        points = frustum_points(T, hfov_deg, width, height, display_range)
        markers.append(
            Marker(
                header=codecs.header(stamp_ns, frame_id),
                ns=VIEWS_NS,
                id=index,
                type=Marker.LINE_LIST,
                action=Marker.ADD,
                pose=Pose(orientation=Quaternion(w=1.0)),
                scale=Vector3(x=LINE_WIDTH_FRACTION * display_range),
                color=ColorRGBA(r=float(rgb[0]), g=float(rgb[1]), b=float(rgb[2]), a=1.0),
                points=[Point(x=float(x), y=float(y), z=float(z)) for x, y, z in points],
            )
        )
    return MarkerArray(markers=markers)


def hard_region_markers(
    centres: np.ndarray, sizes: np.ndarray, frame_id: str, stamp_ns: int
) -> MarkerArray:
    """Hard regions as translucent boxes: `centres` (N, 3) and `sizes` (N, 3) in metres (edge
    lengths along the world axes). A DELETEALL for the namespace first."""
    centres = np.asarray(centres, float).reshape(-1, 3)
    sizes = np.asarray(sizes, float).reshape(-1, 3)
    if len(centres) != len(sizes):
        raise InputError("sizes", len(sizes), f"one size per centre ({len(centres)})")
    if not (np.all(np.isfinite(centres)) and np.all(np.isfinite(sizes)) and np.all(sizes > 0)):
        raise InputError("centres/sizes", "non-finite or <= 0", "finite centres and sizes > 0 m")
    markers = [_delete_all(HARD_REGIONS_NS, frame_id, stamp_ns)]
    for index, (centre, size) in enumerate(zip(centres, sizes, strict=True)):
        markers.append(
            Marker(
                header=codecs.header(stamp_ns, frame_id),
                ns=HARD_REGIONS_NS,
                id=index,
                type=Marker.CUBE,
                action=Marker.ADD,
                pose=Pose(
                    position=Point(x=float(centre[0]), y=float(centre[1]), z=float(centre[2])),
                    orientation=Quaternion(w=1.0),
                ),
                scale=Vector3(x=float(size[0]), y=float(size[1]), z=float(size[2])),
                color=HARD_REGION_COLOUR,
            )
        )
    return MarkerArray(markers=markers)


def grid_messages(grid, stamp_ns: int, frame_id: str, regions_max: int) -> tuple:
    """What the planner publishes of its grid, stamped `stamp_ns` in `frame_id`: the uncertainty
    grid (sensor_msgs/PointCloud2), its hard regions, the `regions_max` largest
    (HardRegionArray), their boxes (MarkerArray), and how many hard regions there are in all."""
    cloud = grid_to_cloud(grid)
    regions = cloud_hard_regions(cloud, grid)
    shown = regions[:regions_max]
    return (
        codecs.pointcloud_to_msg(cloud, stamp_ns, frame_id),
        codecs.hard_regions_to_msg(shown, stamp_ns, frame_id),
        hard_region_markers(shown["centroid"], shown["extent"], frame_id, stamp_ns),
        len(regions),
    )


def views_path(poses: Sequence, frame_id: str, stamp_ns: int) -> msgs.Path:
    """Views (4x4 T_world_cam) as nav_msgs/Path in `frame_id`."""
    header = codecs.header(stamp_ns, frame_id)
    return msgs.Path(
        header=header,
        poses=[msgs.PoseStamped(header=header, pose=codecs.matrix_to_pose(T)) for T in poses],
    )
