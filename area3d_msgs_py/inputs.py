"""What a node accepts on its inputs: the checks every subscriber runs before it trusts a message.

Another process can publish anything on a topic (a broken driver, a replay of the wrong bag, a
hostile node). Each check raises `InputError` naming the field, the value and what was expected,
so `guard.guarded` logs one line, counts it and the node keeps running. Checks run on the header
before an image's bytes are copied, so a huge image costs its transport and nothing more.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from area3d_msgs_py import codecs
from area3d_msgs_py.errors import InputError

# Larger than any camera the graph expects (12 MP stills are 4000 x 3000); an 8k x 8k image is
# refused from its header, before its 200+ MB are copied.
MAX_IMAGE_PIXELS = 4096 * 4096
# A capture stamp lies in the past of whoever receives it; this much ahead of the receiver's clock
# allows for clock skew between hosts. A stamp further ahead would move every stamp-paired buffer's
# horizon into the future and make it drop every real frame after it.
MAX_STAMP_AHEAD_S = 5.0
COLOR_ENCODINGS = ("rgb8", "bgr8")
DEPTH_ENCODINGS = ("32FC1", "16UC1")
# No RGB-D camera returns depth this far (16UC1 millimetres end at 65.5 m): a 32FC1 depth whose
# returns lie beyond it is in other units, a driver's millimetres most often.
MAX_CAMERA_DEPTH_M = 100.0
FLOAT_ENCODINGS = ("32FC1",)


def check_stamp(msg: Any, now_ns: int, max_ahead_s: float = MAX_STAMP_AHEAD_S) -> int:
    """The capture stamp of a stamped message in int ns: > 0 and at most max_ahead_s ahead of now."""
    stamp = codecs.stamp_to_ns(msg.header.stamp)
    if stamp <= 0:
        raise InputError("header.stamp", stamp, "a capture stamp > 0 ns since the epoch")
    if stamp > now_ns + int(max_ahead_s * 1e9):
        raise InputError(
            "header.stamp",
            stamp,
            f"a capture stamp at most {max_ahead_s:g} s ahead of this node's clock ({now_ns} ns)",
        )
    return stamp


def check_frame_id(msg: Any, expected: str | None = None) -> str:
    """The header's frame_id: non-empty, and equal to `expected` when given."""
    frame_id = msg.header.frame_id
    if not frame_id:
        raise InputError("header.frame_id", frame_id, "the frame the data is expressed in")
    if expected is not None and frame_id != expected:
        raise InputError("header.frame_id", frame_id, f"{expected!r}")
    return frame_id


def check_image_header(
    msg: Any,
    encodings: Sequence[str],
    size: tuple[int, int] | None = None,
    max_pixels: int = MAX_IMAGE_PIXELS,
) -> None:
    """Encoding, size and pixel count of a sensor_msgs/Image from its header alone.

    size: (width, height) the image must have (the camera info's), or None.
    """
    if msg.encoding not in encodings:
        raise InputError("encoding", msg.encoding, f"one of {', '.join(encodings)} on this topic")
    width, height = int(msg.width), int(msg.height)
    if width <= 0 or height <= 0:
        raise InputError("width x height", f"{width}x{height}", "a non-empty image")
    if width * height > max_pixels:
        raise InputError("width x height", f"{width}x{height}", f"at most {max_pixels} pixels")
    if size is not None and (width, height) != tuple(size):
        raise InputError("width x height", f"{width}x{height}", f"the camera's {size[0]}x{size[1]}")


def decode_image(
    msg: Any,
    encodings: Sequence[str],
    size: tuple[int, int] | None = None,
    max_pixels: int = MAX_IMAGE_PIXELS,
) -> np.ndarray:
    """`codecs.msg_to_image` after `check_image_header` (step and data length checked there)."""
    check_image_header(msg, encodings, size, max_pixels)
    return codecs.msg_to_image(msg)


def decode_camera_depth(msg: Any, size: tuple[int, int] | None = None) -> np.ndarray:
    """A camera's depth image in metres (32FC1 metres, REP 117, or 16UC1 millimetres); a 32FC1
    image whose median return lies beyond MAX_CAMERA_DEPTH_M is refused as one in other units."""
    depth = decode_image(msg, DEPTH_ENCODINGS, size)
    if msg.encoding == "32FC1":
        sample = depth.ravel()[::16]  # every frame: a sample tells the units
        returns = sample[np.isfinite(sample) & (sample > 0)]
        median = float(np.median(returns)) if returns.size else 0.0
        if median > MAX_CAMERA_DEPTH_M:
            raise InputError(
                "data",
                f"32FC1 depth with a median return of {median:.4g}",
                f"metres (REP 117), returns within {MAX_CAMERA_DEPTH_M:g}; a driver's "
                "millimetres come as 16UC1",
            )
    return depth


def _range_ignoring_nan(image: np.ndarray) -> tuple[float, float]:
    """(min, max) over the non-NaN values (+-inf included); (nan, nan) when all are NaN. One pass
    each, no copy: this runs on every frame."""
    return float(np.fmin.reduce(image, axis=None)), float(np.fmax.reduce(image, axis=None))


def check_unit_range(image: np.ndarray, field: str) -> np.ndarray:
    """A per-pixel map in [0, 1] with NaN = no estimate; +-inf or values outside are refused."""
    lo, hi = _range_ignoring_nan(image)
    if lo < 0.0 or hi > 1.0:  # False for NaN: an all-NaN map is accepted
        bad = int(np.count_nonzero((image < 0.0) | (image > 1.0)))
        raise InputError(
            field,
            f"{bad} pixels outside [0, 1] (min {lo:g}, max {hi:g})",
            "values in [0, 1], NaN = no estimate",
        )
    return image


def check_depth_values(depth: np.ndarray, field: str = "depth") -> np.ndarray:
    """Metric depth computed by the graph (REP 117): metres > 0, NaN = no estimate, +Inf = no
    return within range; -Inf or <= 0 refused."""
    lo, _ = _range_ignoring_nan(depth)
    if lo <= 0.0:  # -inf included; False for NaN
        bad = int(np.count_nonzero(depth <= 0.0))
        raise InputError(
            field,
            f"{bad} pixels -inf or <= 0",
            "metres > 0, NaN = no estimate, +inf = no return within range",
        )
    return depth


def decode_camera_info(msg: Any, max_pixels: int = MAX_IMAGE_PIXELS) -> tuple[np.ndarray, int, int]:
    """`codecs.camera_info_to_intrinsics` for a camera no larger than max_pixels, of full-size
    images: binning or a region of interest (which describe another image than the one sent
    at the calibration's size) refused by field."""
    for field in ("binning_x", "binning_y"):
        if getattr(msg, field, 0) > 1:
            raise InputError(field, getattr(msg, field), "0 or 1: full-resolution images")
    roi = getattr(msg, "roi", None)
    if roi is not None and (roi.width or roi.height or roi.x_offset or roi.y_offset):
        raise InputError(
            "roi", f"{roi.width}x{roi.height}+{roi.x_offset}+{roi.y_offset}", "all 0: full images"
        )
    K, width, height = codecs.camera_info_to_intrinsics(msg)
    if width * height > max_pixels:
        raise InputError("width x height", f"{width}x{height}", f"at most {max_pixels} pixels")
    return K, width, height


PINHOLE_MODELS = ("", "plumb_bob", "rational_polynomial")


def distortion_note(msg: Any) -> str | None:
    """What to say of a camera info that describes lens distortion (non-zero `d`, or a model
    that is no pinhole): the graph projects with `k` as a pinhole camera and never undistorts, so
    its images must be rectified; None when there is none."""
    model = str(msg.distortion_model)
    d = [float(v) for v in msg.d]
    if model in PINHOLE_MODELS and not any(abs(v) > 1e-9 for v in d):
        return None
    return (
        f"camera_info: distortion_model {model!r} with d {[round(v, 4) for v in d]}: the graph "
        "projects with k as a pinhole camera and does not undistort: give it rectified images "
        "(image_proc) whose intrinsics are k, or the surfaces land off their place"
    )


def decode_frame_part(key: str, msg: Any) -> np.ndarray:
    """A part of a frame from perception or semantics, decoded and checked: its frame id, its
    encoding and its values: "color" rgb8 or bgr8, "depth" 32FC1 depth (`check_depth_values`),
    any other key 32FC1 values in [0, 1] named by the key (confidence, semantic uncertainty)."""
    check_frame_id(msg)
    if key == "color":
        return decode_image(msg, COLOR_ENCODINGS)
    image = decode_image(msg, FLOAT_ENCODINGS)
    return check_depth_values(image) if key == "depth" else check_unit_range(image, key)
