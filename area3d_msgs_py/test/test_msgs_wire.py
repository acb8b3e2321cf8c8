"""Wire format: our DDS writer sends exactly the CDR that ROS 2 (rosbags / rmw_cyclonedds) uses."""

import numpy as np
import pytest

from area3d_msgs_py import codecs, dds_types, msgs

T = np.array([[0.0, -1.0, 0.0, 1.5], [1.0, 0.0, 0.0, -2.0], [0.0, 0.0, 1.0, 0.25], [0, 0, 0, 1.0]])


def examples():
    head = codecs.header(1_700_000_000_123_456_789, "camera_optical_frame")
    pose = codecs.matrix_to_pose(T)
    stamped = msgs.PoseStamped(header=head, pose=pose)
    tf = msgs.TransformStamped(
        header=head, child_frame_id="camera_link", transform=codecs.matrix_to_transform(T)
    )
    cloud = np.zeros(5, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("uncertainty", "<f4")])
    cloud["x"] = np.arange(5)
    cloud["uncertainty"] = np.nan
    image = codecs.image_to_msg(np.arange(12, dtype=np.uint8).reshape(2, 2, 3), "rgb8", 5, "cam")
    return {
        "std_msgs/msg/Header": head,
        "std_msgs/msg/String": msgs.String(data="regions: é ünïcode"),
        "builtin_interfaces/msg/Time": codecs.ns_to_stamp(3_000_000_007),
        "geometry_msgs/msg/Pose": pose,
        "geometry_msgs/msg/PoseStamped": stamped,
        "geometry_msgs/msg/Transform": tf.transform,
        "geometry_msgs/msg/TransformStamped": tf,
        "sensor_msgs/msg/Image": image,
        "sensor_msgs/msg/CameraInfo": codecs.intrinsics_to_camera_info(
            np.array([[320.0, 0, 320], [0, 320, 240], [0, 0, 1]]), 640, 480, 5, "cam"
        ),
        "sensor_msgs/msg/PointCloud2": codecs.pointcloud_to_msg(cloud, 9, "world"),
        "sensor_msgs/msg/PointField": msgs.PointField(name="x", offset=4, datatype=7, count=1),
        "nav_msgs/msg/Path": msgs.Path(header=head, poses=[stamped, stamped]),
        "nav_msgs/srv/GetPlan_Request": msgs.GetPlan_Request(
            start=stamped, goal=stamped, tolerance=0.5
        ),
        "nav_msgs/srv/GetPlan_Response": msgs.GetPlan_Response(
            plan=msgs.Path(header=head, poses=[stamped])
        ),
        "tf2_msgs/msg/TFMessage": msgs.TFMessage(transforms=[tf, tf]),
    }


EXAMPLES = examples()


def cyclone_padded(data: bytes) -> bytes:
    """DataWriter.write pads the serialised sample to a multiple of 4 bytes."""
    return data.ljust((len(data) + 3) & ~3, b"\0")


@pytest.mark.parametrize("type_name", sorted(EXAMPLES))
def test_writer_bytes_equal_rosbags_cdr_and_cyclone_own_serialisation(type_name):
    msg = EXAMPLES[type_name]
    expected = bytes(msgs.typestore.serialize_cdr(msg, type_name))
    assert expected[:4] == b"\x00\x01\x00\x00"  # CDR little endian encapsulation, as ROS 2 sends
    wire_cls = dds_types.wire_type(type_name)
    sent = wire_cls.serialize(
        dds_types.wire_sample(wire_cls, msgs.serialize(msg)), use_version_2=None
    )
    assert sent == expected
    # cyclonedds-python's element-wise serialisation of the generated struct: the declared DDS type
    # describes exactly these bytes.
    own = dds_types.to_idl_sample(msg, type_name).serialize()
    assert cyclone_padded(own) == cyclone_padded(expected)
    assert msgs.serialize(msgs.deserialize(sent, type_name), type_name) == expected


def test_service_request_carries_the_rmw_cyclonedds_header_before_the_body():
    request = EXAMPLES["nav_msgs/srv/GetPlan_Request"]
    guid, seq = 0x0123456789ABCDEF, 42
    data = dds_types.add_request_header(msgs.serialize(request), guid, seq)
    own = dds_types.to_idl_sample(request, request_header=(guid, seq)).serialize()
    assert data == own
    assert data[4:12] == guid.to_bytes(8, "little") and data[12:20] == seq.to_bytes(8, "little")
    assert dds_types.split_request_header(data) == (guid, seq, msgs.serialize(request))


def test_dds_names_follow_ros2_conventions():
    assert dds_types.dds_type_name("sensor_msgs/msg/Image") == "sensor_msgs::msg::dds_::Image_"
    assert (
        dds_types.dds_type_name("nav_msgs/srv/GetPlan_Request")
        == "nav_msgs::srv::dds_::GetPlan_Request_"
    )
    assert dds_types.dds_topic_name("/area3d/camera/pose") == "rt/area3d/camera/pose"
    assert dds_types.dds_service_topics("/area3d/planner/next_best_view") == (
        "rq/area3d/planner/next_best_viewRequest",
        "rr/area3d/planner/next_best_viewReply",
    )
    assert dds_types.wire_type(
        "nav_msgs/srv/GetPlan_Response", True
    ).__idl__.idl_transformed_typename == ("nav_msgs::srv::dds_::GetPlan_Response_")
