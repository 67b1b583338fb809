"""ROS 2 messages as the node and the player send and receive them: their definitions, their wire
names and their bytes, all through ``rosbags`` (no ROS installation).

- :func:`typestore`: rosbags' store of the stock ROS 2 messages (Jazzy's definitions; the messages
  used here are the same from Humble on), with ``grid_map_msgs`` registered from its ``.msg``
  definitions (:data:`GRID_MAP_MSGS`: the ROS 2 layout of ANYbotics' grid_map, whose ``GridMap``
  carries the header and whose ``GridMapInfo`` the map's pose).
- :func:`dds_topic_name` and :func:`dds_type_name`: how a ROS 2 node names a topic and a type on
  DDS (``/scan`` is ``rt/scan``; ``sensor_msgs/msg/LaserScan`` is
  ``sensor_msgs::msg::dds_::LaserScan_``), the names rmw_cyclonedds and rmw_fastrtps both use.
- :class:`Codec`: a message to its CDR bytes and back (plain CDR, little endian, the 4-byte
  encapsulation header ``00 01 00 00`` first: what DDS calls XCDR1, the only representation ROS 2's
  nodes read), and each type's RIHS01 hash (REP 2011), which Iron and later put in the
  readers' and writers' USER_DATA.
"""

from __future__ import annotations

import functools
import re

import numpy as np

from dem_graph.errors import DemGraphError
from dem_graph.optional import import_rosbags_typesys

# grid_map_msgs' two messages in their ROS 2 form (ANYbotics/grid_map, branch ros2): the fields and
# their types, which the type hash and the bytes depend on; the comments are this project's own
GRID_MAP_MSGS = {
    "grid_map_msgs/msg/GridMapInfo": """
float64 resolution        # metres a cell
float64 length_x          # the map's extent along its frame's x, metres
float64 length_y          # and along y
geometry_msgs/Pose pose   # the map's centre in the header's frame (grid_map reads its position)
""",
    "grid_map_msgs/msg/GridMap": """
std_msgs/Header header
grid_map_msgs/GridMapInfo info
string[] layers
string[] basic_layers
std_msgs/Float32MultiArray[] data
uint16 outer_start_index  # the circular buffer's start: the row of the first cell
uint16 inner_start_index  # and its column
""",
}
CDR_LE_HEADER = b"\x00\x01\x00\x00"
"""The encapsulation header of plain CDR (XCDR1), little endian, as ROS 2 writes and reads it."""

_TOPIC = re.compile(r"^/?[A-Za-z_~{][A-Za-z0-9_/{}~]*$")


class MessageError(DemGraphError):
    """A message that cannot be encoded or decoded (named by its topic or type)."""


@functools.cache
def typestore():
    """rosbags' ROS 2 type store with grid_map_msgs registered (made once)."""
    typesys = import_rosbags_typesys()
    store = typesys.get_typestore(typesys.Stores.ROS2_JAZZY)
    types = {}
    for name, text in GRID_MAP_MSGS.items():
        types.update(typesys.get_types_from_msg(text, name))
    store.register(types)
    return store


def dds_topic_name(topic: str) -> str:
    """The DDS topic of a ROS 2 topic: ``/scan`` -> ``rt/scan`` (a relative name is taken from the root)."""
    if not _TOPIC.match(topic) or "//" in topic or topic.endswith("/") and topic != "/":
        raise MessageError(f"{topic!r} is not a ROS 2 topic name")
    return "rt/" + topic.lstrip("/")


def ros_topic_name(dds_topic: str) -> str | None:
    """The ROS 2 topic of a DDS topic (``rt/scan`` -> ``/scan``), None for DDS topics that are no ROS topic."""
    return "/" + dds_topic[3:] if dds_topic.startswith("rt/") else None


def dds_type_name(msgtype: str) -> str:
    """The DDS type of a ROS 2 message type: ``sensor_msgs/msg/Image`` -> ``sensor_msgs::msg::dds_::Image_``."""
    parts = msgtype.split("/")
    if len(parts) != 3 or parts[1] != "msg":
        raise MessageError(f"{msgtype!r} is not a ROS 2 message type (package/msg/Name)")
    return f"{parts[0]}::msg::dds_::{parts[2]}_"


def ros_type_name(dds_type: str) -> str | None:
    """The ROS 2 message type of a DDS type name, None for one that is not a ROS message's."""
    m = re.fullmatch(r"(\w+)::msg::dds_::(\w+)_", dds_type)
    return f"{m.group(1)}/msg/{m.group(2)}" if m else None


class Codec:
    """Messages of the type store to bytes and back, and their type hashes (see the module)."""

    def __init__(self, store=None):
        self.store = store or typestore()
        self._warm: set[str] = set()

    def has(self, msgtype: str) -> bool:
        return msgtype in self.store.types

    def message_class(self, msgtype: str):
        """The dataclass of ``msgtype`` (``codec.message_class('sensor_msgs/msg/Image')(header=..., ...)``)."""
        try:
            return self.store.types[msgtype]
        except KeyError:
            raise MessageError(f"unknown message type {msgtype!r}") from None

    def encode(self, message, msgtype: str) -> bytes:
        """``message`` as plain CDR (XCDR1), the encapsulation header first."""
        try:
            return bytes(self.store.serialize_cdr(message, msgtype))
        except Exception as exc:  # noqa: BLE001 - rosbags raises several kinds for a message that is not of its type
            raise MessageError(f"a {msgtype} cannot be encoded ({type(exc).__name__}: {' '.join(str(exc).split())[:200]})") from None

    def decode(self, data: bytes | memoryview, msgtype: str):
        """The message of CDR bytes; :class:`MessageError` for bytes that are not one (too short, of
        another representation: an XCDR2 or big-endian writer's)."""
        head = bytes(data[:4])
        if head != CDR_LE_HEADER:
            what = {b"\x00\x00": "big-endian CDR", b"\x00\x06": "XCDR2 (big endian)", b"\x00\x07": "XCDR2", b"\x00\x08": "XCDR2 (big endian)", b"\x00\x09": "XCDR2", b"\x00\x0a": "XCDR2 (big endian)", b"\x00\x0b": "XCDR2"}.get(head[:2], f"encapsulation {head.hex()}")
            raise MessageError(f"a {msgtype} in {what}, not plain little-endian CDR (XCDR1) as ROS 2 writes it")
        try:
            return self.store.deserialize_cdr(bytes(data), msgtype)
        except Exception as exc:  # noqa: BLE001 - truncated or foreign bytes: rosbags raises several kinds
            raise MessageError(f"a {msgtype} cannot be decoded from {len(data)} bytes ({type(exc).__name__}: {' '.join(str(exc).split())[:160]})") from None

    def type_hash(self, msgtype: str) -> str:
        """The RIHS01 hash of ``msgtype`` (``RIHS01_`` and 64 hex digits)."""
        return self.store.hash_rihs01(msgtype)

    def warm_up(self, msgtype: str) -> None:
        """Make rosbags generate ``msgtype``'s (de)serialiser now, not on the first message (a tenth of
        a second for a large type, long enough to lose messages on a busy topic)."""
        if msgtype in self._warm:
            return
        message = self.store.deserialize_cdr(self.store.serialize_cdr(self._empty(msgtype), msgtype), msgtype)
        del message
        self._warm.add(msgtype)

    def _empty(self, msgtype: str):
        """A message of ``msgtype`` with every field zero or empty."""
        from rosbags.typesys.store import Nodetype

        _consts, fields = self.store.fielddefs[msgtype]
        values = {}
        for name, (kind, detail) in fields:
            if kind == Nodetype.BASE:
                values[name] = "" if detail[0] in ("string", "wstring") else False if detail[0] == "bool" else 0
            elif kind == Nodetype.NAME:
                values[name] = self._empty(detail)
            elif kind == Nodetype.ARRAY:
                sub_kind, sub = detail[0]
                if sub_kind == Nodetype.BASE and sub[0] not in ("string", "wstring"):
                    values[name] = np.zeros(detail[1], dtype=_NUMPY.get(sub[0], "f8"))
                else:
                    values[name] = [self._empty(sub) if sub_kind == Nodetype.NAME else "" for _ in range(detail[1])]
            else:  # a sequence
                sub_kind, sub = detail[0]
                values[name] = np.zeros(0, dtype=_NUMPY.get(sub[0], "f8")) if sub_kind == Nodetype.BASE and sub[0] not in ("string", "wstring") else []
        return self.store.types[msgtype](**values)


_NUMPY = {"bool": "?", "byte": "u1", "char": "u1", "int8": "i1", "uint8": "u1", "int16": "i2", "uint16": "u2", "int32": "i4", "uint32": "u4", "int64": "i8", "uint64": "u8", "float32": "f4", "float64": "f8"}


__all__ = ["CDR_LE_HEADER", "GRID_MAP_MSGS", "Codec", "MessageError", "dds_topic_name", "dds_type_name", "ros_topic_name", "ros_type_name", "typestore"]
