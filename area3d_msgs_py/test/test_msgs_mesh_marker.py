"""Mesh markers (codecs.mesh_marker_cdr): the hand-written CDR against rclpy's own serialisation
of the same Marker built the slow way, and the rejection of bad input."""

import numpy as np
import pytest
from geometry_msgs.msg import Point
from rclpy.serialization import deserialize_message, serialize_message
from std_msgs.msg import ColorRGBA
from visualization_msgs.msg import Marker

from area3d_msgs_py import codecs
from area3d_msgs_py.errors import InputError

S = 1_000_000_000
T0 = 1_700_000_000 * S + 123_456_789  # a plausible stamp with nanoseconds


def f32(x) -> float:
    """The float32 a ROS float32 field holds after the wire."""
    return float(np.float32(x))


def slow_marker(vertices, triangles, colours, stamp_ns, frame_id, ns="reconstruction", mid=0):
    """The same Marker built from rclpy message classes (float32 fields already rounded, so it
    equals its own round trip)."""
    m = Marker()
    m.header.stamp.sec, m.header.stamp.nanosec = divmod(stamp_ns, S)
    m.header.frame_id = frame_id
    m.ns = ns
    m.id = mid
    m.type = Marker.TRIANGLE_LIST
    m.action = Marker.ADD
    m.pose.orientation.w = 1.0
    m.scale.x = m.scale.y = m.scale.z = 1.0
    m.color = ColorRGBA(r=f32(0.7), g=f32(0.7), b=f32(0.7), a=1.0)
    corners = np.asarray(triangles, dtype=int).reshape(-1)
    m.points = [
        Point(x=float(x), y=float(y), z=float(z)) for x, y, z in np.asarray(vertices)[corners]
    ]
    if colours is not None:
        m.colors = [
            ColorRGBA(r=f32(r), g=f32(g), b=f32(b), a=1.0)
            for r, g, b in np.asarray(colours)[corners]
        ]
    return m


def random_mesh(rng, n_vertices, n_triangles, coloured=True):
    vertices = rng.uniform(-20, 20, (n_vertices, 3))
    triangles = rng.integers(0, max(n_vertices, 1), (n_triangles, 3))
    colours = rng.uniform(0, 1, (n_vertices, 3)) if coloured else None
    return vertices, triangles, colours


def assert_same_as_rclpy(data: bytes, slow: Marker) -> None:
    """Same message, same bytes. rmw_fastrtps leaves alignment padding uninitialised (it varies
    from call to call) while ours is zero, so bytes may differ only where ours is zero; a real
    field byte that differed would also change the deserialised message."""
    ref = serialize_message(slow)
    assert len(data) == len(ref)
    ours, theirs = np.frombuffer(data, np.uint8), np.frombuffer(ref, np.uint8)
    assert not ours[ours != theirs].any()
    assert deserialize_message(data, Marker) == slow
    assert deserialize_message(ref, Marker) == slow


@pytest.mark.parametrize("coloured", [True, False])
@pytest.mark.parametrize("ns", ["", "n", "abc", "reconstruction"])
@pytest.mark.parametrize("frame_id", ["m", "ma", "map", "odom", "world", "cämera"])
def test_bytes_match_rclpy_for_every_string_padding(frame_id, ns, coloured):
    rng = np.random.default_rng(len(frame_id) * 7 + len(ns))
    vertices, triangles, colours = random_mesh(rng, 6, 3, coloured)
    data = codecs.mesh_marker_cdr(vertices, triangles, colours, T0, frame_id, ns, marker_id=-4)
    assert data[:4] == b"\x00\x01\x00\x00"  # CDR little endian
    assert_same_as_rclpy(data, slow_marker(vertices, triangles, colours, T0, frame_id, ns, -4))


def test_bytes_match_rclpy_for_a_larger_mesh_and_extreme_fields():
    rng = np.random.default_rng(0)
    vertices, triangles, colours = random_mesh(rng, 500, 1000)
    colours[0] = (0.0, 1.0, 0.0)  # both ends of the range
    triangles[0] = (0, 0, 499)
    stamp = (2**31 - 1) * S + S - 1  # the last representable stamp
    data = codecs.mesh_marker_cdr(
        vertices.astype(np.float32),
        triangles.astype(np.uint16),
        colours,
        stamp,
        "w",
        "s",
        2**31 - 1,
    )
    slow = slow_marker(vertices.astype(np.float32), triangles, colours, stamp, "w", "s", 2**31 - 1)
    assert_same_as_rclpy(data, slow)


def test_small_mesh_keeps_triangle_order_and_every_field():
    vertices = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0.5]], dtype=float)
    triangles = np.array([[0, 1, 2], [2, 3, 0]])
    colours = np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1], [0.5, 0.25, 0.125]])
    m = deserialize_message(
        codecs.mesh_marker_cdr(vertices, triangles, colours, T0, "map", "mesh", 7), Marker
    )
    assert (m.header.stamp.sec, m.header.stamp.nanosec) == (1_700_000_000, 123_456_789)
    assert (m.header.frame_id, m.ns, m.id) == ("map", "mesh", 7)
    assert (m.type, m.action) == (Marker.TRIANGLE_LIST, Marker.ADD)
    p, q = m.pose.position, m.pose.orientation
    assert (p.x, p.y, p.z, q.x, q.y, q.z, q.w) == (0, 0, 0, 0, 0, 0, 1)
    assert (m.scale.x, m.scale.y, m.scale.z) == (1, 1, 1)
    assert (m.color.r, m.color.g, m.color.b, m.color.a) == (f32(0.7), f32(0.7), f32(0.7), 1.0)
    assert (m.lifetime.sec, m.lifetime.nanosec, m.frame_locked) == (0, 0, False)
    corners = [0, 1, 2, 2, 3, 0]
    assert [(pt.x, pt.y, pt.z) for pt in m.points] == [tuple(vertices[i]) for i in corners]
    assert [(c.r, c.g, c.b, c.a) for c in m.colors] == [(*colours[i], 1.0) for i in corners]
    assert (m.texture_resource, m.text, m.mesh_resource, m.mesh_file.filename) == ("",) * 4
    assert m.texture == type(m.texture)()
    assert len(m.uv_coordinates) == len(m.mesh_file.data) == 0
    assert m.mesh_use_embedded_materials is False


def test_mesh_without_colours_is_plain_grey():
    vertices = np.eye(3)
    m = deserialize_message(codecs.mesh_marker_cdr(vertices, [[0, 1, 2]], None, 0, "map"), Marker)
    assert len(m.points) == 3 and len(m.colors) == 0
    assert (m.color.r, m.color.a) == (f32(0.7), 1.0)
    assert m.ns == "reconstruction" and m.id == 0
    points, colours = codecs.marker_to_mesh(m)
    assert np.array_equal(points, vertices)
    assert colours.shape == (0, 3) and colours.dtype == np.float32


@pytest.mark.parametrize("n_vertices", [0, 4])
@pytest.mark.parametrize("coloured", [True, False])
def test_empty_mesh(n_vertices, coloured):
    vertices = np.zeros((n_vertices, 3))
    colours = np.full((n_vertices, 3), 0.5) if coloured else None
    triangles = np.zeros((0, 3))  # float dtype is fine when empty
    data = codecs.mesh_marker_cdr(vertices, triangles, colours, T0, "odom")
    assert_same_as_rclpy(data, slow_marker(vertices, triangles, colours, T0, "odom"))
    points, rgb = codecs.marker_to_mesh(deserialize_message(data, Marker))
    assert points.shape == rgb.shape == (0, 3)
    assert (points.dtype, rgb.dtype) == (np.float64, np.float32)


def test_marker_to_mesh_gives_back_corners_and_colours():
    rng = np.random.default_rng(3)
    vertices, triangles, colours = random_mesh(rng, 40, 60)
    data = codecs.mesh_marker_cdr(vertices, triangles, colours, T0, "map")
    points, rgb = codecs.marker_to_mesh(deserialize_message(data, Marker))
    corners = triangles.reshape(-1)
    assert points.dtype == np.float64 and np.array_equal(points, vertices[corners])
    assert rgb.dtype == np.float32 and np.array_equal(rgb, colours[corners].astype(np.float32))


def test_marker_to_mesh_rejects_other_markers():
    m = slow_marker(np.eye(3), [[0, 1, 2]], np.eye(3), 0, "map")
    m.type = Marker.LINE_LIST
    with pytest.raises(InputError) as err:
        codecs.marker_to_mesh(m)
    assert err.value.field == "type"
    m.type = Marker.TRIANGLE_LIST
    m.points = m.points[:2]
    with pytest.raises(InputError) as err:
        codecs.marker_to_mesh(m)
    assert err.value.field == "points"
    m.points = m.points + [Point()]
    m.colors = m.colors[:1]
    with pytest.raises(InputError) as err:
        codecs.marker_to_mesh(m)
    assert err.value.field == "colors"


GOOD = dict(
    vertices=np.eye(3),
    triangles=np.array([[0, 1, 2]]),
    colours=np.full((3, 3), 0.5),
    stamp_ns=T0,
    frame_id="map",
)


@pytest.mark.parametrize(
    "field, value",
    [
        ("vertices", np.zeros((3, 2))),
        ("vertices", np.zeros(9)),
        ("vertices", np.array([[0, 0, np.nan], [1, 0, 0], [0, 1, 0]])),
        ("vertices", np.array([[0, 0, np.inf], [1, 0, 0], [0, 1, 0]])),
        ("vertices", np.array([["a", "b", "c"]] * 3)),
        ("triangles", np.array([[0, 1]])),
        ("triangles", np.array([[0.0, 1.0, 2.0]])),
        ("triangles", np.array([[0, 1, 3]])),
        ("triangles", np.array([[-1, 1, 2]])),
        ("colours", np.full((2, 3), 0.5)),
        ("colours", np.full((3, 4), 0.5)),
        ("colours", np.full((3, 3), 1.5)),
        ("colours", np.full((3, 3), -0.1)),
        ("colours", np.full((3, 3), np.nan)),
        ("stamp_ns", -1),
        ("stamp_ns", 2**31 * S),
        ("frame_id", 3),
        ("frame_id", "ma\x00p"),
        ("ns", None),
        ("marker_id", 2**31),
        ("marker_id", 1.0),
    ],
)
def test_bad_input_is_rejected_naming_the_field(field, value):
    with pytest.raises(InputError) as err:
        codecs.mesh_marker_cdr(**{**GOOD, field: value})
    assert err.value.field == field
