"""Rotations (area3d_msgs_py.rotations) as specifications, against scipy: quaternion to matrix and
back (w >= 0), slerp, the angle between two rotations; and the refusal of quaternions off unit
length."""

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation, Slerp

from area3d_msgs_py.errors import InputError
from area3d_msgs_py.rotations import (
    QUATERNION_NORM2_TOLERANCE,
    check_quaternion,
    invert,
    matrix,
    quaternion_to_rotation,
    rotation_angle,
    rotation_to_quaternion,
    slerp,
)


@st.composite
def quaternions(draw):
    q = np.array(draw(st.tuples(*[st.floats(-1, 1, allow_nan=False)] * 4)))
    assume(np.linalg.norm(q) > 0.1)
    return q / np.linalg.norm(q)


def scipy_matrix(q: np.ndarray) -> np.ndarray:
    return Rotation.from_quat(q).as_matrix()


@settings(max_examples=100, deadline=None)
@given(q=quaternions())
def test_a_quaternion_becomes_the_rotation_matrix_scipy_makes_of_it(q):
    R = quaternion_to_rotation(q)
    np.testing.assert_allclose(R, scipy_matrix(q), atol=1e-12)
    np.testing.assert_allclose(quaternion_to_rotation(-q), R, atol=1e-12)  # one rotation
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)


@settings(max_examples=100, deadline=None)
@given(q=quaternions())
def test_a_rotation_matrix_becomes_its_quaternion_with_w_not_negative(q):
    got = rotation_to_quaternion(scipy_matrix(q))
    assert got.shape == (4,) and got[3] >= 0
    assert np.linalg.norm(got) == pytest.approx(1.0, abs=1e-12)
    expected = q if q[3] >= 0 else -q
    if abs(q[3]) > 1e-9:  # w = 0: q and -q both have w >= 0, either is right
        np.testing.assert_allclose(got, expected, atol=1e-9)
    np.testing.assert_allclose(scipy_matrix(got), scipy_matrix(q), atol=1e-9)


@settings(max_examples=100, deadline=None)
@given(a=quaternions(), b=quaternions(), u=st.floats(0, 1))
def test_slerp_agrees_with_scipy(a, b, u):
    assume(abs(np.dot(a, b)) > 1e-3)  # not half a turn apart: two geodesics, either is right
    expected = Slerp([0.0, 1.0], Rotation.from_quat([a, b]))([u]).as_matrix()[0]
    got = slerp(a, b, u)
    assert np.linalg.norm(got) == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_allclose(quaternion_to_rotation(got), expected, atol=1e-6)


@settings(max_examples=50, deadline=None)
@given(a=quaternions(), b=quaternions())
def test_slerp_ends_at_its_two_rotations(a, b):
    np.testing.assert_allclose(quaternion_to_rotation(slerp(a, b, 0.0)), scipy_matrix(a), atol=1e-9)
    np.testing.assert_allclose(quaternion_to_rotation(slerp(a, b, 1.0)), scipy_matrix(b), atol=1e-6)


@settings(max_examples=100, deadline=None)
@given(a=quaternions(), b=quaternions())
def test_the_angle_between_two_rotations_agrees_with_scipy(a, b):
    expected = (Rotation.from_quat(a).inv() * Rotation.from_quat(b)).magnitude()
    assert rotation_angle(a, b) == pytest.approx(expected, abs=1e-6)
    assert rotation_angle(a, -a) == pytest.approx(0.0, abs=1e-6)  # q and -q: one rotation


@settings(max_examples=50, deadline=None)
@given(q=quaternions(), t=st.tuples(*[st.floats(-10, 10, allow_nan=False)] * 3))
def test_a_transform_and_its_inverse_compose_to_the_identity(q, t):
    T = matrix(np.array(t), q)
    np.testing.assert_allclose(T[:3, :3], scipy_matrix(q), atol=1e-12)
    np.testing.assert_allclose(T[:3, 3], t)
    np.testing.assert_allclose(invert(T) @ T, np.eye(4), atol=1e-9)


def test_a_quaternion_is_normalised_within_the_tolerance_and_refused_beyond_it():
    slightly_long = np.array([0.0, 0.0, 0.0, 1.0 + 0.5 * QUATERNION_NORM2_TOLERANCE / 2])
    np.testing.assert_allclose(check_quaternion(slightly_long, "pose.orientation"), [0, 0, 0, 1])
    # a norm of 0.997 is taken as tf2 and RViz take it (|0.997^2 - 1| = 0.006); 0.99 is not (0.0199)
    short = check_quaternion([0.0, 0.0, 0.6 * 0.997, 0.8 * 0.997], "pose.orientation")
    np.testing.assert_allclose(short, [0, 0, 0.6, 0.8], atol=1e-12)
    for bad in ([0, 0, 0.6 * 0.99, 0.8 * 0.99], [0.0, 0.0, 0.0, 2.0], [0.0, 0.0, 0.0, 0.0],
                [np.nan, 0, 0, 1], [0.0, 1.0]):  # fmt: skip
        with pytest.raises(InputError) as refused:
            check_quaternion(bad, "pose.orientation")
        assert refused.value.field == "pose.orientation"
        message = str(refused.value)
        assert message.startswith("pose.orientation: got ") and "unit quaternion" in message
    with pytest.raises(InputError, match=r"got \[0\.0, 0\.0, 0\.0, 2\.0\]"):
        check_quaternion([0.0, 0.0, 0.0, 2.0], "pose.orientation")
