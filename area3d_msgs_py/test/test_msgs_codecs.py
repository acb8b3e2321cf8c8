"""Codecs: round trips (hypothesis) and rejection of bad input."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from area3d_msgs_py import codecs, msgs
from area3d_msgs_py.errors import InputError
from area3d_msgs_py.rotations import quaternion_to_rotation


def wire(msg):
    """What a receiver sees: the message after CDR serialisation."""
    return msgs.deserialize(msgs.serialize(msg), msgs.type_name_of(msg))


shapes = st.tuples(st.integers(1, 12), st.integers(1, 12))
stamps = st.integers(0, 2**31 * 10**9 - 1)


@settings(max_examples=40, deadline=None)
@given(data=st.data(), shape=shapes, encoding=st.sampled_from(["rgb8", "bgr8"]), stamp=stamps)
def test_color_image_round_trips_in_rgb_order(data, shape, encoding, stamp):
    rgb = data.draw(hnp.arrays(np.uint8, shape + (3,)))
    msg = wire(codecs.image_to_msg(rgb, encoding, stamp, "cam"))
    assert np.array_equal(codecs.msg_to_image(msg), rgb)
    assert codecs.stamp_to_ns(msg.header.stamp) == stamp
    assert msg.header.frame_id == "cam"
    first = bytes(msg.data[:3])
    assert first == (rgb[0, 0].tobytes() if encoding == "rgb8" else rgb[0, 0, ::-1].tobytes())


@settings(max_examples=40, deadline=None)
@given(data=st.data(), shape=shapes)
def test_mono8_round_trips(data, shape):
    mono = data.draw(hnp.arrays(np.uint8, shape))
    assert np.array_equal(
        codecs.msg_to_image(wire(codecs.image_to_msg(mono, "mono8", 0, "c"))), mono
    )


@settings(max_examples=40, deadline=None)
@given(data=st.data(), shape=shapes)
def test_32fc1_depth_round_trips_bit_exact_including_nan(data, shape):
    depth = data.draw(
        hnp.arrays(np.float32, shape, elements=st.floats(0, 100, width=32) | st.just(np.nan))
    )
    out = codecs.msg_to_image(wire(codecs.image_to_msg(depth, "32FC1", 1, "c")))
    assert out.dtype == np.float32
    assert np.array_equal(out, depth, equal_nan=True)


@settings(max_examples=40, deadline=None)
@given(data=st.data(), shape=shapes)
def test_16uc1_depth_round_trips_to_the_millimetre_with_nan_as_zero(data, shape):
    depth = data.draw(
        hnp.arrays(np.float64, shape, elements=st.floats(0.001, 65.0) | st.just(np.nan))
    )
    msg = wire(codecs.image_to_msg(depth, "16UC1", 1, "c"))
    raw = np.frombuffer(bytes(msg.data), "<u2").reshape(shape)
    assert np.array_equal(raw == 0, np.isnan(depth))
    out = codecs.msg_to_image(msg)
    assert out.dtype == np.float32
    assert np.array_equal(np.isnan(out), np.isnan(depth))
    valid = ~np.isnan(depth)
    # half a millimetre of quantisation, plus the float32 rounding of the decoded metres (one
    # float32 step: 3.8 um at 32 m, more than the 1 um this allowed before; seen at 32.8155 m)
    float32_step = np.spacing(depth[valid].astype(np.float32)).astype(np.float64)
    assert np.all(np.abs(out[valid] - depth[valid]) <= 0.0005 + float32_step)


def test_big_endian_and_padded_rows_are_decoded():
    depth = np.arange(6, dtype=np.float32).reshape(2, 3) + 0.5
    rows = np.zeros((2, 16), np.uint8)
    rows[:, :12] = depth.astype(">f4").view(np.uint8).reshape(2, 12)
    msg = codecs.image_to_msg(depth, "32FC1", 0, "c")
    msg.is_bigendian, msg.step, msg.data = 1, 16, rows.reshape(-1)
    assert np.array_equal(codecs.msg_to_image(msg), depth)


point_dtypes = [
    "i1",
    "u1",
    "<i2",
    "<u2",
    "<i4",
    "<u4",
    "<f4",
    "<f8",
    ">i2",
    ">u2",
    ">i4",
    ">u4",
    ">f4",
    ">f8",
]


@st.composite
def clouds(draw):
    big = draw(st.booleans())
    kinds = draw(st.lists(st.sampled_from(point_dtypes), min_size=1, max_size=5))
    kinds = [k.replace("<", ">") if big else k.replace(">", "<") for k in kinds]
    offsets, offset = [], 0
    for k in kinds:
        size = np.dtype(k).itemsize
        offset += draw(st.integers(0, 3))  # padding before the field
        offsets.append(offset)
        offset += size
    itemsize = offset + draw(st.integers(0, 4))
    dtype = np.dtype(
        {
            "names": [f"f{i}" for i in range(len(kinds))],
            "formats": kinds,
            "offsets": offsets,
            "itemsize": itemsize,
        }
    )
    shape = draw(
        st.sampled_from(
            [(draw(st.integers(0, 30)),), (draw(st.integers(2, 4)), draw(st.integers(1, 5)))]
        )
    )
    raw = draw(hnp.arrays(np.uint8, (int(np.prod(shape)) * itemsize,)))
    return raw.view(dtype).reshape(shape)


@settings(max_examples=60, deadline=None)
@given(cloud=clouds())
def test_pointcloud_round_trips_any_field_set_padding_and_byte_order(cloud):
    msg = wire(codecs.pointcloud_to_msg(cloud, 7, "world"))
    out = codecs.msg_to_pointcloud(msg)
    assert out.shape == cloud.shape
    assert out.dtype.names == cloud.dtype.names
    for name in cloud.dtype.names:
        assert out.dtype[name] == cloud.dtype[name]
        assert np.array_equal(out[name], cloud[name], equal_nan=True)
    floats_finite = all(
        np.isfinite(cloud[n]).all() for n in cloud.dtype.names if cloud.dtype[n].kind == "f"
    )
    assert bool(msg.is_dense) == floats_finite
    assert msg.point_step == cloud.dtype.itemsize
    assert msg.height == (1 if cloud.ndim == 1 else cloud.shape[0])


def test_pointcloud_with_padded_rows_is_decoded():
    cloud = np.zeros((2, 3), dtype=[("x", "<f4"), ("i", "<u2")])
    cloud["x"] = np.arange(6).reshape(2, 3)
    msg = codecs.pointcloud_to_msg(cloud, 0, "w")
    step = msg.point_step * 3
    rows = np.zeros((2, step + 5), np.uint8)
    rows[:, :step] = np.asarray(msg.data).reshape(2, step)
    msg.row_step, msg.data = step + 5, rows.reshape(-1)
    assert np.array_equal(codecs.msg_to_pointcloud(msg)["x"], cloud["x"])


unit_quaternions = (
    hnp.arrays(np.float64, 4, elements=st.floats(-1, 1))
    .filter(lambda q: np.linalg.norm(q) > 0.1)
    .map(lambda q: q / np.linalg.norm(q))
)


@settings(max_examples=100, deadline=None)
@given(q=unit_quaternions, t=hnp.arrays(np.float64, 3, elements=st.floats(-100, 100)))
def test_pose_round_trips_and_rotation_is_orthonormal(q, t):
    T = np.eye(4)
    T[:3, :3] = quaternion_to_rotation(q)
    T[:3, 3] = t
    pose = wire(codecs.matrix_to_pose(T))
    back = codecs.pose_to_matrix(pose)
    np.testing.assert_allclose(back, T, atol=1e-9)
    q_back = np.array(
        [pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w]
    )
    assert np.allclose(q_back, q, atol=1e-9) or np.allclose(q_back, -q, atol=1e-9)
    assert q_back[3] >= 0
    np.testing.assert_allclose(
        codecs.transform_to_matrix(codecs.matrix_to_transform(T)), T, atol=1e-9
    )


def test_quaternion_convention_is_x_y_z_w_about_z():
    pose = msgs.Pose(
        position=msgs.Point(x=0.0, y=0.0, z=0.0),
        orientation=msgs.Quaternion(x=0.0, y=0.0, z=np.sin(np.pi / 4), w=np.cos(np.pi / 4)),
    )
    R = codecs.pose_to_matrix(pose)[:3, :3]
    np.testing.assert_allclose(R @ [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], atol=1e-12)


@settings(max_examples=40, deadline=None)
@given(
    f=st.floats(10, 2000),
    cx=st.floats(1, 1000),
    cy=st.floats(1, 1000),
    w=st.integers(1, 4096),
    h=st.integers(1, 4096),
    stamp=stamps,
)
def test_camera_info_round_trips_and_is_filled_like_ros(f, cx, cy, w, h, stamp):
    K = np.array([[f, 0, cx], [0, f, cy], [0, 0, 1.0]])
    msg = wire(codecs.intrinsics_to_camera_info(K, w, h, stamp, "optical"))
    K2, w2, h2 = codecs.camera_info_to_intrinsics(msg)
    np.testing.assert_array_equal(K2, K)
    assert (w2, h2) == (w, h)
    assert msg.distortion_model == "plumb_bob" and not np.any(msg.d)
    np.testing.assert_array_equal(np.asarray(msg.r).reshape(3, 3), np.eye(3))
    np.testing.assert_array_equal(np.asarray(msg.p).reshape(3, 4), np.c_[K, np.zeros(3)])
    assert codecs.stamp_to_ns(msg.header.stamp) == stamp


def test_right_camera_info_carries_the_baseline_in_tx_like_ros():
    K = np.array([[320.0, 0, 320], [0, 320.0, 240], [0, 0, 1.0]])
    msg = wire(codecs.intrinsics_to_camera_info(K, 640, 480, 1, "right", baseline=0.06))
    assert np.asarray(msg.p)[3] == pytest.approx(-320.0 * 0.06)  # Tx = -fx B
    assert codecs.camera_info_to_baseline(msg) == pytest.approx(0.06)
    left = wire(codecs.intrinsics_to_camera_info(K, 640, 480, 1, "left"))
    with pytest.raises(InputError) as err:
        codecs.camera_info_to_baseline(left)
    assert err.value.field == "p[3]"


@given(ns=stamps)
def test_stamp_round_trips(ns):
    stamp = codecs.ns_to_stamp(ns)
    assert 0 <= stamp.nanosec < 10**9
    assert codecs.stamp_to_ns(stamp) == ns


# ---- bad input -------------------------------------------------------------------------------
def test_input_error_message_names_field_value_and_expectation():
    err = InputError("encoding", "yuv422", "one of rgb8, bgr8")
    assert isinstance(err, ValueError)
    assert str(err) == "encoding: got 'yuv422', expected one of rgb8, bgr8"
    assert (err.field, err.value, err.expected) == ("encoding", "yuv422", "one of rgb8, bgr8")
    assert len(str(InputError("data", "x" * 10_000, "short"))) < 300


def raises_field(field, fn, *args):
    with pytest.raises(InputError) as info:
        fn(*args)
    assert info.value.field == field
    return info.value


def good_depth_msg():
    return codecs.image_to_msg(np.ones((2, 3), np.float32), "32FC1", 0, "c")


def test_unknown_encoding_is_rejected_both_ways():
    raises_field("encoding", codecs.image_to_msg, np.zeros((2, 2), np.uint8), "yuv422", 0, "c")
    msg = good_depth_msg()
    msg.encoding = "64FC1"
    raises_field("encoding", codecs.msg_to_image, msg)


def test_image_data_length_must_equal_height_times_step():
    msg = good_depth_msg()
    msg.data = np.asarray(msg.data)[:-1]
    err = raises_field("data", codecs.msg_to_image, msg)
    assert "24" in err.expected


def test_image_step_must_cover_a_row():
    msg = good_depth_msg()
    msg.step, msg.data = 8, np.zeros(16, np.uint8)
    raises_field("step", codecs.msg_to_image, msg)


def test_image_array_shape_and_dtype_are_checked():
    raises_field("array.shape", codecs.image_to_msg, np.zeros((2, 2), np.uint8), "rgb8", 0, "c")
    raises_field(
        "array.dtype", codecs.image_to_msg, np.zeros((2, 2, 3), np.float32), "rgb8", 0, "c"
    )


def test_pointfield_with_unknown_datatype_or_count_is_rejected_by_name():
    msg = codecs.pointcloud_to_msg(np.zeros(3, dtype=[("x", "<f4"), ("rgb", "<f4")]), 0, "w")
    msg.fields[1].datatype = 9
    assert "rgb" in raises_field("field 'rgb' datatype", codecs.msg_to_pointcloud, msg).field
    msg.fields[1].datatype, msg.fields[1].count = 7, 3
    raises_field("field 'rgb' count", codecs.msg_to_pointcloud, msg)


def test_pointcloud_with_array_or_unsupported_field_is_rejected_by_name():
    raises_field(
        "field 'n'", codecs.pointcloud_to_msg, np.zeros(2, dtype=[("n", "<f4", (3,))]), 0, "w"
    )
    raises_field("field 'id'", codecs.pointcloud_to_msg, np.zeros(2, dtype=[("id", "<u8")]), 0, "w")


def test_pointcloud_data_length_and_field_offsets_are_checked():
    msg = codecs.pointcloud_to_msg(np.zeros(3, dtype=[("x", "<f4")]), 0, "w")
    msg.data = np.zeros(11, np.uint8)
    raises_field("data", codecs.msg_to_pointcloud, msg)
    msg = codecs.pointcloud_to_msg(np.zeros(3, dtype=[("x", "<f4")]), 0, "w")
    msg.fields[0].offset = 2
    raises_field("field 'x' offset", codecs.msg_to_pointcloud, msg)


def test_non_unit_quaternion_is_rejected_naming_orientation():
    pose = msgs.Pose(
        position=msgs.Point(x=0.0, y=0.0, z=0.0),
        orientation=msgs.Quaternion(x=0.0, y=0.0, z=0.0, w=1.01),
    )
    raises_field("orientation", codecs.pose_to_matrix, pose)
    pose.orientation.w = 1.0005  # within ROS' tolerance: accepted and normalised
    np.testing.assert_allclose(codecs.pose_to_matrix(pose), np.eye(4), atol=1e-12)


def test_non_orthonormal_or_reflecting_matrix_is_rejected():
    T = np.eye(4)
    T[0, 0] = 1.1
    with pytest.raises(InputError, match="rotation"):
        codecs.matrix_to_pose(T)
    T = np.diag([1.0, 1.0, -1.0, 1.0])
    with pytest.raises(InputError, match="rotation"):
        codecs.matrix_to_pose(T)
    raises_field("T", codecs.matrix_to_pose, np.eye(3))


def test_bad_intrinsics_and_stamps_are_rejected():
    raises_field("K", codecs.intrinsics_to_camera_info, np.eye(2), 4, 4, 0, "c")
    raises_field("width", codecs.intrinsics_to_camera_info, np.eye(3), 0, 4, 0, "c")
    raises_field("stamp_ns", codecs.ns_to_stamp, -1)


def test_unknown_message_type_is_rejected():
    raises_field("type_name", msgs.get, "sensor_msgs/msg/Nope")
    raises_field("type_name", msgs.get, "not a type")


# ---- TF, the next-best-view service and hard regions -----------------------------------------
def rigid(q, t):
    T = np.eye(4)
    T[:3, :3] = quaternion_to_rotation(q)
    T[:3, 3] = t
    return T


translations = hnp.arrays(np.float64, 3, elements=st.floats(-100, 100))
rigids = st.builds(rigid, unit_quaternions, translations)
frame_names = st.text(
    alphabet=st.characters(min_codepoint=ord("a"), max_codepoint=ord("z")) | st.just("_"),
    min_size=1,
    max_size=12,
)


@settings(max_examples=60, deadline=None)
@given(edges=st.lists(st.tuples(frame_names, frame_names, stamps, rigids), min_size=0, max_size=6))
def test_tf_message_round_trips_as_parent_child_stamp_and_matrix(edges):
    msg = wire(codecs.transforms_to_tf_message(edges))
    assert msgs.type_name_of(msg) == "tf2_msgs/msg/TFMessage"
    back = codecs.tf_message_to_transforms(msg)
    assert len(back) == len(edges)
    for (parent, child, stamp, T), got in zip(edges, back, strict=True):
        assert (got.parent, got.child, got.stamp_ns) == (parent, child, stamp)
        np.testing.assert_allclose(got.T, T, atol=1e-9)


def test_a_bad_transform_in_a_tf_message_is_named_by_its_index():
    edges = [("world", "a", 1, np.eye(4)), ("a", "b", 1, np.eye(4))]
    msg = codecs.transforms_to_tf_message(edges)
    msg.transforms[1].transform.rotation.w = 2.0
    raises_field("transforms[1].transform.rotation", codecs.tf_message_to_transforms, msg)
    msg.transforms[1].transform.rotation.w = 1.0
    msg.transforms[0].transform.translation.x = float("nan")
    raises_field("transforms[0].transform.translation", codecs.tf_message_to_transforms, msg)
    raises_field("child", codecs.stamped_transform_to_msg, ("world", "", 1, np.eye(4)))


@settings(max_examples=60, deadline=None)
@given(
    count=st.integers(0, 2**32 - 1),
    mode=st.sampled_from(["", "closed_loop", "batch"]),
    current=rigids,
    stamp=stamps,
    frame=frame_names,
    request_id=st.integers(0, 2**64 - 1),
)
def test_next_best_view_request_round_trips(count, mode, current, stamp, frame, request_id):
    msg = wire(codecs.view_request_to_msg(count, current, stamp, frame, mode, request_id))
    assert msgs.type_name_of(msg) == "area3d_interfaces/srv/NextBestView_Request"
    got = codecs.msg_to_view_request(msg)
    assert (got.count, got.mode, got.stamp_ns, got.frame_id) == (count, mode, stamp, frame)
    assert got.request_id == request_id
    np.testing.assert_allclose(got.current, current, atol=1e-9)


@settings(max_examples=60, deadline=None)
@given(
    views=st.lists(rigids, min_size=0, max_size=8),
    data=st.data(),
    stamp=stamps,
    frame=frame_names,
)
def test_next_best_view_response_round_trips_views_best_first_with_their_gains(
    views, data, stamp, frame
):
    gains = data.draw(hnp.arrays(np.float32, len(views), elements=st.floats(0, 1e6, width=32)))
    Ts = np.array(views).reshape(-1, 4, 4)
    msg = wire(codecs.view_answer_to_msg(Ts, gains, stamp, frame))
    got = codecs.msg_to_view_answer(msg)
    assert got.success and got.message == ""
    assert (got.stamp_ns, got.frame_id) == (stamp, frame)
    np.testing.assert_allclose(got.views, Ts, atol=1e-9)
    np.testing.assert_array_equal(got.gains, gains)  # float32 on the wire: exact


def test_a_refused_request_carries_its_reason_and_no_view():
    msg = wire(codecs.view_refusal_to_msg("no frame yet: wait for the first capture", 5, "map"))
    got = codecs.msg_to_view_answer(msg)
    assert not got.success and got.message.startswith("no frame yet")
    assert got.views.shape == (0, 4, 4) and got.gains.shape == (0,)
    assert got.frame_id == "map"
    raises_field("message", codecs.view_refusal_to_msg, "", 5, "map")


def test_bad_next_best_view_fields_are_named():
    raises_field("mode", codecs.view_request_to_msg, 1, np.eye(4), 1, "w", "sideways")
    raises_field("count", codecs.view_request_to_msg, -1, np.eye(4), 1, "w")
    raises_field("count", codecs.view_request_to_msg, 2.5, np.eye(4), 1, "w")
    for request_id in (-1, 2**64, True, 1.0):
        raises_field("request_id", codecs.view_request_to_msg, 1, np.eye(4), 1, "w", "", request_id)
    request = codecs.view_request_to_msg(1, np.eye(4), 1, "w")
    request.current.pose.orientation.w = 3.0
    raises_field("current.pose.orientation", codecs.msg_to_view_request, request)
    request.current.pose.orientation.w, request.mode = 1.0, "Batch"
    raises_field("mode", codecs.msg_to_view_request, request)
    raises_field("gains", codecs.view_answer_to_msg, np.stack([np.eye(4)] * 2), [1.0], 1, "w")
    raises_field("gains", codecs.view_answer_to_msg, np.eye(4)[None], [np.nan], 1, "w")
    answer = codecs.view_answer_to_msg(np.stack([np.eye(4)] * 2), [2.0, 1.0], 1, "w")
    answer.views.poses[1].position.z = float("inf")
    raises_field("views.poses[1].position", codecs.msg_to_view_answer, answer)
    answer.views.poses[1].position.z = 0.0
    answer.gains = [1.0]
    raises_field("gains", codecs.msg_to_view_answer, answer)


@settings(max_examples=40, deadline=None)
@given(data=st.data(), n=st.integers(0, 10), stamp=stamps)
def test_hard_regions_round_trip(data, n, stamp):
    regions = np.zeros(n, codecs.HARD_REGION_DTYPE)
    regions["centroid"] = data.draw(hnp.arrays(np.float64, (n, 3), elements=st.floats(-50, 50)))
    regions["extent"] = data.draw(hnp.arrays(np.float64, (n, 3), elements=st.floats(0, 10)))
    regions["voxel_count"] = data.draw(hnp.arrays(np.uint32, n))
    regions["direction_count"] = data.draw(hnp.arrays(np.uint32, n))
    regions["mean_uncertainty"] = data.draw(
        hnp.arrays(np.float32, n, elements=st.floats(0, 1, width=32))
    )
    msg = wire(codecs.hard_regions_to_msg(regions, stamp, "world"))
    back = codecs.msg_to_hard_regions(msg)
    assert back.dtype == codecs.HARD_REGION_DTYPE
    for name in codecs.HARD_REGION_DTYPE.names:
        np.testing.assert_array_equal(back[name], regions[name])
    assert codecs.stamp_to_ns(msg.header.stamp) == stamp


def test_bad_hard_regions_are_refused():
    regions = np.zeros(1, codecs.HARD_REGION_DTYPE)
    regions["extent"] = -1.0
    raises_field("regions.extent", codecs.hard_regions_to_msg, regions, 1, "w")
    regions["extent"], regions["centroid"] = 1.0, np.nan
    raises_field("regions", codecs.hard_regions_to_msg, regions, 1, "w")
    raises_field("regions", codecs.hard_regions_to_msg, np.zeros(3), 1, "w")
