"""Camera frustums and hard regions as markers: the apex at the camera centre, the corners on the
camera's optical frustum, colours by order, and the messages RViz and Foxglove draw."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from visualization_msgs.msg import Marker

from area3d_msgs_py.camera import intrinsics
from area3d_msgs_py.errors import InputError
from area3d_planner.markers import (
    FIRST_COLOUR,
    HARD_REGIONS_NS,
    LAST_COLOUR,
    VIEWS_NS,
    frustum_points,
    hard_region_markers,
    order_colours,
    view_markers,
)


def _rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    axis = axis / np.linalg.norm(axis)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


poses = st.builds(
    lambda axis, angle, t: np.block([[_rotation(np.array(axis), angle), np.c_[t]], [0, 0, 0, 1]]),
    st.tuples(*[st.floats(0.1, 1.0)] * 3),
    st.floats(-np.pi, np.pi),
    st.lists(st.floats(-5, 5), min_size=3, max_size=3),
)


@settings(max_examples=60, deadline=None)
@given(
    T=poses,
    hfov=st.floats(20.0, 150.0),
    size=st.sampled_from([(640, 480), (320, 240), (100, 300)]),
    depth=st.floats(0.05, 5.0),
)
def test_the_apex_is_the_camera_centre_and_the_corners_lie_on_the_optical_frustum(
    T, hfov, size, depth
):
    width, height = size
    points = frustum_points(T, hfov, width, height, depth).reshape(8, 2, 3)
    # the first four segments start at the camera centre
    np.testing.assert_allclose(points[:4, 0], np.tile(T[:3, 3], (4, 1)), atol=1e-9)
    corners = points[:4, 1]
    # the corners, back in the optical frame, project onto the image's corners at the range
    local = (corners - T[:3, 3]) @ T[:3, :3]
    np.testing.assert_allclose(local[:, 2], depth, rtol=1e-9)
    pixels = local @ intrinsics(width, height, hfov).T
    pixels = pixels[:, :2] / pixels[:, 2:]
    expected = [[0, 0], [width, 0], [width, height], [0, height]]
    np.testing.assert_allclose(pixels, expected, atol=1e-6 * max(width, height))
    # the rectangle joins the corners in order
    rectangle = points[4:]
    np.testing.assert_allclose(rectangle[:, 0], corners, atol=1e-9)
    np.testing.assert_allclose(rectangle[:, 1], np.roll(corners, -1, axis=0), atol=1e-9)


def test_colours_run_from_the_first_to_the_last_view():
    colours = order_colours(5)
    np.testing.assert_allclose(colours[0], FIRST_COLOUR)
    np.testing.assert_allclose(colours[-1], LAST_COLOUR)
    steps = np.linalg.norm(np.diff(colours, axis=0), axis=1)
    np.testing.assert_allclose(steps, steps[0])  # evenly spaced, so the order can be read
    np.testing.assert_allclose(order_colours(1)[0], FIRST_COLOUR)


def test_view_markers_clear_the_last_plan_then_draw_one_frustum_per_view_in_order():
    T0, T1 = np.eye(4), np.eye(4)
    T1[:3, 3] = [1.0, 2.0, 3.0]
    array = view_markers([T0, T1], "map", 5_000_000_000, 90.0, 640, 480, 0.5)
    clear, first, second = array.markers
    assert clear.action == Marker.DELETEALL and clear.ns == VIEWS_NS
    for index, marker in enumerate((first, second)):
        assert (marker.ns, marker.id, marker.type) == (VIEWS_NS, index, Marker.LINE_LIST)
        assert marker.header.frame_id == "map" and marker.header.stamp.sec == 5
        assert len(marker.points) == 16 and marker.color.a == 1.0
        assert marker.scale.x > 0
    assert (second.points[0].x, second.points[0].y, second.points[0].z) == (1.0, 2.0, 3.0)
    # 90 degrees over 640 x 480 at 0.5 m: the top-left corner is (-0.5, -0.375, 0.5)
    corner = first.points[1]
    np.testing.assert_allclose([corner.x, corner.y, corner.z], [-0.5, -0.375, 0.5])
    assert (first.color.r, first.color.g, first.color.b) != (
        second.color.r,
        second.color.g,
        second.color.b,
    )


def test_an_empty_plan_only_clears_the_views():
    (clear,) = view_markers([], "world", 0, 90.0, 640, 480, 0.5).markers
    assert clear.action == Marker.DELETEALL


def test_hard_regions_are_boxes_at_their_centres_with_their_sizes():
    array = hard_region_markers([[0.1, 0.2, 0.3]], [[0.05, 0.1, 0.2]], "world", 0)
    clear, box = array.markers
    assert clear.action == Marker.DELETEALL and clear.ns == HARD_REGIONS_NS
    assert box.type == Marker.CUBE and box.ns == HARD_REGIONS_NS and box.color.a < 1
    assert (box.pose.position.x, box.pose.position.y, box.pose.position.z) == (0.1, 0.2, 0.3)
    assert (box.scale.x, box.scale.y, box.scale.z) == (0.05, 0.1, 0.2)


@pytest.mark.parametrize(
    ("call", "field"),
    [
        (lambda: frustum_points(np.eye(4), 180.0, 640, 480, 1.0), "hfov_deg"),
        (lambda: frustum_points(np.eye(4), 90.0, 0, 480, 1.0), "width/height"),
        (lambda: frustum_points(np.eye(4), 90.0, 640, 480, 0.0), "display_range"),
        (lambda: frustum_points(np.eye(3), 90.0, 640, 480, 1.0), "T_world_cam"),
        (lambda: hard_region_markers([[0, 0, 0]], [[0.1, 0, 0.1]], "world", 0), "centres/sizes"),
        (lambda: hard_region_markers([[0, 0, 0]], np.zeros((2, 3)), "world", 0), "sizes"),
    ],
)
def test_bad_geometry_is_refused_naming_the_field(call, field):
    with pytest.raises(InputError) as err:
        call()
    assert err.value.field == field
