"""DDS types for ROS 2 messages, generated from the rosbags field lists, with rosbags CDR payloads.

ROS 2 over Cyclone DDS names message type ``pkg/msg/Name`` ``pkg::msg::dds_::Name_`` and service
halves ``pkg::srv::dds_::Name_Request_`` / ``Name_Response_``. The generated classes give Cyclone
the type name and type information for discovery; the payload bytes are the rosbags CDR of the
message, which are what cyclonedds-python would produce for the same struct (see the tests), only
numpy-fast instead of element by element.
"""

from __future__ import annotations

import struct
from typing import Any

from cyclonedds.idl import IdlStruct, make_idl_struct
from cyclonedds.idl import types as t

from area3d_msgs_py import msgs
from area3d_msgs_py.errors import InputError

# rosidl maps .msg primitives onto IDL like this (rosidl_adapter, "char" is an 8-bit unsigned).
_BASE_TYPES: dict[str, Any] = {
    "bool": bool,
    "byte": t.byte,
    "char": t.uint8,
    "int8": t.int8,
    "uint8": t.uint8,
    "int16": t.int16,
    "uint16": t.uint16,
    "int32": t.int32,
    "uint32": t.uint32,
    "int64": t.int64,
    "uint64": t.uint64,
    "float32": t.float32,
    "float64": t.float64,
    "string": str,
}

# rmw_cyclonedds prefixes every request and reply with {uint64 guid; int64 seq} (its
# cdds_request_header); the reply echoes the request's pair so the client can match it.
REQUEST_HEADER = struct.Struct("<Qq")
REQUEST_HEADER_FIELDS = {"client_guid": t.uint64, "sequence_number": t.int64}
ENCAPSULATION_BYTES = 4

_NODETYPE_BASE, _NODETYPE_NAME, _NODETYPE_ARRAY, _NODETYPE_SEQUENCE = 1, 2, 3, 4


def dds_type_name(type_name: str) -> str:
    """``'sensor_msgs/msg/Image'`` -> ``'sensor_msgs::msg::dds_::Image_'``."""
    parts = type_name.split("/")
    if len(parts) != 3 or parts[1] not in ("msg", "srv") or not all(parts):
        raise InputError("type_name", type_name, "'<package>/msg/<Name>' or '<package>/srv/<Name>'")
    pkg, kind, name = parts
    return f"{pkg}::{kind}::dds_::{name}_"


def dds_topic_name(topic: str) -> str:
    """ROS topic ``/a/b`` -> DDS topic ``rt/a/b``."""
    return "rt/" + _strip_slash(topic, "topic")


def dds_service_topics(service: str) -> tuple[str, str]:
    """ROS service ``/s`` -> (``rq/sRequest``, ``rr/sReply``)."""
    name = _strip_slash(service, "service")
    return f"rq/{name}Request", f"rr/{name}Reply"


def _strip_slash(name: str, field: str) -> str:
    if not isinstance(name, str) or not name.strip("/"):
        raise InputError(field, name, "a non-empty ROS name such as '/area3d/camera/pose'")
    return name.lstrip("/")


_STRUCT_CACHE: dict[tuple[str, bool], type[IdlStruct]] = {}


def _field_type(desc: tuple) -> Any:
    nodetype, arg = desc
    if nodetype == _NODETYPE_BASE:
        base, bound = arg
        if base == "string" and bound:
            return t.bounded_str[bound]
        if base not in _BASE_TYPES:
            raise InputError("field type", base, f"one of {sorted(_BASE_TYPES)}")
        return _BASE_TYPES[base]
    if nodetype == _NODETYPE_NAME:
        return idl_struct(arg)
    sub, count = arg
    element = _field_type(sub)
    if nodetype == _NODETYPE_ARRAY:
        return t.array[element, count]
    if nodetype == _NODETYPE_SEQUENCE:
        return t.sequence[element, count] if count else t.sequence[element]
    raise InputError("field node type", nodetype, "BASE, NAME, ARRAY or SEQUENCE")


def _make_struct(type_name: str, with_request_header: bool, suffix: str) -> type[IdlStruct]:
    msgs.get(type_name)
    _, fields = msgs.typestore.fielddefs[type_name]
    idl_fields: dict[str, Any] = dict(REQUEST_HEADER_FIELDS) if with_request_header else {}
    for name, desc in fields:
        idl_fields[name] = _field_type(desc)
    class_name = (
        type_name.replace("/", "__")
        + suffix
        + ("__with_request_header" if with_request_header else "")
    )
    return make_idl_struct(class_name, dds_type_name(type_name), idl_fields)


def idl_struct(type_name: str, with_request_header: bool = False) -> type[IdlStruct]:
    """The plain cyclonedds-python struct of a message type (its own, element-wise serialisation).

    ``with_request_header`` prepends the rmw_cyclonedds request header, as on service topics.
    """
    key = (type_name, with_request_header)
    if key not in _STRUCT_CACHE:
        _STRUCT_CACHE[key] = _make_struct(type_name, with_request_header, "")
    return _STRUCT_CACHE[key]


def to_idl_sample(
    msg: Any, type_name: str | None = None, request_header: tuple[int, int] | None = None
) -> IdlStruct:
    """The ``idl_struct`` instance holding the same values as a rosbags message (slow; for checks)."""
    type_name = type_name or msgs.type_name_of(msg)
    cls = idl_struct(type_name, request_header is not None)
    _, fields = msgs.typestore.fielddefs[type_name]
    values: dict[str, Any] = {}
    if request_header is not None:
        values["client_guid"], values["sequence_number"] = request_header
    for name, desc in fields:
        values[name] = _to_idl_value(getattr(msg, name), desc)
    return cls(**values)


def _to_idl_value(value: Any, desc: tuple) -> Any:
    nodetype, arg = desc
    if nodetype == _NODETYPE_BASE:
        return value.item() if hasattr(value, "item") else value
    if nodetype == _NODETYPE_NAME:
        return to_idl_sample(value, arg)
    sub = arg[0]
    return [_to_idl_value(v, sub) for v in value]


class RawSample:
    """What a reader hands over: the CDR bytes of one sample (Cyclone attaches ``sample_info``)."""

    def __init__(self, data: bytes) -> None:
        self.data = data


def _serialize_payload(self, buffer=None, endianness=None, use_version_2=None) -> bytes:
    return self._area3d_cdr


def _deserialize_payload(cls, data, has_header=True, use_version_2=None) -> RawSample:
    return RawSample(data)


_WIRE_CACHE: dict[tuple[str, bool], type[IdlStruct]] = {}


def wire_type(type_name: str, with_request_header: bool = False) -> type[IdlStruct]:
    """The DDS type our readers and writers use: named and described like ``idl_struct``, but its
    ``serialize`` returns prepared CDR bytes and its ``deserialize`` returns a ``RawSample``.

    A separate class from ``idl_struct`` (Cyclone rejects subclasses), patched on the class itself.
    """
    key = (type_name, with_request_header)
    if key not in _WIRE_CACHE:
        cls = _make_struct(type_name, with_request_header, "__cdr")
        cls.serialize = _serialize_payload
        cls.deserialize = classmethod(_deserialize_payload)
        cls.deserialize_key = classmethod(_deserialize_payload)
        _WIRE_CACHE[key] = cls
    return _WIRE_CACHE[key]


def wire_sample(cls: type[IdlStruct], cdr: bytes) -> IdlStruct:
    """An instance of ``cls`` that a DataWriter accepts and that serialises to ``cdr``."""
    sample = object.__new__(cls)
    sample._area3d_cdr = cdr
    return sample


def add_request_header(cdr: bytes, guid: int, seq: int) -> bytes:
    """Insert the rmw_cyclonedds request header after the encapsulation header.

    The header is 16 bytes, so the body's 8-byte CDR alignment is unchanged.
    """
    return cdr[:ENCAPSULATION_BYTES] + REQUEST_HEADER.pack(guid, seq) + cdr[ENCAPSULATION_BYTES:]


def split_request_header(data: bytes) -> tuple[int, int, bytes]:
    """(guid, seq, CDR of the body) from the bytes of a request or reply sample."""
    if len(data) < ENCAPSULATION_BYTES + REQUEST_HEADER.size:
        raise InputError("request sample", len(data), "at least 20 bytes (encapsulation + header)")
    little = data[1] & 1
    fmt = "<Qq" if little else ">Qq"
    guid, seq = struct.unpack_from(fmt, data, ENCAPSULATION_BYTES)
    body = data[:ENCAPSULATION_BYTES] + data[ENCAPSULATION_BYTES + REQUEST_HEADER.size :]
    return guid, seq, body
