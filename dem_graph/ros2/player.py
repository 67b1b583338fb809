"""``dem-graph ros2 play``: a ROS 1 or ROS 2 bag published on a ROS 2 graph at its own pace, as
``ros2 bag play`` does, so that the node can be tried on any recording without a robot.

- Each message goes out when its record time, counted from the bag's first, has passed on the wall
  clock (``rate`` times faster); its header stamps are the bag's (the robot's clock).
- A ROS 2 bag's bytes go out as recorded; a ROS 1 bag's messages are made ROS 2 messages of the same
  name field by field (ROS 1's header ``seq`` dropped, CameraInfo's ``D K R P`` as ``d k r p``,
  ``tf/tfMessage`` sent as ``tf2_msgs/TFMessage``). A type with no ROS 2 definition here is left
  out, said once.
- The QoS is the one ROS 2 drivers use: sensor data (best effort) for images, CameraInfo, scans,
  IMU and point clouds, tf2's for ``/tf`` and ``/tf_static`` (the latter latched), the default
  (reliable) for the rest.
"""

from __future__ import annotations

import csv
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path

from dem_graph.datasets.rosbag import open_bag
from dem_graph.errors import DatasetError
from dem_graph.progress import progress
from dem_graph.ros2.dds import Participant, Writer
from dem_graph.ros2.messages import CDR_LE_HEADER, Codec, MessageError
from dem_graph.ros2.qos import DEFAULT, SENSOR_DATA, TF, TF_STATIC, QosProfile

log = logging.getLogger(__name__)

SENSOR_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage", "sensor_msgs/msg/CameraInfo", "sensor_msgs/msg/LaserScan", "sensor_msgs/msg/Imu", "sensor_msgs/msg/PointCloud2")
ROS1_RENAMED = {"tf/msg/tfMessage": "tf2_msgs/msg/TFMessage"}
WAIT_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage", "sensor_msgs/msg/LaserScan")


@dataclass
class PlayOptions:
    """What ``dem-graph ros2 play`` takes."""

    bag: Path
    rate: float = 1.0  # times the recording's pace
    topics: tuple[str, ...] | None = None  # only these (None: every topic)
    wait_for_subscribers_s: float = 0.0  # wait up to this long for a subscription on the image and scan topics
    domain_id: int | None = None  # None: ROS_DOMAIN_ID
    timing_csv: Path | None = None  # every message's topic, header stamp and the time it was written (ns)


@dataclass
class PlayResult:
    messages: dict[str, int] = field(default_factory=dict)  # by topic
    duration_s: float = 0.0  # wall time from the first message to the last
    left_out: dict[str, str] = field(default_factory=dict)  # topic: why


def qos_for(topic: str, msgtype: str) -> QosProfile:
    """The QoS a ROS 2 driver publishes ``topic`` with (see the module)."""
    if topic == "/tf_static":
        return TF_STATIC
    if topic == "/tf":
        return TF
    return SENSOR_DATA if msgtype in SENSOR_TYPES else DEFAULT


def ros2_message(message, msgtype: str, codec: Codec):
    """A ROS 1 message (rosbags' object) as the ROS 2 message ``msgtype``, field by field by name
    (a field ROS 1 spells in capitals found too; one ROS 2 has and ROS 1 lacks left empty)."""
    from rosbags.typesys.store import Nodetype

    _consts, fields = codec.store.fielddefs[msgtype]
    empty = None
    values = {}
    for name, (kind, detail) in fields:
        value = getattr(message, name, None)
        if value is None:
            value = getattr(message, name.upper(), None)
        if value is None:
            empty = empty or codec._empty(msgtype)
            values[name] = getattr(empty, name)
            continue
        if kind == Nodetype.NAME:
            value = ros2_message(value, detail, codec)
        elif kind in (Nodetype.ARRAY, Nodetype.SEQUENCE) and detail[0][0] == Nodetype.NAME:
            value = [ros2_message(v, detail[0][1], codec) for v in value]
        values[name] = value
    return codec.message_class(msgtype)(**values)


def play_bag(options: PlayOptions, participant: Participant | None = None) -> PlayResult:
    """Publish the bag (see the module); returns what went out. Ctrl-C stops it."""
    own = participant is None
    participant = participant or Participant(options.domain_id, Codec())
    codec = participant.codec
    result = PlayResult()
    timing: list[tuple[str, int, int]] = []
    try:
        with open_bag(options.bag) as reader:
            ros2 = bool(getattr(reader, "is2", not getattr(reader, "ros1", False)))
            writers: dict[tuple[str, str], tuple[Writer, str, str]] = {}
            for c in reader.connections:
                if options.topics is not None and c.topic not in options.topics:
                    continue
                target = c.msgtype if ros2 else ROS1_RENAMED.get(c.msgtype, c.msgtype)
                if not codec.has(target):
                    result.left_out[c.topic] = f"{c.msgtype}: no ROS 2 definition here"
                    continue
                key = (c.topic, target)
                if key not in writers:
                    writers[key] = (participant.writer(c.topic, target, qos_for(c.topic, target)), c.msgtype, target)
            for topic, why in result.left_out.items():
                log.warning("%s: %s: left out", topic, why)
            if not writers:
                raise DatasetError(options.bag, "no topic of the bag can be published (see the warnings)")
            _wait_for_subscribers([w for w, src, tgt in writers.values() if tgt in WAIT_TYPES], options.wait_for_subscribers_s)
            connections = [c for c in reader.connections if (c.topic, c.msgtype if ros2 else ROS1_RENAMED.get(c.msgtype, c.msgtype)) in writers]
            by_connection = {id(c): writers[(c.topic, c.msgtype if ros2 else ROS1_RENAMED.get(c.msgtype, c.msgtype))] for c in connections}
            total = sum(1 for _ in reader.messages(connections=connections)) if connections else 0
            t0_bag = wall0 = None
            rate = max(float(options.rate), 1e-6)
            for c, t_ns, raw in progress(reader.messages(connections=connections), total=total, desc="play", unit="msg"):
                writer, source_type, target = by_connection[id(c)]
                if t0_bag is None:
                    t0_bag, wall0 = t_ns, time.perf_counter()
                wait_s = (t_ns - t0_bag) * 1e-9 / rate - (time.perf_counter() - wall0)
                if wait_s > 0:
                    time.sleep(wait_s)
                try:
                    data, message = _bytes_of(reader, raw, source_type, target, ros2, codec)
                except MessageError as exc:
                    result.left_out.setdefault(c.topic, str(exc))
                    log.warning("%s: %s: message skipped", c.topic, exc)
                    continue
                if options.timing_csv is not None:
                    message = message if message is not None else codec.decode(data, target)
                    header = getattr(message, "header", None)
                    stamp_ns = int(header.stamp.sec) * 10**9 + int(header.stamp.nanosec) if header is not None else -1
                    timing.append((c.topic, stamp_ns, time.time_ns()))
                writer.publish_bytes(data)
                result.messages[c.topic] = result.messages.get(c.topic, 0) + 1
            result.duration_s = time.perf_counter() - wall0 if wall0 is not None else 0.0
            _linger([w for w, _, _ in writers.values()])
    finally:
        if options.timing_csv is not None and timing:
            with open(options.timing_csv, "w", newline="") as fh:
                w = csv.writer(fh)
                w.writerow(["topic", "stamp_ns", "written_ns"])
                w.writerows(timing)
        if own:
            participant.close()
    return result


def _bytes_of(reader, raw, source_type: str, target: str, ros2: bool, codec: Codec):
    """The CDR bytes of one bag message (and the message when it had to be made)."""
    if ros2 and bytes(raw[:4]) == CDR_LE_HEADER:
        return bytes(raw), None
    try:
        message = reader.deserialize(raw, source_type)
    except Exception as exc:  # noqa: BLE001 - a damaged message costs that message
        raise MessageError(f"a {source_type} that cannot be read ({type(exc).__name__})") from None
    if not ros2:
        message = ros2_message(message, target, codec)
    return codec.encode(message, target), message


def _wait_for_subscribers(writers: list[Writer], timeout_s: float) -> None:
    """Wait until each of ``writers`` has a subscription (at most ``timeout_s``; said when one has none)."""
    if timeout_s <= 0 or not writers:
        return
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if all(w.matched() > 0 for w in writers):
            time.sleep(0.2)  # the subscriber's other readers come with the same discovery
            return
        time.sleep(0.02)
    missing = [w.topic for w in writers if not w.matched()]
    log.warning("no subscription on %s after %.1f s: playing anyway", ", ".join(missing), timeout_s)


def _linger(writers: list[Writer], max_s: float = 0.5) -> None:
    """A moment for the reliable writers' last messages to be acknowledged before the participant goes."""
    deadline = time.monotonic() + max_s
    while time.monotonic() < deadline:
        time.sleep(0.05)
        if not any(w.qos.reliable for w in writers):
            return


__all__ = ["PlayOptions", "PlayResult", "play_bag", "qos_for", "ros2_message"]
