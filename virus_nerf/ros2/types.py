"""ROS 2 message types for a node that speaks DDS through cyclonedds, with no ROS install.

A ROS 2 node (rmw_cyclonedds_cpp) matches a DDS topic by its name ("rt/map") and type name
("nav_msgs::msg::dds_::OccupancyGrid_"); samples are final structs in plain CDR (XCDR1, little
endian, encapsulation header 00 01 00 00). Payloads are (de)serialised by rosbags, whose message
objects the decoders in data/bags/messages.py already read; the cyclonedds `IdlStruct` classes made
here only register topics, so each one describes exactly the layout rosbags writes: ROS 2 `byte`
and `char` are one unsigned octet each, an empty message holds rosidl's
`uint8 structure_needs_at_least_one_member`. Jazzy endpoints also carry the type's RIHS01 hash
in USER_DATA (`user_data`); Humble ones carry none.
"""

from __future__ import annotations

import dataclasses
import re
from functools import cache
from typing import Any

import numpy as np

from virus_nerf.errors import UsageError

DISTROS = ("humble", "jazzy")

# rosbags field descriptors: (Nodetype, payload); Nodetype BASE=1, NAME=2, ARRAY=3, SEQUENCE=4.
_BASE, _NAME, _ARRAY, _SEQUENCE = 1, 2, 3, 4
_DDS_NAME = re.compile(r"^([A-Za-z]\w*)::(msg|srv|action)::dds_::([A-Za-z]\w*)_$")
# numpy dtypes rosbags uses for numeric arrays and sequences (rosbags.serde.utils.ndtype).
_NDTYPE = {"bool": "bool_", "char": "uint8", "byte": "int8"}


def _check_distro(distro: str) -> None:
    if distro not in DISTROS:
        raise UsageError(f"ROS 2 distro {distro!r}: expected one of {', '.join(DISTROS)}")


@cache
def _store(distro: str) -> Any:
    from rosbags.typesys import Stores, get_typestore

    from virus_nerf.data.bags.messages import custom_types

    store = get_typestore(Stores.ROS2_HUMBLE if distro == "humble" else Stores.ROS2_JAZZY)
    store.register(custom_types())
    return store


def typestore(distro: str) -> Any:
    """The rosbags typestore of `distro` ('humble' or 'jazzy') plus the robot's custom messages."""
    _check_distro(distro)
    return _store(distro)


def _fields(distro: str, msgtype: str) -> list[tuple[str, tuple]]:
    defs = typestore(distro).fielddefs
    if msgtype not in defs:
        raise UsageError(f"message type {msgtype!r}: not a {distro} message type "
                         "(expected e.g. 'sensor_msgs/msg/Image')")
    return defs[msgtype][1]


def dds_type_name(msgtype: str) -> str:
    """'sensor_msgs/msg/Image' -> 'sensor_msgs::msg::dds_::Image_' (the DDS type name ROS 2 uses)."""
    parts = msgtype.split("/")
    if len(parts) != 3 or not all(parts):
        raise UsageError(f"message type {msgtype!r}: expected 'package/msg/Name'")
    return f"{parts[0]}::{parts[1]}::dds_::{parts[2]}_"


def ros_type_name(dds_name: str) -> str | None:
    """'sensor_msgs::msg::dds_::Image_' -> 'sensor_msgs/msg/Image'; None for any other name."""
    m = _DDS_NAME.match(dds_name)
    return f"{m[1]}/{m[2]}/{m[3]}" if m else None


def _idl_type(distro: str, desc: tuple, msgtype: str) -> Any:
    """A rosbags field descriptor -> the cyclonedds annotation of the same wire layout."""
    from cyclonedds.idl import types as t

    kind, arg = int(desc[0]), desc[1]
    if kind == _NAME:
        return idl_struct(distro, arg)
    if kind in (_ARRAY, _SEQUENCE):
        sub = _idl_type(distro, arg[0], msgtype)
        if kind == _ARRAY:
            return t.array[sub, arg[1]]
        return t.sequence[sub, arg[1]] if arg[1] else t.sequence[sub]
    name, bound = arg
    if name == "string":
        return t.bounded_str[bound] if bound else str
    base = {"bool": bool, "byte": t.uint8, "char": t.uint8, "int8": t.int8, "uint8": t.uint8,
            "int16": t.int16, "uint16": t.uint16, "int32": t.int32, "uint32": t.uint32,
            "int64": t.int64, "uint64": t.uint64, "float32": t.float32, "float64": t.float64}
    if name not in base:
        raise UsageError(f"message type {msgtype!r}: field type {name!r} has no DDS mapping here")
    return base[name]


@cache
def idl_struct(distro: str, msgtype: str) -> type:
    """The final cyclonedds IdlStruct of `msgtype` (nested messages as nested IdlStructs), named
    dds_type_name(msgtype), laid out exactly as rosbags serialises it (constants are ignored)."""
    from cyclonedds.idl import make_idl_struct
    from cyclonedds.idl.annotations import final

    fields = {name: _idl_type(distro, desc, msgtype) for name, desc in _fields(distro, msgtype)}
    return final(make_idl_struct(msgtype.replace("/", "__"), dds_type_name(msgtype), fields))


def type_hash(distro: str, msgtype: str) -> str | None:
    """'RIHS01_<64 hex>' of `msgtype` for Jazzy (REP 2011 type hash); None for Humble."""
    _fields(distro, msgtype)
    return typestore(distro).hash_rihs01(msgtype) if distro == "jazzy" else None


def user_data(distro: str, msgtype: str) -> bytes:
    """USER_DATA QoS of a ROS 2 reader or writer: rmw_cyclonedds_cpp (rmw_node.cpp,
    create_readwrite_qos, Iron and later) sets rmw_dds_common::encode_type_hash_for_user_data_qos
    (qos.cpp): "typehash=" + "RIHS01_<hex>" + ";"; Humble sets none for topics."""
    h = type_hash(distro, msgtype)
    return f"typehash={h};".encode() if h else b""


def _ndtype(base: str) -> np.dtype:
    return np.dtype(_NDTYPE.get(base, base))


def _zero(desc: tuple, store: Any) -> Any:
    """The zero value rosbags would hold for a field of descriptor `desc`."""
    kind, arg = int(desc[0]), desc[1]
    if kind == _NAME:
        return store.types[arg](**{n: _zero(d, store) for n, d in store.fielddefs[arg][1]})
    if kind in (_ARRAY, _SEQUENCE):
        sub, n = arg
        n = n if kind == _ARRAY else 0
        if int(sub[0]) == _BASE and sub[1][0] != "string":
            return np.zeros(n, dtype=_ndtype(sub[1][0]))
        return [_zero(sub, store) for _ in range(n)]
    name = arg[0]
    return "" if name == "string" else False if name == "bool" else 0.0 if "float" in name else 0


def _convert(value: Any, desc: tuple, store: Any) -> Any:
    kind, arg = int(desc[0]), desc[1]
    if kind == _NAME:
        return to_ros2(value, arg, store)
    if kind in (_ARRAY, _SEQUENCE):
        sub = arg[0]
        if int(sub[0]) == _BASE and sub[1][0] != "string":
            return np.asarray(value, dtype=_ndtype(sub[1][0]))
        return [_convert(v, sub, store) for v in value]
    name = arg[0]
    if name == "string":
        return str(value)
    return bool(value) if name == "bool" else float(value) if "float" in name else int(value)


def _names(msg: Any) -> list[str]:
    if dataclasses.is_dataclass(msg):
        return [f.name for f in dataclasses.fields(msg)]
    names = [*getattr(msg, "__dict__", {}), *getattr(type(msg), "__slots__", ())]
    return [n.lstrip("_") for n in names if hasattr(msg, n.lstrip("_"))]


def to_ros2(msg: Any, msgtype: str, store: Any) -> Any:
    """A message of type `msgtype`, possibly ROS 1 shaped (Header.seq, CameraInfo.D/K/R/P), as an
    instance of the ROS 2 class of `store`: fields matched by name, else case-insensitively
    (recursively); ROS 2 fields the source lacks get zero values, ROS 1-only fields are dropped."""
    if msgtype not in store.fielddefs:
        raise UsageError(f"message type {msgtype!r}: not in the ROS 2 typestore")
    lower = {n.lower(): n for n in _names(msg)}
    values = {}
    for name, desc in store.fielddefs[msgtype][1]:
        src = name if hasattr(msg, name) else lower.get(name.lower())
        values[name] = _zero(desc, store) if src is None else _convert(getattr(msg, src), desc, store)
    return store.types[msgtype](**values)


def serialize(msg: Any, msgtype: str, store: Any) -> bytes:
    """CDR (little endian, with the 4-byte encapsulation header) of a ROS 2 message."""
    return bytes(store.serialize_cdr(msg, msgtype, little_endian=True))


def deserialize(raw: bytes | memoryview, msgtype: str, store: Any) -> Any:
    """The rosbags message of a CDR payload (up to 3 bytes of end padding, as cyclonedds adds,
    are accepted)."""
    return store.deserialize_cdr(raw, msgtype)
