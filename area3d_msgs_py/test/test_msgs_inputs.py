"""Boundary checks on incoming messages: each refusal names the field, the value and what was expected."""

from __future__ import annotations

import numpy as np
import pytest

from area3d_msgs_py import codecs, inputs, msgs
from area3d_msgs_py.errors import InputError
from area3d_msgs_py.guard import Rejections, guarded

NOW = 1_800_000_000 * 1_000_000_000


def _image(width: int = 4, height: int = 3, encoding: str = "32FC1") -> msgs.Image:
    array = (
        np.ones((height, width, 3), np.uint8)
        if encoding == "rgb8"
        else np.ones((height, width), np.float32)
    )
    return codecs.image_to_msg(array, encoding, NOW, "cam")


def test_an_image_is_refused_from_its_header_before_its_bytes_are_read():
    huge = _image()
    huge.width, huge.height = 8192, 8192  # data does not match either: the header is enough
    with pytest.raises(InputError, match=r"width x height: got '8192x8192', expected at most"):
        inputs.decode_image(huge, inputs.DEPTH_ENCODINGS)
    with pytest.raises(InputError, match=r"encoding: got 'rgb8', expected one of 32FC1, 16UC1"):
        inputs.decode_image(_image(encoding="rgb8"), inputs.DEPTH_ENCODINGS)
    empty = _image()
    empty.width = empty.height = empty.step = 0
    empty.data = b""
    with pytest.raises(InputError, match="non-empty"):
        inputs.decode_image(empty, inputs.DEPTH_ENCODINGS)
    with pytest.raises(InputError, match="the camera's 640x480"):
        inputs.decode_image(_image(), inputs.DEPTH_ENCODINGS, size=(640, 480))
    assert inputs.decode_image(_image(), inputs.DEPTH_ENCODINGS, size=(4, 3)).shape == (3, 4)


def test_stamps_must_be_positive_and_not_ahead_of_the_clock_frame_ids_as_expected():
    msg = msgs.PoseStamped(header=codecs.header(NOW + 6 * 10**9, "map"))
    with pytest.raises(InputError, match="header.stamp: got .* at most 5 s ahead"):
        inputs.check_stamp(msg, NOW)
    assert inputs.check_stamp(msg, NOW, max_ahead_s=10.0) == NOW + 6 * 10**9
    msg.header.stamp.sec = -1
    with pytest.raises(InputError, match="> 0 ns"):
        inputs.check_stamp(msg, NOW)
    with pytest.raises(InputError, match="header.frame_id: got 'map', expected 'world'"):
        inputs.check_frame_id(msg, "world")


def test_maps_in_unit_range_allow_nan_but_not_inf_or_values_outside():
    ok = np.array([[0.0, 1.0, np.nan]], np.float32)
    assert inputs.check_unit_range(ok, "confidence") is ok
    for bad in (np.inf, -np.inf, 1.5, -0.1):
        with pytest.raises(InputError, match="confidence: got '1 pixels outside"):
            inputs.check_unit_range(np.array([[0.5, bad]], np.float32), "confidence")
    for bad in (-np.inf, 0.0, -1.0):
        with pytest.raises(InputError, match="depth: got '1 pixels -inf or <= 0'"):
            inputs.check_depth_values(np.array([[0.5, bad, np.nan]], np.float32))
    rep117 = np.array([[0.5, np.inf, np.nan]], np.float32)  # no return within range, no estimate
    assert inputs.check_depth_values(rep117) is rep117


class _Node:
    """A node whose logger keeps its lines (warnings and errors alike) in `lines`."""

    def __init__(self, lines: list[str]) -> None:
        self.lines = lines

    def get_logger(self):
        lines = self.lines

        class Log:
            warning = error = staticmethod(lines.append)

        return Log()


def test_guarded_counts_rejections_by_topic_and_field_and_logs_one_line():
    lines = []

    rejections = Rejections()
    callback = guarded(
        _Node(lines), lambda m: inputs.check_frame_id(m, "world"), "pose", rejections
    )
    callback(msgs.PoseStamped(header=codecs.header(7, "map")))
    callback(msgs.PoseStamped(header=codecs.header(8, "world")))
    assert rejections.snapshot() == {
        "total": 1,
        "by_topic": {"pose": 1},
        "by_field": {"header.frame_id": 1},
    }
    assert lines == ["pose at stamp 7: rejected: header.frame_id: got 'map', expected 'world'"]


def test_a_refusal_repeated_at_the_publishers_rate_is_logged_once_a_period_and_counted_each_time():
    lines, now = [], [100.0]
    rejections = Rejections(clock=lambda: now[0])

    def check(msg):
        inputs.check_stamp(msg, NOW)
        inputs.check_frame_id(msg, "world")

    callback = guarded(_Node(lines), check, "odom", rejections)
    for stamp in range(1, 51):  # 50 Hz for a second, all refused
        callback(msgs.PoseStamped(header=codecs.header(stamp, "map")))
        now[0] += 0.02
    callback(msgs.PoseStamped(header=codecs.header(0, "map")))  # another field: logged at once
    assert rejections.snapshot()["total"] == 51
    assert len(lines) == 2 and lines[0] == (
        "odom at stamp 1: rejected: header.frame_id: got 'map', expected 'world'"
    )
    assert lines[1].startswith("odom at stamp 0: rejected: header.stamp: got 0")
    now[0] += 1.0
    callback(msgs.PoseStamped(header=codecs.header(52, "map")))
    assert lines[-1] == (
        "odom at stamp 52: rejected: header.frame_id: got 'map', expected 'world' "
        "(49 more of header.frame_id refused since, not logged)"
    )


def test_a_callback_of_a_node_being_destroyed_ends_quietly_and_counts_nothing():
    """rclpy raises InvalidHandle when a callback still running at shutdown publishes, or when
    counting a rejection resets the status timer of a node being destroyed: neither is an input's
    fault, and neither may escape into the executor's thread."""
    from rclpy.exceptions import InvalidHandle

    lines = []

    def destroyed():
        raise InvalidHandle("cannot use Destroyable because destruction was requested")

    def publish(_msg):
        destroyed()

    rejections = Rejections()
    assert guarded(_Node(lines), publish, "depth", rejections)(_image()) is None
    assert rejections.total == 0 and lines == []
    # a real bad input whose count then finds the status timer destroyed
    counted = Rejections(on_count=destroyed)
    check = guarded(_Node(lines), lambda m: inputs.check_frame_id(m, "world"), "pose", counted)
    assert check(msgs.PoseStamped(header=codecs.header(7, "map"))) is None
    assert counted.total == 1 and len(lines) == 1
    # anything else is still an error, logged with its traceback and counted
    failing = guarded(_Node(lines), lambda m: 1 / 0, "depth", rejections)
    assert failing(_image()) is None
    assert rejections.snapshot()["by_field"] == {"exception": 1}
    assert "ZeroDivisionError" in lines[-1]


def test_a_cameras_depth_in_millimetres_sent_as_32fc1_metres_is_refused_naming_the_units():
    metres = np.full((48, 64), 1.2, np.float32)
    metres[:, :8] = np.nan  # no return there
    size = (64, 48)
    ok = inputs.decode_camera_depth(codecs.image_to_msg(metres, "32FC1", NOW, "cam"), size)
    np.testing.assert_array_equal(ok, metres)
    millimetres = (np.nan_to_num(metres) * 1000).astype(np.uint16)  # 16UC1 is millimetres
    as_16 = inputs.decode_camera_depth(codecs.image_to_msg(millimetres, "16UC1", NOW, "c"), size)
    np.testing.assert_allclose(as_16[:, 8:], 1.2, atol=1e-6)
    with pytest.raises(InputError) as wrong:
        inputs.decode_camera_depth(codecs.image_to_msg(metres * 1000, "32FC1", NOW, "cam"), size)
    assert wrong.value.field == "data"
    assert "median return of 1200" in str(wrong.value) and "16UC1" in str(wrong.value)
    # a camera that sees nothing (every pixel NaN or +inf) is no units error
    nothing = np.full((48, 64), np.inf, np.float32)
    inputs.decode_camera_depth(codecs.image_to_msg(nothing, "32FC1", NOW, "cam"), size)
