"""sensor_msgs/Image <-> numpy: colour images (H, W, 3) uint8 in rgb order, (H, W) uint8 for mono8,
depth (H, W) float32 metres (NaN = no return)."""

from __future__ import annotations

from typing import Any

import numpy as np

from area3d_msgs_py import msgs
from area3d_msgs_py.codecs.header import data_bytes, header
from area3d_msgs_py.errors import InputError

# REP 118 / sensor_msgs image_encodings: bytes per pixel and the numpy element type.
IMAGE_ENCODINGS: dict[str, tuple[int, int, str]] = {
    # encoding: (channels, bytes per channel, numpy kind)
    "rgb8": (3, 1, "u1"),
    "bgr8": (3, 1, "u1"),
    "mono8": (1, 1, "u1"),
    "16UC1": (1, 2, "u2"),
    "32FC1": (1, 4, "f4"),
}
# 16UC1 depth is millimetres (REP 118), 0 = no return.
DEPTH_MM_PER_M = 1000.0
UINT16_MAX = 65535


def image_to_msg(array: np.ndarray, encoding: str, stamp_ns: int, frame_id: str) -> Any:
    """sensor_msgs/Image from an array.

    array: rgb8/bgr8 (H, W, 3) uint8 in rgb order (bgr8 swaps on the wire); mono8 (H, W) uint8;
    32FC1 (H, W) float metres; 16UC1 (H, W) float metres (stored as millimetres, NaN/<=0 -> 0) or
    uint16 millimetres as is.
    """
    if encoding not in IMAGE_ENCODINGS:
        raise InputError("encoding", encoding, f"one of {sorted(IMAGE_ENCODINGS)}")
    channels, _, kind = IMAGE_ENCODINGS[encoding]
    array = np.asarray(array)
    expected_shape = "(H, W, 3)" if channels == 3 else "(H, W)"
    if array.ndim != (3 if channels == 3 else 2) or (channels == 3 and array.shape[2] != 3):
        raise InputError("array.shape", array.shape, f"{expected_shape} for {encoding}")
    if array.shape[0] == 0 or array.shape[1] == 0:
        raise InputError("array.shape", array.shape, "a non-empty image")
    if encoding in ("rgb8", "bgr8", "mono8"):
        if array.dtype != np.uint8:
            raise InputError("array.dtype", str(array.dtype), f"uint8 for {encoding}")
        pixels = array[..., ::-1] if encoding == "bgr8" else array
    elif encoding == "32FC1":
        if array.dtype.kind != "f":
            raise InputError("array.dtype", str(array.dtype), "a float dtype (metres) for 32FC1")
        pixels = array.astype("<f4", copy=False)
    else:
        if array.dtype == np.uint16:
            pixels = array.astype("<u2", copy=False)
        elif array.dtype.kind == "f":
            mm = np.rint(np.nan_to_num(array, nan=0.0, posinf=0.0, neginf=0.0) * DEPTH_MM_PER_M)
            pixels = np.clip(mm, 0, UINT16_MAX).astype("<u2")
        else:
            raise InputError(
                "array.dtype", str(array.dtype), "float metres or uint16 millimetres for 16UC1"
            )
    height, width = array.shape[:2]
    data = np.ascontiguousarray(pixels).tobytes()
    return msgs.Image(
        header=header(stamp_ns, frame_id),
        height=int(height),
        width=int(width),
        encoding=encoding,
        is_bigendian=0,
        step=width * IMAGE_ENCODINGS[encoding][0] * IMAGE_ENCODINGS[encoding][1],
        data=data,
    )


def msg_to_image(msg: Any) -> np.ndarray:
    """Array from sensor_msgs/Image (own memory, writable).

    rgb8/bgr8 -> (H, W, 3) uint8 rgb order; mono8 -> (H, W) uint8; 32FC1 -> (H, W) float32 metres;
    16UC1 -> (H, W) float32 metres from millimetres with 0 -> NaN. Row padding (step) and
    big-endian data are handled.
    """
    encoding = msg.encoding
    if encoding not in IMAGE_ENCODINGS:
        raise InputError("encoding", encoding, f"one of {sorted(IMAGE_ENCODINGS)}")
    channels, size, kind = IMAGE_ENCODINGS[encoding]
    height, width, step = int(msg.height), int(msg.width), int(msg.step)
    row_bytes = width * channels * size
    if step < row_bytes:
        raise InputError("step", step, f">= width * bytes per pixel = {row_bytes} for {encoding}")
    data = data_bytes(msg.data)
    if data.size != height * step:
        raise InputError("data", f"{data.size} bytes", f"height * step = {height * step} bytes")
    order = ">" if msg.is_bigendian and size > 1 else "<"
    rows = data.reshape(height, step)[:, :row_bytes].copy()
    pixels = rows.view(order + kind).reshape((height, width, channels))
    if encoding == "bgr8":
        return np.ascontiguousarray(pixels[..., ::-1])
    if encoding == "rgb8":
        return pixels
    if encoding == "mono8":
        return pixels[..., 0].copy()
    if encoding == "32FC1":
        return pixels[..., 0].astype(np.float32)
    metres = pixels[..., 0].astype(np.float32) / np.float32(DEPTH_MM_PER_M)
    metres[pixels[..., 0] == 0] = np.nan
    return metres
