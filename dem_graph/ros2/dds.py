"""A participant of a ROS 2 graph over Eclipse Cyclone DDS (the ``cyclonedds`` wheel, its C library
bundled), with no ROS installation.

A ROS 2 node is a DDS participant; its publishers and subscriptions are DDS writers and readers on
the topics and types :mod:`~dem_graph.ros2.messages` names. :class:`Participant` makes them so that
a ROS 2 node of any distribution from Humble on matches them:

- the DDS type of each message is made from rosbags' definition of it (every struct final, no key
  field), so that the type a writer announces is the ROS 2 message's;
- writers and readers carry the data representation XCDR1 only, and USER_DATA
  ``typehash=RIHS01_...;`` (Iron and later read it; Humble ignores it);
- the bytes are rosbags' CDR (:class:`~dem_graph.ros2.messages.Codec`), handed to Cyclone as they
  are (Cyclone's own Python serialiser is not on the path: a 640x480 image costs it far more);
- a reader whose QoS no writer on its topic satisfies, or a writer none of whose readers it
  satisfies, is reported once per topic and policy (a warning, and :attr:`Participant.incompatible`).

The domain is ``ROS_DOMAIN_ID`` (unset or empty: 0), read as ROS 2 reads it; ``CYCLONEDDS_URI``
configures Cyclone as it does under rmw_cyclonedds; without it, ``ROS_LOCALHOST_ONLY=1`` or
``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`` keep the traffic on the loopback interface.
"""

from __future__ import annotations

import logging
import os
import threading
import time
from dataclasses import dataclass

from dem_graph.errors import ConfigError
from dem_graph.optional import import_cyclonedds
from dem_graph.ros2.messages import Codec, dds_topic_name, dds_type_name
from dem_graph.ros2.qos import POLICY_NAMES, QosProfile

log = logging.getLogger(__name__)

MAX_DOMAIN_ID = 232  # rmw's bound (the RTPS ports of a larger domain leave the 16-bit range)
LINUX_SAFE_DOMAIN_ID = 101  # above this, Linux's ephemeral ports may clash with DDS's (ROS 2's documentation)

LOOPBACK_CONFIG = """<?xml version="1.0" encoding="UTF-8" ?>
<CycloneDDS xmlns="https://cdds.io/config">
  <Domain Id="any">
    <General>
      <Interfaces><NetworkInterface name="lo"/></Interfaces>
      <AllowMulticast>false</AllowMulticast>
    </General>
    <Discovery>
      <ParticipantIndex>auto</ParticipantIndex>
      <MaxAutoParticipantIndex>60</MaxAutoParticipantIndex>
      <Peers><Peer address="127.0.0.1"/></Peers>
    </Discovery>
  </Domain>
</CycloneDDS>
"""
"""Cyclone bound to the loopback interface, discovery by unicast to this machine (``lo`` has no multicast)."""


def ros_domain_id(environ: dict | None = None) -> int:
    """``ROS_DOMAIN_ID`` as ROS 2 reads it: unset or empty is 0; otherwise an integer 0-232 (a
    :class:`ConfigError` naming the variable for anything else)."""
    text = (os.environ if environ is None else environ).get("ROS_DOMAIN_ID", "").strip()
    if not text:
        return 0
    try:
        value = int(text)
    except ValueError:
        raise ConfigError(f"ROS_DOMAIN_ID={text!r} is not a number: give an integer 0-{MAX_DOMAIN_ID} (or leave it unset for 0)") from None
    if not 0 <= value <= MAX_DOMAIN_ID:
        raise ConfigError(f"ROS_DOMAIN_ID={value} is out of range: 0-{MAX_DOMAIN_ID}")
    if value > LINUX_SAFE_DOMAIN_ID:
        log.warning("ROS_DOMAIN_ID=%d: above %d, Linux's ephemeral ports may clash with DDS's (ROS 2 recommends 0-%d)", value, LINUX_SAFE_DOMAIN_ID, LINUX_SAFE_DOMAIN_ID)
    return value


def localhost_only(environ: dict | None = None) -> bool:
    """Whether the environment asks ROS 2 to stay on this machine (``ROS_LOCALHOST_ONLY=1``, Humble and
    Iron; ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``, Jazzy on)."""
    env = os.environ if environ is None else environ
    return env.get("ROS_LOCALHOST_ONLY", "").strip() == "1" or env.get("ROS_AUTOMATIC_DISCOVERY_RANGE", "").strip().upper() == "LOCALHOST"


@dataclass
class Received:
    """One message as it came: its CDR bytes, the writer's source time and the time it was taken (ns since the epoch)."""

    data: bytes
    source_ns: int
    received_ns: int


class _Endpoint:
    """What a writer and a reader share: the topic, its type, the QoS and the time spent in DDS."""

    def __init__(self, participant: Participant, topic: str, msgtype: str, qos: QosProfile):
        self.participant, self.topic, self.msgtype, self.qos = participant, topic, msgtype, qos
        self.count = 0
        self.bytes = 0
        self.seconds = 0.0  # time spent encoding, decoding and in Cyclone's write or take

    def _dds_qos(self, dds, ignore_local: bool = False):
        P = dds.qos.Policy
        policies = [P.IgnoreLocal.Participant] if ignore_local else []  # a reader does not take this participant's own writers' messages (its own /tf)
        policies += [
            P.Reliability.Reliable(max_blocking_time=100_000_000) if self.qos.reliable else P.Reliability.BestEffort,
            P.Durability.TransientLocal if self.qos.transient_local else P.Durability.Volatile,
            P.History.KeepLast(max(int(self.qos.depth), 1)),
            P.DataRepresentation(use_cdrv0_representation=True),
            P.Userdata(data=f"typehash={self.participant.codec.type_hash(self.msgtype)};".encode()),
        ]
        return dds.qos.Qos(*policies)


class Writer(_Endpoint):
    """A ROS 2 publisher: :meth:`publish` a message, or :meth:`publish_bytes` its CDR."""

    def __init__(self, participant: Participant, topic: str, msgtype: str, qos: QosProfile):
        super().__init__(participant, topic, msgtype, qos)
        dds = participant.dds
        listener = dds.core.Listener(on_offered_incompatible_qos=lambda _w, status: participant._incompatible("publisher", topic, status))
        self._writer = dds.pub.DataWriter(participant.dp, participant.topic(topic, msgtype), qos=self._dds_qos(dds), listener=listener)
        self._write = participant._clayer.ddspy_write

    def publish(self, message) -> bytes:
        """Encode ``message`` and write it; its bytes are returned."""
        t0 = time.perf_counter()
        data = self.participant.codec.encode(message, self.msgtype)
        self._send(data, t0)
        return data

    def publish_bytes(self, data: bytes) -> None:
        """Write CDR bytes as they are (an encapsulation header first)."""
        self._send(data, time.perf_counter())

    def _send(self, data: bytes, t0: float) -> None:
        ret = self._write(self._writer._ref, data)
        self.seconds += time.perf_counter() - t0
        if ret is not None and ret < 0:
            log.warning("%s: DDS write failed (return code %d): message dropped", self.topic, ret)
            return
        self.count += 1
        self.bytes += len(data)

    def matched(self) -> int:
        """Subscriptions matched now."""
        return int(self._writer.get_publication_matched_status().current_count)


class Reader(_Endpoint):
    """A ROS 2 subscription taking raw CDR (:meth:`take`); decode with the participant's codec."""

    def __init__(self, participant: Participant, topic: str, msgtype: str, qos: QosProfile):
        super().__init__(participant, topic, msgtype, qos)
        dds = participant.dds
        listener = dds.core.Listener(on_requested_incompatible_qos=lambda _r, status: participant._incompatible("subscription", topic, status))
        self._reader = dds.sub.DataReader(participant.dp, participant.topic(topic, msgtype), qos=self._dds_qos(dds, ignore_local=True), listener=listener)
        self._take = participant._clayer.ddspy_take
        self.condition = dds.core.ReadCondition(self._reader, dds.core.SampleState.Any | dds.core.ViewState.Any | dds.core.InstanceState.Any)
        self.invalid = 0  # samples without data (a writer gone: its instance unregistered)

    def take(self, max_samples: int = 64) -> list[Received]:
        """The messages waiting, oldest first (at most ``max_samples``)."""
        t0 = time.perf_counter()
        samples = self._take(self._reader._ref, self._mask, max_samples)
        now_ns = time.time_ns()
        out = []
        if isinstance(samples, int):  # a negative DDS return code
            log.warning("%s: DDS take failed (return code %d)", self.topic, samples)
            return out
        for data, info in samples:
            if not info.valid_data:
                self.invalid += 1
                continue
            out.append(Received(bytes(data), int(info.source_timestamp), now_ns))
            self.bytes += len(data)
        self.count += len(out)
        self.seconds += time.perf_counter() - t0
        return out

    def take_all(self, batch: int = 256) -> list[Received]:
        """Every message waiting, oldest first."""
        out = self.take(batch)
        while len(out) and len(out) % batch == 0:
            more = self.take(batch)
            if not more:
                break
            out.extend(more)
        return out

    @property
    def _mask(self) -> int:
        return self.condition.mask

    def matched(self) -> int:
        """Publishers matched now."""
        return int(self._reader.get_subscription_matched_status().current_count)


class Participant:
    """This process on the ROS 2 graph: one DDS participant in ``domain_id`` (None: ``ROS_DOMAIN_ID``).

    Make writers and readers with :meth:`writer` and :meth:`reader`; :meth:`wait` blocks until a
    reader has data (or :meth:`wake` is called, from any thread); :meth:`close` leaves the graph."""

    def __init__(self, domain_id: int | None = None, codec: Codec | None = None):
        self.dds = _modules()
        from cyclonedds import _clayer

        self._clayer = _clayer
        self.codec = codec or Codec()
        self.domain_id = ros_domain_id() if domain_id is None else int(domain_id)
        self._domain = None
        if not os.environ.get("CYCLONEDDS_URI") and localhost_only():
            self._domain = self.dds.domain.Domain(self.domain_id, LOOPBACK_CONFIG)
        P = self.dds.qos.Policy
        self.dp = self.dds.domain.DomainParticipant(self.domain_id, qos=self.dds.qos.Qos(P.Userdata(data=b"enclave=/;")))
        self._topics: dict[str, object] = {}
        self._types: dict[str, type] = {}
        self._waitset = self.dds.core.WaitSet(self.dp)
        self._guard = self.dds.core.GuardCondition(self.dp)
        self._waitset.attach(self._guard)
        self.readers: list[Reader] = []
        self.writers: list[Writer] = []
        self.incompatible: list[str] = []  # one line per topic and policy
        self._reported: set[tuple[str, str, int]] = set()
        self._lock = threading.Lock()

    # --- endpoints --------------------------------------------------------------------------
    def topic(self, topic: str, msgtype: str):
        """The DDS topic of the ROS 2 ``topic`` (made once per name)."""
        name = dds_topic_name(topic)
        if name not in self._topics:
            self._topics[name] = self.dds.topic.Topic(self.dp, name, self._idl_type(msgtype))
        return self._topics[name]

    def writer(self, topic: str, msgtype: str, qos: QosProfile) -> Writer:
        self.codec.warm_up(msgtype)
        w = Writer(self, topic, msgtype, qos)
        self.writers.append(w)
        return w

    def reader(self, topic: str, msgtype: str, qos: QosProfile) -> Reader:
        self.codec.warm_up(msgtype)
        r = Reader(self, topic, msgtype, qos)
        self._waitset.attach(r.condition)
        self.readers.append(r)
        return r

    # --- waiting ----------------------------------------------------------------------------
    def wait(self, timeout_s: float) -> bool:
        """Block until a reader has data or :meth:`wake` was called, at most ``timeout_s``; True if woken."""
        woken = self._waitset.wait(max(int(timeout_s * 1e9), 0)) > 0
        if self._guard.read():
            self._guard.set(False)
        return woken

    def wake(self) -> None:
        """End a :meth:`wait` now (safe from any thread or a signal handler's)."""
        self._guard.set(True)

    def close(self) -> None:
        """Leave the graph: the participant and its writers and readers are deleted."""
        dp, self.dp = self.dp, None
        if dp is not None:
            del self._waitset, self._guard
            self.readers.clear()
            self.writers.clear()
            self._topics.clear()
            del dp

    # --- types and reports ------------------------------------------------------------------
    def _idl_type(self, msgtype: str):
        """A Cyclone IDL struct of ``msgtype`` made from rosbags' definition (nested types made too)."""
        if msgtype in self._types:
            return self._types[msgtype]
        from rosbags.typesys.store import Nodetype

        types = self.dds.idl.types
        base = {
            "bool": bool, "byte": types.uint8, "char": types.uint8, "int8": types.int8, "uint8": types.uint8, "int16": types.int16, "uint16": types.uint16,
            "int32": types.int32, "uint32": types.uint32, "int64": types.int64, "uint64": types.uint64, "float32": types.float32, "float64": types.float64,
            "string": str, "wstring": str,
        }

        def field_type(node):
            kind, detail = node
            if kind == Nodetype.BASE:
                name, bound = detail
                return types.bounded_str[bound] if name in ("string", "wstring") and bound else base[name]
            if kind == Nodetype.NAME:
                return self._idl_type(detail)
            if kind == Nodetype.ARRAY:
                return types.array[field_type(detail[0]), detail[1]]
            return types.sequence[field_type(detail[0]), detail[1]] if detail[1] else types.sequence[field_type(detail[0])]

        _consts, fields = self.codec.store.fielddefs[msgtype]
        members = {name: field_type(node) for name, node in fields}
        if not members:  # an empty ROS message is a struct with one uint8 (rosidl's structure_needs_at_least_one_member)
            members = {"structure_needs_at_least_one_member": types.uint8}
        dotted = dds_type_name(msgtype).replace("::", ".")
        cls = self.dds.idl.make_idl_struct(msgtype.replace("/", "_"), dotted, members)
        self._types[msgtype] = cls
        return cls

    def _incompatible(self, side: str, topic: str, status) -> None:
        """Cyclone's listener thread: a writer or reader on ``topic`` whose QoS does not match ours."""
        policy = int(status.last_policy_id)
        key = (side, topic, policy)
        with self._lock:
            if key in self._reported:
                return
            self._reported.add(key)
            name = POLICY_NAMES.get(policy, f"policy {policy}")
            other = "a subscription" if side == "publisher" else "a publisher"
            line = f"{topic}: {other} with incompatible QoS ({name}) does not match this {side}"
            self.incompatible.append(line)
        log.warning("%s (ros2 topic info -v %s shows the endpoints' QoS)", line, topic)


def _modules():
    """The cyclonedds modules used here, imported (a MissingDependencyError naming the extra when absent)."""
    import_cyclonedds()
    import cyclonedds.core
    import cyclonedds.domain
    import cyclonedds.idl
    import cyclonedds.idl.types
    import cyclonedds.pub
    import cyclonedds.qos
    import cyclonedds.sub
    import cyclonedds.topic

    return cyclonedds


__all__ = ["LOOPBACK_CONFIG", "Participant", "Reader", "Received", "Writer", "localhost_only", "ros_domain_id"]
