"""sensor_msgs/PointCloud2 <-> numpy structured arrays, one field per PointField."""

from __future__ import annotations

from typing import Any

import numpy as np

from area3d_msgs_py import msgs
from area3d_msgs_py.codecs.header import data_bytes, header
from area3d_msgs_py.errors import InputError

# sensor_msgs/PointField datatypes.
POINTFIELD_DTYPES: dict[int, str] = {
    1: "i1",
    2: "u1",
    3: "i2",
    4: "u2",
    5: "i4",
    6: "u4",
    7: "f4",
    8: "f8",
}
_DTYPE_TO_POINTFIELD = {v: k for k, v in POINTFIELD_DTYPES.items()}


def pointcloud_to_msg(points: np.ndarray, stamp_ns: int, frame_id: str) -> Any:
    """sensor_msgs/PointCloud2 from a structured array.

    points: (N,) unorganised or (H, W) organised structured array; every field a scalar of int8,
    uint8, int16, uint16, int32, uint32, float32 or float64 (one byte order for all), offsets and
    padding as in the dtype. ``is_dense`` is False when any float field holds a non-finite value.
    """
    points = np.asarray(points)
    if points.dtype.names is None:
        raise InputError(
            "points.dtype", str(points.dtype), "a structured dtype such as [('x','<f4'),...]"
        )
    if points.ndim not in (1, 2):
        raise InputError("points.shape", points.shape, "(N,) or (H, W)")
    fields = []
    orders = set()
    for name in points.dtype.names:
        field_dtype, offset = points.dtype.fields[name][:2]
        if field_dtype.shape:
            raise InputError(
                f"field {name!r}", str(field_dtype), "a scalar field (PointField count 1)"
            )
        code = field_dtype.kind + str(field_dtype.itemsize)
        if code not in _DTYPE_TO_POINTFIELD:
            raise InputError(
                f"field {name!r}", str(field_dtype), "one of int8..uint32, float32, float64"
            )
        if field_dtype.itemsize > 1:
            big = field_dtype.byteorder == ">" or (
                field_dtype.byteorder == "=" and not np.little_endian
            )
            orders.add(big)
        fields.append(
            msgs.PointField(
                name=name, offset=int(offset), datatype=_DTYPE_TO_POINTFIELD[code], count=1
            )
        )
    if len(orders) > 1:
        raise InputError("points.dtype", str(points.dtype), "all fields in one byte order")
    is_bigendian = bool(orders.pop()) if orders else False
    height, width = (1, points.shape[0]) if points.ndim == 1 else points.shape
    flat = np.ascontiguousarray(points).reshape(-1)
    is_dense = True
    for name in points.dtype.names:
        if points.dtype.fields[name][0].kind == "f" and not np.isfinite(flat[name]).all():
            is_dense = False
            break
    point_step = points.dtype.itemsize
    return msgs.PointCloud2(
        header=header(stamp_ns, frame_id),
        height=int(height),
        width=int(width),
        fields=fields,
        is_bigendian=is_bigendian,
        point_step=point_step,
        row_step=point_step * width,
        data=flat.tobytes(),
        is_dense=is_dense,
    )


def pointcloud_dtype(msg: Any) -> np.dtype:
    """Structured dtype (itemsize = point_step) described by a PointCloud2's fields."""
    names, formats, offsets = [], [], []
    order = ">" if msg.is_bigendian else "<"
    point_step = int(msg.point_step)
    for field in msg.fields:
        if field.datatype not in POINTFIELD_DTYPES:
            raise InputError(
                f"field {field.name!r} datatype", field.datatype, "1..8 (INT8..FLOAT64)"
            )
        if field.count not in (0, 1):
            raise InputError(f"field {field.name!r} count", field.count, "1 (scalar fields only)")
        code = POINTFIELD_DTYPES[field.datatype]
        size = int(code[1])
        if field.offset + size > point_step:
            raise InputError(
                f"field {field.name!r} offset",
                field.offset,
                f"offset + {size} <= point_step {point_step}",
            )
        if field.name in names:
            raise InputError("fields", field.name, "unique field names")
        names.append(field.name)
        formats.append((order if size > 1 else "|") + code)
        offsets.append(int(field.offset))
    try:
        return np.dtype(
            {"names": names, "formats": formats, "offsets": offsets, "itemsize": point_step}
        )
    except ValueError as exc:
        raise InputError(
            "fields", [f.name for f in msg.fields], f"non-overlapping fields ({exc})"
        ) from None


def msg_to_pointcloud(msg: Any) -> np.ndarray:
    """Structured array from sensor_msgs/PointCloud2 (own memory, native byte order kept as sent).

    Returns (width,) when height == 1, else (height, width); row padding is dropped.
    """
    dtype = pointcloud_dtype(msg)
    height, width, row_step = int(msg.height), int(msg.width), int(msg.row_step)
    if row_step < width * dtype.itemsize:
        raise InputError("row_step", row_step, f">= width * point_step = {width * dtype.itemsize}")
    data = data_bytes(msg.data)
    if data.size != height * row_step:
        raise InputError(
            "data", f"{data.size} bytes", f"height * row_step = {height * row_step} bytes"
        )
    rows = data.reshape(height, row_step)[:, : width * dtype.itemsize].copy()
    cloud = rows.view(dtype).reshape(height, width)
    return cloud[0] if height == 1 else cloud
