"""numpy <-> ROS 2 message codecs (on the generated rclpy message classes), one module per message
family, used as one namespace (`codecs.image_to_msg`, `codecs.pose_to_matrix`, ...):

- ``header``: stamps and std_msgs/Header
- ``images``: sensor_msgs/Image
- ``clouds``: sensor_msgs/PointCloud2
- ``meshes``: coloured triangle meshes as visualization_msgs/Marker (TRIANGLE_LIST), encoded
  straight to CDR bytes for ``Publisher.publish``
- ``poses``: Pose / Transform / PoseArray / TransformStamped, TF (tf2_msgs/TFMessage)
- ``camera_info``: sensor_msgs/CameraInfo
- ``views``: the NextBestView service
- ``hard_regions``: area3d_interfaces/HardRegionArray

Conventions: images are (H, W, 3) uint8 in rgb order, (H, W) uint8 for mono8 and (H, W) float32
metres for depth (NaN = no return); poses are 4x4 float64 homogeneous matrices; stamps are int
nanoseconds since the Unix epoch.
"""

from area3d_msgs_py.codecs.camera_info import (
    camera_info_to_baseline,
    camera_info_to_intrinsics,
    intrinsics_to_camera_info,
)
from area3d_msgs_py.codecs.clouds import msg_to_pointcloud, pointcloud_dtype, pointcloud_to_msg
from area3d_msgs_py.codecs.hard_regions import hard_regions_to_msg, msg_to_hard_regions
from area3d_msgs_py.codecs.header import header, ns_to_stamp, stamp_to_ns
from area3d_msgs_py.codecs.images import image_to_msg, msg_to_image
from area3d_msgs_py.codecs.meshes import marker_to_mesh, mesh_marker_cdr
from area3d_msgs_py.codecs.poses import (
    matrices_to_pose_array,
    matrix_to_pose,
    matrix_to_transform,
    msg_to_stamped_transform,
    pose_array_to_matrices,
    pose_to_matrix,
    stamped_transform_to_msg,
    tf_message_to_transforms,
    transform_to_matrix,
    transforms_to_tf_message,
)
from area3d_msgs_py.codecs.views import (
    VIEW_MODES,
    ViewAnswer,
    ViewRequest,
    msg_to_view_answer,
    msg_to_view_request,
    view_answer_to_msg,
    view_refusal_to_msg,
    view_request_to_msg,
)
from area3d_msgs_py.hard_region import HARD_REGION_DTYPE

__all__ = [
    "HARD_REGION_DTYPE",
    "VIEW_MODES",
    "ViewAnswer",
    "ViewRequest",
    "camera_info_to_baseline",
    "camera_info_to_intrinsics",
    "hard_regions_to_msg",
    "header",
    "image_to_msg",
    "intrinsics_to_camera_info",
    "marker_to_mesh",
    "matrices_to_pose_array",
    "matrix_to_pose",
    "matrix_to_transform",
    "mesh_marker_cdr",
    "msg_to_hard_regions",
    "msg_to_image",
    "msg_to_pointcloud",
    "msg_to_stamped_transform",
    "msg_to_view_answer",
    "msg_to_view_request",
    "ns_to_stamp",
    "pointcloud_dtype",
    "pointcloud_to_msg",
    "pose_array_to_matrices",
    "pose_to_matrix",
    "stamp_to_ns",
    "stamped_transform_to_msg",
    "tf_message_to_transforms",
    "transform_to_matrix",
    "transforms_to_tf_message",
    "view_answer_to_msg",
    "view_refusal_to_msg",
    "view_request_to_msg",
]
