"""Damaged recordings read up to the damage: a ROS 1 bag without its index and an MCAP file without its
summary (a recording killed, a file cut short), read record by record as far as the records are whole.

``rosbags`` refuses both (it reads a ROS 1 bag through its index and an MCAP file from its footer).
The ROS tools read them sequentially (``rosbag reindex``, ``mcap recover``); so does :func:`salvage_bag`,
which gives a reader with the part of ``rosbags``' AnyReader that :mod:`~dem_graph.datasets.rosbag`
uses (``connections``, ``messages``, ``deserialize``) and says where the whole part ends (a byte offset).

The formats, as read here:

- ROS 1 (bag format 2.0): the line ``#ROSBAG V2.0``, then records, each ``header_len`` (uint32),
  the header (fields ``len`` uint32 + ``name=value``), ``data_len`` (uint32), the data. ``op`` 0x03 the
  bag header, 0x05 a chunk (its data: records, compressed as its ``compression`` field says), 0x07 a
  connection (its data: the fields ``type``, ``message_definition``, ...), 0x02 a message (``conn``,
  ``time`` sec+nsec), 0x04 and 0x06 index records (not needed). The chunk being written when the
  recording was killed is read as far as its records are whole when it is not compressed.
- MCAP: the magic ``\\x89MCAP0\\r\\n``, then records, each an opcode (uint8), a length (uint64) and the
  content: 0x03 schema, 0x04 channel, 0x05 message, 0x06 chunk (its records, compressed or not); the
  others are skipped. A chunk cut short is read as far as its records are whole when it is not compressed.
"""

from __future__ import annotations

import mmap
import struct
from dataclasses import dataclass, field
from io import BytesIO
from pathlib import Path

ROS1_MAGIC = b"#ROSBAG V2.0\n"
MCAP_MAGIC = b"\x89MCAP0\r\n"


@dataclass(frozen=True)
class SalvagedConnection:
    """A topic of a salvaged bag: ``id`` (the bag's connection or channel id), ``topic``, ``msgtype``
    (ROS 2 style, ``sensor_msgs/msg/Image``) and its message definition (``msgdef_format`` "msg" or "idl")."""

    id: int
    topic: str
    msgtype: str
    msgdef: str
    msgdef_format: str


@dataclass(frozen=True)
class _Location:
    """Where a message's bytes are: in the file (``chunk`` None) or in the chunk at file offset ``chunk``."""

    t_ns: int
    conn_id: int
    chunk: int | None
    start: int
    length: int


@dataclass
class SalvagedBag:
    """The whole part of a damaged bag: its connections and where each message is; ``whole_bytes``:
    the byte offset where the whole part ends, ``size_bytes``: the file's size."""

    path: Path
    ros1: bool
    connections: list[SalvagedConnection] = field(default_factory=list)
    whole_bytes: int = 0
    size_bytes: int = 0
    _messages: list[_Location] = field(default_factory=list)
    _chunks: dict[int, tuple[str, int, int, int, int]] = field(
        default_factory=dict
    )  # offset -> (compression, data offset, length, size, crc)
    _typestore: object = None

    def messages(self, connections=(), start: int | None = None, stop: int | None = None):
        """``(connection, t_ns, raw bytes)`` of the messages of ``connections`` (all when empty) in file order."""
        wanted = {c.id for c in connections} if connections else {c.id for c in self.connections}
        by_id = {c.id: c for c in self.connections}
        chunk_at, chunk_data = None, b""
        with self.path.open("rb") as f:
            for loc in self._messages:
                if loc.conn_id not in wanted or (start is not None and loc.t_ns < start) or (stop is not None and loc.t_ns >= stop):
                    continue
                if loc.chunk is None:
                    f.seek(loc.start)
                    raw = f.read(loc.length)
                else:
                    if chunk_at != loc.chunk:
                        chunk_at, chunk_data = loc.chunk, self._chunk_bytes(loc.chunk)
                    raw = chunk_data[loc.start : loc.start + loc.length]
                yield by_id[loc.conn_id], loc.t_ns, raw

    def deserialize(self, raw: bytes, msgtype: str):
        """A message of ``msgtype`` from its bytes (ROS 1 serialisation or CDR)."""
        if self.ros1:
            return self._typestore.deserialize_ros1(raw, msgtype)
        return self._typestore.deserialize_cdr(raw, msgtype)

    def _chunk_bytes(self, offset: int) -> bytes:
        compression, start, length, size, crc = self._chunks[offset]
        with self.path.open("rb") as f:
            f.seek(start)
            return _decompress(self.ros1, compression, f.read(length), size, crc)


def _decompress(ros1: bool, compression: str, data: bytes, size: int, crc: int) -> bytes:
    """A chunk's records from its stored bytes, with ``rosbags``' own decompressors."""
    if ros1:
        from rosbags.rosbag1.reader import decompressors

        return decompressors[compression](data)
    from rosbags.rosbag2.storage_mcap import decompress

    return decompress(data, compression, size, crc)


# ----------------------------------------------------------------------------------------------
# ROS 1


def _ros1_fields(header: bytes) -> dict[str, bytes] | None:
    """A ROS 1 record header's fields, None when they do not parse."""
    fields, pos = {}, 0
    while pos < len(header):
        if pos + 4 > len(header):
            return None
        (n,) = struct.unpack_from("<I", header, pos)
        pos += 4
        name, sep, value = header[pos : pos + n].partition(b"=")
        if not sep or pos + n > len(header):
            return None
        fields[name.decode(errors="replace")] = value
        pos += n
    return fields


def _ros1_records(buf: bytes, start: int):
    """``(offset, header fields, data start, data length)`` of the whole records of ``buf`` from ``start``;
    then one last ``(offset, None, 0, 0)`` at the first record that is not whole (or the end)."""
    pos = start
    while pos + 4 <= len(buf):
        (hlen,) = struct.unpack_from("<I", buf, pos)
        if pos + 4 + hlen + 4 > len(buf):
            break
        fields = _ros1_fields(buf[pos + 4 : pos + 4 + hlen])
        (dlen,) = struct.unpack_from("<I", buf, pos + 4 + hlen)
        data_start = pos + 8 + hlen
        if fields is None or "op" not in fields:
            break
        yield pos, fields, data_start, dlen
        pos = data_start + dlen
    yield pos, None, 0, 0


def _salvage_ros1(path: Path, buf: bytes) -> SalvagedBag:
    from rosbags.typesys.msg import normalize_msgtype

    bag = SalvagedBag(path, ros1=True, size_bytes=len(buf))
    seen: set[int] = set()

    def connection(fields: dict[str, bytes], data: bytes) -> None:
        conn = struct.unpack("<I", fields["conn"])[0]
        info = _ros1_fields(data) or {}
        if conn in seen or "type" not in info:
            return
        seen.add(conn)
        topic = fields["topic"].decode()
        msgtype = normalize_msgtype(info["type"].decode())
        bag.connections.append(SalvagedConnection(conn, topic, msgtype, info.get("message_definition", b"").decode(), "msg"))

    def message(fields: dict[str, bytes], chunk: int | None, start: int, length: int) -> None:
        sec, nsec = struct.unpack("<II", fields["time"])
        bag._messages.append(_Location(sec * 10**9 + nsec, struct.unpack("<I", fields["conn"])[0], chunk, start, length))

    def take(fields: dict[str, bytes], data: bytes, chunk: int | None, start: int, length: int) -> None:
        """A connection or a message record whose data is ``data[start : start + length]``; others are passed over."""
        if fields["op"][0] == 0x07:
            connection(fields, data[start : start + length])
        elif fields["op"][0] == 0x02:
            message(fields, chunk, start, length)

    whole = len(ROS1_MAGIC)
    for pos, fields, data_start, dlen in _ros1_records(buf, len(ROS1_MAGIC)):
        if fields is None:
            whole = pos
            break
        op = fields["op"][0]
        complete = data_start + dlen <= len(buf)
        if op == 0x05:
            compression = fields.get("compression", b"none").decode()
            if complete and dlen > 0:
                raw = _decompress(True, compression, buf[data_start : data_start + dlen], 0, 0)
                bag._chunks[pos] = (compression, data_start, dlen, 0, 0)
                for _, f, s, n in _ros1_records(raw, 0):
                    if f is None:
                        break
                    take(f, raw, pos, s, n)
                whole = data_start + dlen
                continue
            if compression != "none":  # a compressed chunk cut short: nothing in it is whole
                whole = pos
                break
            # the chunk being written when the recording stopped: its records, as far as they are whole
            end = pos
            for p, f, s, n in _ros1_records(buf, data_start):
                if f is None or s + n > len(buf):
                    end = p
                    break
                take(f, buf, None, s, n)
                end = s + n
            whole = end
            break
        if not complete:
            whole = pos
            break
        take(fields, buf, None, data_start, dlen)
        whole = data_start + dlen
    bag.whole_bytes = whole
    return bag


# ----------------------------------------------------------------------------------------------
# MCAP


def _string(b: BytesIO) -> str:
    (n,) = struct.unpack("<I", b.read(4))
    return b.read(n).decode()


def _mcap_records(buf: bytes, start: int):
    """``(offset, opcode, content start, content length)`` of the whole records of ``buf`` from ``start``;
    then one last ``(offset, None, 0, 0)`` at the first record that is not whole (or the end)."""
    pos = start
    while pos + 9 <= len(buf):
        op, n = buf[pos], struct.unpack_from("<Q", buf, pos + 1)[0]
        if pos + 9 + n > len(buf):
            break
        yield pos, op, pos + 9, n
        pos += 9 + n
    yield pos, None, 0, 0


def _salvage_mcap(path: Path, buf: bytes) -> SalvagedBag:
    bag = SalvagedBag(path, ros1=False, size_bytes=len(buf))
    schemas: dict[int, tuple[str, str, str]] = {}

    def record(op: int, content: bytes, chunk: int | None, start: int) -> None:
        b = BytesIO(content)
        if op == 0x03:
            (sid,) = struct.unpack("<H", b.read(2))
            name, encoding = _string(b), _string(b)
            (n,) = struct.unpack("<I", b.read(4))
            schemas[sid] = (name, encoding, b.read(n).decode())
        elif op == 0x04:
            cid, sid = struct.unpack("<HH", b.read(4))
            topic = _string(b)
            if sid in schemas and cid not in {c.id for c in bag.connections}:
                name, encoding, data = schemas[sid]
                bag.connections.append(SalvagedConnection(cid, topic, name, data, "msg" if encoding == "ros2msg" else "idl"))
        elif op == 0x05:
            cid, _, log_time = struct.unpack_from("<HIQ", content, 0)
            bag._messages.append(_Location(log_time, cid, chunk, start + 22, len(content) - 22))

    whole = len(MCAP_MAGIC)
    for pos, op, s, n in _mcap_records(buf, len(MCAP_MAGIC)):
        if op is None:
            whole = pos
            break
        if op == 0x06:
            b = BytesIO(buf[s : s + n])
            _, _, size, crc = struct.unpack("<QQQI", b.read(28))
            compression = _string(b)
            (clen,) = struct.unpack("<Q", b.read(8))
            at = s + b.tell()
            bag._chunks[pos] = (compression, at, clen, size, crc)
            raw = _decompress(False, compression, buf[at : at + clen], size, crc)
            for _, cop, cs, cn in _mcap_records(raw, 0):
                if cop is None:
                    break
                record(cop, raw[cs : cs + cn], pos, cs)
        elif op in (0x03, 0x04, 0x05):
            record(op, buf[s : s + n], None, s)
        whole = s + n
        if op == 0x02:  # the footer: the file is whole
            break
    bag.whole_bytes = _with_partial_mcap_chunk(bag, buf, whole, record)
    return bag


def _with_partial_mcap_chunk(bag: SalvagedBag, buf: bytes, whole: int, record) -> int:
    """The records of an uncompressed chunk cut short at ``whole``, as far as they are whole; the new end of the whole part."""
    if whole + 9 + 40 > len(buf) or buf[whole] != 0x06:
        return whole
    b = BytesIO(buf[whole + 9 :])
    b.read(28)
    if _string(b) != "":
        return whole
    b.read(8)
    start = whole + 9 + b.tell()
    end = whole
    for _, op, s, n in _mcap_records(buf, start):
        if op is None:
            break
        record(op, buf[s : s + n], None, s)
        end = s + n
    return end


# ----------------------------------------------------------------------------------------------


def _typestore_of(connections: list[SalvagedConnection]):
    """A typestore with the bags' own message definitions."""
    from rosbags.typesys import Stores, get_types_from_idl, get_types_from_msg, get_typestore

    types: dict = {}
    for c in connections:
        if c.msgdef_format == "msg":
            types.update(get_types_from_msg(c.msgdef, c.msgtype))
        else:
            separator = "=" * 80 + "\n"
            parts = c.msgdef.split(separator)[1:] if c.msgdef.startswith(separator + "IDL: ") else [c.msgdef]
            for part in parts:
                types.update(get_types_from_idl(part.split("\n", 1)[1] if part.startswith("IDL: ") else part))
    store = get_typestore(Stores.EMPTY)
    store.register(types)
    return store


def mcap_file_of(path: Path) -> Path | None:
    """The MCAP file of ``path`` (a ``.mcap`` file, or a ROS 2 bag folder holding one), None when it has none."""
    if path.is_file():
        return path if path.suffix == ".mcap" else None
    files = sorted(path.glob("*.mcap")) if path.is_dir() else []
    return files[0] if len(files) == 1 else None


def salvage_bag(path: Path) -> SalvagedBag | None:
    """The whole part of the ROS 1 bag or MCAP file at ``path`` read sequentially; None when it is
    neither format or holds no whole message."""
    path = Path(path)
    mcap = mcap_file_of(path)
    target = mcap if mcap is not None else path
    if not target.is_file():
        return None
    with target.open("rb") as f:
        if target.stat().st_size < len(ROS1_MAGIC):
            return None
        buf = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)  # read as needed, not all into memory
        try:
            if buf[: len(ROS1_MAGIC)] == ROS1_MAGIC:
                bag = _salvage_ros1(target, buf)
            elif buf[: len(MCAP_MAGIC)] == MCAP_MAGIC:
                bag = _salvage_mcap(target, buf)
            else:
                return None
        finally:
            buf.close()
    if not bag._messages:
        return None
    bag._typestore = _typestore_of(bag.connections)
    return bag


__all__ = ["SalvagedBag", "SalvagedConnection", "mcap_file_of", "salvage_bag"]
