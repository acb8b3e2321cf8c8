"""The transform buffer (area3d_msgs_py.transforms): lookups, interpolation, tolerance, history
and the rejection of bad samples, as specifications."""

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation, Slerp

from area3d_msgs_py import transforms
from area3d_msgs_py.errors import InputError
from area3d_msgs_py.rotations import matrix, slerp
from area3d_msgs_py.transforms import (
    ODOMETRY_FIELDS,
    LookupFailure,
    PoseStream,
    TransformBuffer,
)

S = transforms.NS_PER_S
T0 = 1_700_000_000 * S  # a plausible stamp

coords = st.floats(-10, 10, allow_nan=False)
translations = st.tuples(coords, coords, coords).map(np.array)


@st.composite
def quaternions(draw):
    q = np.array(draw(st.tuples(*[st.floats(-1, 1, allow_nan=False)] * 4)))
    assume(np.linalg.norm(q) > 0.1)
    return q / np.linalg.norm(q)


poses = st.tuples(translations, quaternions())


def angle(R0: np.ndarray, R1: np.ndarray) -> float:
    return float(np.linalg.norm(Rotation.from_matrix(R0.T @ R1).as_rotvec()))


# lookups as specifications -------------------------------------------------------------------
@settings(max_examples=60, deadline=None)
@given(samples=st.lists(poses, min_size=1, max_size=8), gaps=st.lists(st.integers(1, 10**9)))
def test_a_lookup_at_a_samples_stamp_is_that_sample(samples, gaps):
    buffer = TransformBuffer()
    stamps = T0 + np.cumsum([0] + (gaps + [S] * len(samples))[: len(samples) - 1])
    for stamp, (t, q) in zip(stamps, samples, strict=True):
        assert buffer.add("odom", "base_link", int(stamp), t, q)
    for stamp, (t, q) in zip(stamps, samples, strict=True):
        np.testing.assert_allclose(
            buffer.lookup("odom", "base_link", int(stamp)), matrix(t, q), atol=1e-12
        )


@settings(max_examples=80, deadline=None)
@given(a=poses, b=poses, span=st.integers(2, 10**9), data=st.data())
def test_interpolation_lies_on_the_geodesic_between_the_two_samples(a, b, span, data):
    m = data.draw(st.integers(1, span - 1))
    u = m / span
    buffer = TransformBuffer()
    buffer.add("map", "camera", T0, *a)
    buffer.add("map", "camera", T0 + span, *b)
    T = buffer.lookup("map", "camera", T0 + m)
    Ta, Tb = matrix(*a), matrix(*b)
    np.testing.assert_allclose(T[:3, 3], (1 - u) * a[0] + u * b[0], atol=1e-9)
    theta = angle(Ta[:3, :3], Tb[:3, :3])
    assert angle(Ta[:3, :3], T[:3, :3]) == pytest.approx(u * theta, abs=1e-6)
    assert angle(T[:3, :3], Tb[:3, :3]) == pytest.approx((1 - u) * theta, abs=1e-6)
    np.testing.assert_allclose(T[3], [0, 0, 0, 1])
    if theta < np.pi - 1e-3:  # half a turn has two geodesics; scipy may take the other
        expected = Slerp([0.0, 1.0], Rotation.from_quat([a[1], b[1]]))([u]).as_matrix()[0]
        np.testing.assert_allclose(T[:3, :3], expected, atol=1e-6)


@st.composite
def chains(draw):
    """A chain world -> f1 -> ... -> fn; each edge static or dynamic, with its expected 4x4 at
    the lookup stamp T0 + S (a dynamic edge has samples at T0 and T0 + 2 S)."""
    n = draw(st.integers(1, 4))
    edges = []
    for i in range(n):
        parent, child = ("world" if i == 0 else f"f{i}"), f"f{i + 1}"
        if draw(st.booleans()):
            t, q = draw(poses)
            edges.append((parent, child, "static", [(0, t, q)], matrix(t, q)))
        else:
            (ta, qa), (tb, qb) = draw(poses), draw(poses)
            middle = matrix((ta + tb) / 2, slerp(qa, qb, 0.5))
            edges.append((parent, child, "dynamic", [(T0, ta, qa), (T0 + 2 * S, tb, qb)], middle))
    return edges


@settings(max_examples=60, deadline=None)
@given(chain=chains(), branch=poses)
def test_chaining_equals_the_matrix_product(chain, branch):
    buffer = TransformBuffer()
    for parent, child, kind, samples, _ in chain:
        for stamp, t, q in samples:
            buffer.add(parent, child, stamp, t, q, static=kind == "static")
    buffer.add("world", "other", 0, *branch, static=True)
    leaf = chain[-1][1]
    product = np.eye(4)
    for *_, T in chain:
        product = product @ T
    np.testing.assert_allclose(buffer.lookup("world", leaf, T0 + S), product, atol=1e-9)
    np.testing.assert_allclose(
        buffer.lookup(leaf, "world", T0 + S), np.linalg.inv(product), atol=1e-6
    )
    # two branches meet at their common ancestor
    np.testing.assert_allclose(
        buffer.lookup("other", leaf, T0 + S),
        np.linalg.inv(matrix(*branch)) @ product,
        atol=1e-6,
    )
    np.testing.assert_allclose(buffer.lookup(leaf, leaf, T0 + S), np.eye(4))


@settings(max_examples=30, deadline=None)
@given(samples=st.lists(poses, min_size=2, max_size=40), seed=st.integers(0, 2**32 - 1))
def test_samples_arriving_out_of_order_give_the_same_lookups(samples, seed):
    stamps = [T0 + i * S // 10 for i in range(len(samples))]
    in_order, shuffled = TransformBuffer(), TransformBuffer()
    for stamp, (t, q) in zip(stamps, samples, strict=True):
        in_order.add("odom", "base_link", stamp, t, q)
    for i in np.random.default_rng(seed).permutation(len(samples)):
        shuffled.add("odom", "base_link", stamps[i], *samples[i])
    for stamp in np.linspace(stamps[0], stamps[-1], 25).astype(np.int64):
        np.testing.assert_allclose(
            shuffled.lookup("odom", "base_link", int(stamp)),
            in_order.lookup("odom", "base_link", int(stamp)),
            atol=1e-12,
        )


def test_static_edges_hold_at_every_stamp():
    buffer = TransformBuffer()
    q = Rotation.from_euler("xyz", [0.1, 0.2, 0.3]).as_quat()
    buffer.add("base_link", "camera_link", 123, [0.1, 0.0, 0.3], q, static=True)
    for stamp in (1, T0, T0 + 10**6 * S):
        np.testing.assert_allclose(
            buffer.lookup("base_link", "camera_link", stamp), matrix(np.array([0.1, 0, 0.3]), q)
        )
    # a later static sample replaces it
    buffer.add("base_link", "camera_link", 0, [0.2, 0.0, 0.3], q, static=True)
    assert buffer.lookup("base_link", "camera_link", T0)[0, 3] == pytest.approx(0.2)


# tolerance and the four causes of a failed lookup ----------------------------------------------
def test_a_stamp_within_the_tolerance_outside_the_samples_takes_the_nearest_sample():
    buffer = TransformBuffer(tolerance_s=0.05)
    identity = [0.0, 0.0, 0.0, 1.0]
    buffer.add("odom", "base_link", T0, [1.0, 0, 0], identity)
    buffer.add("odom", "base_link", T0 + S // 10, [2.0, 0, 0], identity)
    assert buffer.lookup("odom", "base_link", T0 + S // 10 + S // 20)[0, 3] == 2.0  # clamped
    assert buffer.lookup("odom", "base_link", T0 - S // 20)[0, 3] == 1.0
    with pytest.raises(LookupFailure) as late:
        buffer.lookup("odom", "base_link", T0 + S // 10 + S // 20 + 1)
    assert late.value.cause == LookupFailure.IN_FUTURE
    assert "'odom' -> 'base_link'" in str(late.value) and "not arrived" in str(late.value)
    with pytest.raises(LookupFailure) as early:
        buffer.lookup("odom", "base_link", T0 - S // 20 - 1)
    assert early.value.cause == LookupFailure.TOO_OLD


def test_without_tolerance_there_is_no_extrapolation_even_by_a_nanosecond():
    buffer = TransformBuffer()
    buffer.add("odom", "base_link", T0, [0.0, 0, 0], [0, 0, 0, 1.0])
    assert buffer.lookup("odom", "base_link", T0)[0, 3] == 0.0  # one sample: at its stamp only
    for stamp, cause in ((T0 + 1, LookupFailure.IN_FUTURE), (T0 - 1, LookupFailure.TOO_OLD)):
        with pytest.raises(LookupFailure) as failure:
            buffer.lookup("odom", "base_link", stamp)
        assert failure.value.cause == cause


def test_a_frame_never_seen_and_two_unconnected_trees_are_told_apart():
    buffer = TransformBuffer()
    buffer.add("map", "odom", 0, [0.0, 0, 0], [0, 0, 0, 1.0], static=True)
    buffer.add("base_link", "camera", 0, [0.0, 0, 0], [0, 0, 0, 1.0], static=True)
    with pytest.raises(LookupFailure) as missing:
        buffer.lookup("map", "camera_optical_frame", T0)
    assert missing.value.cause == LookupFailure.NO_TRANSFORM
    assert "'camera_optical_frame'" in str(missing.value)
    with pytest.raises(LookupFailure) as apart:
        buffer.lookup("map", "camera", T0)
    assert apart.value.cause == LookupFailure.DISCONNECTED
    assert "'map'" in str(apart.value) and "'base_link'" in str(apart.value)
    assert set(LookupFailure.CAUSES) == {
        missing.value.cause,
        apart.value.cause,
        LookupFailure.TOO_OLD,
        LookupFailure.IN_FUTURE,
        LookupFailure.GAP,
    }


def test_a_stamp_in_a_pause_of_the_transforms_longer_than_the_limit_is_a_gap():
    """An odometry outage: between two samples 3 s apart the body may have moved in any way;
    tf2 would interpolate across it. Within the limit, and with no limit, it interpolates."""
    buffer = TransformBuffer(max_interval_s=1.0)
    for k in range(3):  # 50 Hz, then a pause of 3 s, then 50 Hz again, 1 m further on
        buffer.add("odom", "base_link", T0 + k * S // 50, [0.0, 0, 0], [0, 0, 0, 1.0])
    resumed = T0 + 2 * S // 50 + 3 * S
    for k in range(3):
        buffer.add("odom", "base_link", resumed + k * S // 50, [1.0, 0, 0], [0, 0, 0, 1.0])
    assert buffer.lookup("odom", "base_link", T0 + S // 100)[0, 3] == 0.0  # 20 ms apart: kept
    with pytest.raises(LookupFailure) as pause:
        buffer.lookup("odom", "base_link", T0 + 2 * S)
    assert pause.value.cause == LookupFailure.GAP
    assert "3.000 s apart" in str(pause.value) and "max_interval_s 1" in str(pause.value)
    assert buffer.lookup("odom", "base_link", resumed + S // 100)[0, 3] == 1.0
    unlimited = TransformBuffer()
    unlimited.add("odom", "base_link", T0, [0.0, 0, 0], [0, 0, 0, 1.0])
    unlimited.add("odom", "base_link", T0 + 3 * S, [3.0, 0, 0], [0, 0, 0, 1.0])
    assert unlimited.lookup("odom", "base_link", T0 + S)[0, 3] == pytest.approx(1.0)


def test_history_is_bounded_and_older_stamps_are_too_old():
    buffer = TransformBuffer(history_s=1.0)
    for i in range(1000):  # 10 s at 100 Hz
        buffer.add("odom", "base_link", T0 + i * S // 100, [i * 0.001, 0, 0], [0, 0, 0, 1.0])
    history = buffer._edges["base_link"].history
    assert len(history) == 101  # the newest and 1 s before it
    assert len(history.stamps) <= 256  # the arrays do not grow with the stream
    newest = T0 + 999 * S // 100
    assert buffer.lookup("odom", "base_link", newest - S)[0, 3] == pytest.approx(0.899)
    with pytest.raises(LookupFailure) as old:
        buffer.lookup("odom", "base_link", newest - S - 1)
    assert old.value.cause == LookupFailure.TOO_OLD


def test_a_repeated_stamp_is_ignored_and_the_first_sample_kept():
    buffer = TransformBuffer()
    assert buffer.add("odom", "base_link", T0, [1.0, 0, 0], [0, 0, 0, 1.0])
    assert not buffer.add("odom", "base_link", T0, [5.0, 0, 0], [0, 0, 0, 1.0])
    assert buffer.lookup("odom", "base_link", T0)[0, 3] == 1.0


# rejections name the field ----------------------------------------------------------------------
GOOD = {"parent": "odom", "child": "base_link", "stamp_ns": T0, "translation": [0.0, 0, 0]}
UNIT = [0.0, 0.0, 0.0, 1.0]


@pytest.mark.parametrize(
    ("change", "field", "says"),
    [
        ({"rotation": [0.0, 0.0, 0.0, 2.0]}, "transform.rotation", "unit quaternion"),
        ({"rotation": [0.0, 0.0, 0.0, 0.0]}, "transform.rotation", "unit quaternion"),
        ({"rotation": [np.nan, 0.0, 0.0, 1.0]}, "transform.rotation", "unit quaternion"),
        ({"translation": [np.inf, 0, 0]}, "transform.translation", "finite"),
        ({"translation": [0.0, np.nan, 0]}, "transform.translation", "finite"),
        ({"stamp_ns": 0}, "header.stamp", "> 0"),
        ({"stamp_ns": T0 + 6 * S}, "header.stamp", "5 s ahead"),
        ({"parent": ""}, "header.frame_id", "parent frame"),
        ({"child": ""}, "child_frame_id", "child frame"),
        ({"child": "odom"}, "child_frame_id", "other than its parent"),
    ],
)
def test_a_bad_sample_is_refused_naming_its_field(change, field, says):
    buffer = TransformBuffer()
    sample = {**GOOD, "rotation": UNIT, **change}
    with pytest.raises(InputError) as refused:
        buffer.add(**sample, now_ns=T0)
    assert refused.value.field == field
    assert says in str(refused.value)
    assert buffer.frames() == set()  # nothing kept


def test_a_second_parent_a_loop_and_a_static_dynamic_mix_are_refused():
    buffer = TransformBuffer()
    buffer.add("map", "odom", T0, [0.0, 0, 0], UNIT)
    buffer.add("odom", "base_link", T0, [0.0, 0, 0], UNIT)
    with pytest.raises(InputError) as second:
        buffer.add("world", "base_link", T0, [0.0, 0, 0], UNIT)
    assert second.value.field == "header.frame_id" and "'odom'" in str(second.value)
    with pytest.raises(InputError) as loop:
        buffer.add("base_link", "map", T0, [0.0, 0, 0], UNIT)
    assert loop.value.field == "child_frame_id" and "no loops" in str(loop.value)
    with pytest.raises(InputError) as mixed:
        buffer.add("odom", "base_link", T0, [0.0, 0, 0], UNIT, static=True)
    assert mixed.value.field == "child_frame_id" and "/tf_static" in str(mixed.value)


def test_a_jump_faster_than_the_limits_is_refused_and_the_edge_recovers_after_its_history():
    buffer = TransformBuffer(history_s=2.0, max_linear_speed=2.0, max_angular_speed=3.0)
    buffer.add("odom", "base_link", T0, [0.0, 0, 0], UNIT)
    assert buffer.add("odom", "base_link", T0 + S // 10, [0.15, 0, 0], UNIT)  # 1.5 m/s
    with pytest.raises(InputError) as linear:
        buffer.add("odom", "base_link", T0 + 2 * S // 10, [0.5, 0, 0], UNIT)  # 3.5 m/s
    assert linear.value.field == "transform.translation"
    assert "max_linear_speed 2 m/s" in str(linear.value) and "3.5 m/s" in str(linear.value)
    quarter_turn = Rotation.from_euler("z", 0.5).as_quat()  # 0.5 rad in 0.1 s: 5 rad/s
    with pytest.raises(InputError) as angular:
        buffer.add("odom", "base_link", T0 + 2 * S // 10, [0.15, 0, 0], quarter_turn)
    assert angular.value.field == "transform.rotation"
    assert "max_angular_speed 3 rad/s" in str(angular.value) and "5 rad/s" in str(angular.value)
    # the refused samples were not kept: the newest is still the one at T0 + 0.1 s
    with pytest.raises(LookupFailure):
        buffer.lookup("odom", "base_link", T0 + 2 * S // 10)
    # a relocation more than history_s after the last sample kept starts the edge afresh
    assert buffer.add("odom", "base_link", T0 + 3 * S, [50.0, 0, 0], UNIT)
    assert buffer.lookup("odom", "base_link", T0 + 3 * S)[0, 3] == 50.0


def test_bad_limits_are_refused_naming_the_parameter():
    for name, value in (("tolerance_s", -1.0), ("history_s", 0.0), ("max_linear_speed", np.nan)):
        with pytest.raises(InputError) as refused:
            TransformBuffer(**{name: value})
        assert refused.value.field == name


# the pose stream ---------------------------------------------------------------------------------
def test_a_pose_stream_interpolates_odometry_and_mounts_the_camera():
    mount = matrix(
        np.array([0.2, 0.0, 0.5]), Rotation.from_euler("xyz", [-90, 0, -90], True).as_quat()
    )
    stream = PoseStream("odom", "base_link", mount, fields=ODOMETRY_FIELDS)
    q0 = Rotation.from_euler("z", 0.0).as_quat()
    q1 = Rotation.from_euler("z", 0.2).as_quat()
    stream.add(T0, [0.0, 0, 0], q0, "odom", "base_link")
    stream.add(T0 + S // 50, [0.02, 0, 0], q1, "odom", "base_link")  # 50 Hz odometry
    stamp = T0 + S // 200  # an image a quarter of the way
    expected_body = matrix(np.array([0.005, 0, 0]), Rotation.from_euler("z", 0.05).as_quat())
    np.testing.assert_allclose(stream.pose_at(stamp), expected_body @ mount, atol=1e-9)


def test_a_pose_stream_names_the_odometry_fields_it_refuses():
    stream = PoseStream("odom", "base_link", fields=ODOMETRY_FIELDS)
    with pytest.raises(LookupFailure) as empty:
        stream.pose_at(T0)
    assert empty.value.cause == LookupFailure.NO_TRANSFORM and "'odom'" in str(empty.value)
    cases = [
        (("map", "base_link"), {}, "header.frame_id"),
        (("odom", "base_footprint"), {}, "child_frame_id"),
        (("odom", "base_link"), {"orientation": [0, 0, 0, 2.0]}, "pose.pose.orientation"),
        (("odom", "base_link"), {"position": [np.nan, 0, 0]}, "pose.pose.position"),
    ]
    for (frame, child), change, field in cases:
        sample = {"position": [0.0, 0, 0], "orientation": UNIT, **change}
        with pytest.raises(InputError) as refused:
            stream.add(T0, sample["position"], sample["orientation"], frame, child)
        assert refused.value.field == field


def test_a_pose_stamped_stream_is_the_camera_pose_itself():
    stream = PoseStream("world")
    q = Rotation.from_euler("xyz", [0.3, -0.2, 1.0]).as_quat()
    stream.add(T0, [1.0, 2.0, 3.0], q, "world")
    np.testing.assert_allclose(stream.pose_at(T0), matrix(np.array([1.0, 2, 3]), q), atol=1e-12)
    with pytest.raises(InputError) as refused:
        PoseStream("world", T_body_camera=np.diag([1.0, 1.0, -1.0, 1.0]))
    assert refused.value.field == "T_body_camera"
