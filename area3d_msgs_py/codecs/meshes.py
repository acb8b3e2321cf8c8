"""Coloured triangle meshes <-> visualization_msgs/Marker (TRIANGLE_LIST), which RViz and Foxglove
draw.

A 100k-triangle mesh is 300k points: building that many Point and ColorRGBA objects in Python
and serialising them takes seconds, so ``mesh_marker_cdr`` writes the Marker's CDR bytes
directly with numpy. ``Publisher.publish`` accepts those bytes as an already-serialised message.
"""

from __future__ import annotations

import struct
from typing import Any

import numpy as np

from area3d_msgs_py.codecs.header import ns_to_stamp
from area3d_msgs_py.errors import InputError

TRIANGLE_LIST = 11  # visualization_msgs/Marker.TRIANGLE_LIST
ADD = 0  # visualization_msgs/Marker.ADD
# RGBA of `color`. Alpha 1: RViz multiplies each per-vertex alpha by this one.
GREY = (0.7, 0.7, 0.7, 1.0)

# CDR little endian, options 0: what rmw_fastrtps writes before the message.
_ENCAPSULATION = b"\x00\x01\x00\x00"
_INT32 = np.iinfo(np.int32)


class _CdrWriter:
    """Little-endian CDR writer; alignment counts from the byte after the encapsulation header.

    Padding is written as zeros (rmw_fastrtps leaves it uninitialised; readers ignore it).
    """

    def __init__(self) -> None:
        self.parts: list[Any] = [_ENCAPSULATION]
        self.pos = 0

    def align(self, size: int) -> None:
        pad = -self.pos % size
        if pad:
            self.raw(b"\x00" * pad)

    def raw(self, data: Any) -> None:
        """Bytes or a C-contiguous array, already aligned by the caller."""
        self.parts.append(data)
        self.pos += memoryview(data).nbytes

    def pack(self, fmt: str, *values: Any) -> None:
        """Scalars of one type (fmt such as ``"3d"``), aligned to that type's size."""
        self.align(struct.calcsize(fmt[-1]))
        self.raw(struct.pack("<" + fmt, *values))

    def string(self, text: str) -> None:
        data = text.encode() + b"\x00"
        self.pack("I", len(data))  # length counts the terminating NUL
        self.raw(data)

    def empty_sequence(self) -> None:
        self.pack("I", 0)

    def header(self, sec: int, nanosec: int, frame_id: str) -> None:
        """std_msgs/Header."""
        self.pack("iI", sec, nanosec)
        self.string(frame_id)

    def getvalue(self) -> bytes:
        return b"".join(self.parts)


def _check_str(field: str, value: Any) -> str:
    # rclpy stores strings NUL-terminated, so a NUL would cut the string on the wire.
    if not isinstance(value, str) or "\x00" in value:
        raise InputError(field, value, "a str without NUL characters")
    return value


def _check_vertices(vertices: Any) -> np.ndarray:
    vertices = np.asarray(vertices)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or vertices.dtype.kind not in "fiu":
        raise InputError(
            "vertices", f"{vertices.dtype} {vertices.shape}", "a (V, 3) array of numbers"
        )
    vertices = np.ascontiguousarray(vertices, dtype="<f8")
    if not np.isfinite(vertices).all():
        raise InputError("vertices", "non-finite values", "finite coordinates in metres")
    return vertices


def _check_triangles(triangles: Any, n_vertices: int) -> np.ndarray:
    triangles = np.asarray(triangles)
    # An empty (0, 3) array of any dtype is fine: np.zeros((0, 3)) is float.
    integer = triangles.dtype.kind in "iu" or (triangles.size == 0 and triangles.dtype != object)
    if triangles.ndim != 2 or triangles.shape[1] != 3 or not integer:
        raise InputError(
            "triangles", f"{triangles.dtype} {triangles.shape}", "a (T, 3) array of integers"
        )
    corners = triangles.reshape(-1).astype(np.intp)
    if corners.size and (corners.min() < 0 or corners.max() >= n_vertices):
        bad = corners[(corners < 0) | (corners >= n_vertices)][0]
        raise InputError("triangles", int(bad), f"vertex indices in [0, {n_vertices})")
    return corners


def _check_colours(colours: Any, n_vertices: int) -> np.ndarray:
    colours = np.asarray(colours)
    if colours.shape != (n_vertices, 3) or colours.dtype.kind not in "fiu":
        raise InputError(
            "colours",
            f"{colours.dtype} {colours.shape}",
            f"a (V, 3) = ({n_vertices}, 3) array of rgb",
        )
    colours = colours.astype(np.float64, copy=False)
    if not ((colours >= 0.0) & (colours <= 1.0)).all():  # NaN fails both comparisons
        raise InputError("colours", "values outside [0, 1]", "rgb in [0, 1]")
    return colours


def mesh_marker_cdr(
    vertices: Any,
    triangles: Any,
    colours: Any,
    stamp_ns: int,
    frame_id: str,
    ns: str = "reconstruction",
    marker_id: int = 0,
) -> bytes:
    """Serialised visualization_msgs/Marker (TRIANGLE_LIST) of a mesh, ready for
    ``Publisher.publish``; byte for byte what ``serialize_message`` gives for the same Marker,
    except that padding is zeros.

    vertices: (V, 3) metres in ``frame_id``. triangles: (T, 3) integer vertex indices.
    colours: (V, 3) rgb in [0, 1], or None for a plain grey mesh (``color`` only, no
    ``colors``). stamp_ns: int nanoseconds since the Unix epoch.

    The Marker has identity pose, scale (1, 1, 1), color GREY, ``points`` = the 3T triangle
    corners in order (float64) and, with colours, ``colors`` = one rgba (alpha 1) per point.
    """
    vertices = _check_vertices(vertices)
    corners = _check_triangles(triangles, len(vertices))
    rgb = None if colours is None else _check_colours(colours, len(vertices))
    stamp = ns_to_stamp(stamp_ns)
    frame_id = _check_str("frame_id", frame_id)
    ns = _check_str("ns", ns)
    if isinstance(marker_id, bool) or not isinstance(marker_id, int | np.integer):
        raise InputError("marker_id", marker_id, "an int")
    if not _INT32.min <= marker_id <= _INT32.max:
        raise InputError("marker_id", marker_id, "an int32")

    points = vertices[corners]  # (3T, 3) float64, C-contiguous
    out = _CdrWriter()
    out.header(stamp.sec, stamp.nanosec, frame_id)
    out.string(ns)
    out.pack("3i", int(marker_id), TRIANGLE_LIST, ADD)
    out.pack("7d", 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)  # pose: position, orientation xyzw
    out.pack("3d", 1.0, 1.0, 1.0)  # scale
    out.pack("4f", *GREY)
    out.pack("iI", 0, 0)  # lifetime 0: never expires
    out.pack("?", False)  # frame_locked
    out.pack("I", len(points))
    out.align(8)  # float64 elements; a no-op here (the fixed fields above end 8-aligned)
    out.raw(points.reshape(-1).view(np.uint8))
    if rgb is None:
        out.empty_sequence()
    else:
        rgba = np.ones((len(vertices), 4), dtype="<f4")
        rgba[:, :3] = rgb
        out.pack("I", len(points))
        out.raw(rgba[corners].reshape(-1).view(np.uint8))
    out.string("")  # texture_resource
    out.header(0, 0, "")  # texture: sensor_msgs/CompressedImage
    out.string("")  # texture.format
    out.empty_sequence()  # texture.data
    out.empty_sequence()  # uv_coordinates
    out.string("")  # text
    out.string("")  # mesh_resource
    out.string("")  # mesh_file.filename
    out.empty_sequence()  # mesh_file.data
    out.pack("?", False)  # mesh_use_embedded_materials
    return out.getvalue()


def marker_to_mesh(marker: Any) -> tuple[np.ndarray, np.ndarray]:
    """Triangle corners and their colours from a TRIANGLE_LIST visualization_msgs/Marker.

    Returns (3T, 3) float64 points (in the marker's frame, before its pose) and (3T, 3)
    float32 rgb, one per point; each is (0, 3) when the marker has none.
    """
    if marker.type != TRIANGLE_LIST:
        raise InputError("type", marker.type, f"TRIANGLE_LIST ({TRIANGLE_LIST})")
    n = len(marker.points)
    if n % 3:
        raise InputError("points", f"{n} points", "a multiple of 3 (one triple per triangle)")
    if len(marker.colors) not in (0, n):
        raise InputError("colors", f"{len(marker.colors)} colours", f"0 or one per point ({n})")
    points = np.array([(p.x, p.y, p.z) for p in marker.points], dtype=np.float64).reshape(-1, 3)
    colours = np.array([(c.r, c.g, c.b) for c in marker.colors], dtype=np.float32).reshape(-1, 3)
    return points, colours
