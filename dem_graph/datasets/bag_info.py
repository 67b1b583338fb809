"""What a ROS bag holds, before a run (``dem-graph bag-info``): its topics with their types, message
counts, rates and frames; the topics a run would use; and the rig it would read (:mod:`~dem_graph.datasets.bag_rig`)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import yaml

from dem_graph.datasets.bag_rig import CAMERA_INFO_TYPE, BagTopics, camera_info_candidates, rate_hz, rig_of_bag, topic_times_ns
from dem_graph.datasets.rosbag import IMAGE_TYPES, IMU_TYPE, ODOMETRY_TYPE, SCAN_TYPE, open_bag, topic_messages
from dem_graph.errors import DemGraphError
from dem_graph.geometry.ground_view import laser_view
from dem_graph.geometry.rig import SensorRig, rig_to_dict


@dataclass
class TopicInfo:
    """One topic: its message type(s), how many messages, their rate (Hz, from the record times) and the first message's frame_id."""

    topic: str
    msgtype: str
    count: int
    rate_hz: float | None
    frame_id: str


@dataclass
class BagInfo:
    """A bag's topics, the topics proposed for a run, and the rig it would read (or why none)."""

    path: Path
    duration_s: float
    topics: list[TopicInfo]
    proposed: BagTopics | None
    rig: SensorRig | None = None
    rig_problem: str | None = None
    notes: list[str] = field(default_factory=list)

    def command(self) -> str | None:
        """The ``dem-graph run`` command line of the proposed topics, None without an image and a scan topic."""
        if self.proposed is None:
            return None
        flags = [("--image-topic", self.proposed.image_topic), ("--scan-topic", self.proposed.scan_topic)]
        flags += [("--odometry-topic", self.proposed.odometry_topic), ("--imu-topic", self.proposed.imu_topic)]
        return f"dem-graph run {self.path} " + " ".join(f"{k} {v}" for k, v in flags if v) + " --out RUN"

    def lines(self) -> list[str]:
        """The report as text: the topics table, the proposal, the rig as YAML."""
        width = max([len(t.topic) for t in self.topics] + [5])
        type_width = max([len(t.msgtype) for t in self.topics] + [4])
        out = [f"{self.path}: {len(self.topics)} topics, {self.duration_s:.1f} s", f"{'topic':<{width}}  {'type':<{type_width}}  {'messages':>8}  {'rate (Hz)':>9}  frame"]
        for t in self.topics:
            rate = f"{t.rate_hz:.2f}" if t.rate_hz is not None else "-"
            out.append(f"{t.topic:<{width}}  {t.msgtype:<{type_width}}  {t.count:>8}  {rate:>9}  {t.frame_id or '-'}")
        command = self.command()
        out.append(f"proposed: {command}" if command else "proposed: nothing (a run needs a sensor_msgs/Image or CompressedImage topic and a LaserScan topic)")
        out += [f"  {note}" for note in self.notes]
        if self.rig is not None:
            out.append(laser_view(self.rig).line())
            out.append("the rig it would read (save it, edit it, give it with --rig; every field overrides the bag's):")
            out += yaml.safe_dump(rig_to_dict(self.rig), sort_keys=False, default_flow_style=None).rstrip().splitlines()
        elif self.rig_problem:
            out.append(f"no rig: {self.rig_problem}")
        return out


def _first_frame(reader, topic: str, msgtype: str) -> str:
    if msgtype.startswith(("tf2_msgs/", "tf/")):
        return ""
    for _, msg in topic_messages(reader, topic):
        header = getattr(msg, "header", None)
        return str(header.frame_id) if header is not None else ""
    return ""


def _pick(topics: list[TopicInfo], types: tuple[str, ...], prefer=lambda t: 0) -> TopicInfo | None:
    """The topic of one of ``types`` that ``prefer`` ranks highest, then the one with the most messages."""
    found = [t for t in topics if t.msgtype in types]
    return max(found, key=lambda t: (prefer(t), t.count), default=None)


def propose_topics(topics: list[TopicInfo]) -> tuple[BagTopics | None, list[str]]:
    """The topics a run would use, and why when there is a choice: a raw image with its CameraInfo
    beside it before a compressed one, the LaserScan, Odometry and Imu topics with the most messages."""
    names = {t.topic: t.msgtype for t in topics}

    def image_rank(t: TopicInfo) -> tuple:
        has_info = any(names.get(c) == CAMERA_INFO_TYPE for c in camera_info_candidates(t.topic))
        return (has_info, t.msgtype.endswith("/Image"), "image_raw" in t.topic or "image_rect" in t.topic)

    image = _pick(topics, IMAGE_TYPES, image_rank)
    scan = _pick(topics, (SCAN_TYPE,))
    odometry = _pick(topics, (ODOMETRY_TYPE,), lambda t: "filtered" not in t.topic)
    imu = _pick(topics, (IMU_TYPE,))
    notes = []
    for kind, chosen, types in (("image", image, IMAGE_TYPES), ("scan", scan, (SCAN_TYPE,)), ("odometry", odometry, (ODOMETRY_TYPE,)), ("IMU", imu, (IMU_TYPE,))):
        others = [t.topic for t in topics if t.msgtype in types and chosen is not None and t.topic != chosen.topic]
        if others:
            notes.append(f"{kind}: {chosen.topic} proposed; also {', '.join(others)}")
    if image is None or scan is None:
        return None, notes
    return BagTopics(image.topic, scan.topic, odometry.topic if odometry else None, imu.topic if imu else None), notes


def bag_info(path: str | Path, rig_file: str | Path | None = None) -> BagInfo:
    """What the bag at ``path`` holds (:class:`BagInfo`); ``rig_file`` over its rig as a run would take it."""
    path = Path(path)
    with open_bag(path, quiet=True) as reader:
        types: dict[str, list[str]] = {}
        for c in reader.connections:
            if c.msgtype not in types.setdefault(c.topic, []):
                types[c.topic].append(c.msgtype)
        topics = []
        for topic in sorted(types):
            times = topic_times_ns(reader, topic)
            topics.append(TopicInfo(topic, " + ".join(types[topic]), len(times), rate_hz(times), _first_frame(reader, topic, types[topic][0])))
        duration_s = (reader.end_time - reader.start_time) * 1e-9 if topics else 0.0
        proposed, notes = propose_topics([t for t in topics if " + " not in t.msgtype])
        info = BagInfo(path, duration_s, topics, proposed, notes=notes)
        if proposed is not None:
            try:
                info.rig, derived = rig_of_bag(reader, path, proposed, rig_file)
                info.notes += derived.notes
            except DemGraphError as exc:
                info.rig_problem = str(exc)
    return info


__all__ = ["BagInfo", "TopicInfo", "bag_info", "propose_topics"]
