"""ROS messages as they arrive, one at a time, made into events by the bag readers' rules.

:class:`~dem_graph.datasets.rosbag.RosbagSequence` reads a whole bag; a live source (the ROS 2 node)
has one message at a time. The rules are the same, so that a live run over a bag's messages is the
bag run:

- an image (``Image``, ``CompressedImage``) that does not hold its declared size, is of another size
  than the rig's camera or cannot be decoded is skipped; a 16-bit stream keeps the bit depth of
  its first usable image; frames without texture or frozen are marked (:class:`TextureWatch`);
- a ``LaserScan`` of another beam layout than the rig's is skipped; ranges not finite or outside
  ``[range_min, range_max]`` are no return;
- each ``Odometry`` message after the first gives the increment from the one kept before it, moved
  into the body frame when tf links the body to the message's ``child_frame_id``, its covariance the
  rig's odometry model; a pose not finite is skipped, an increment beyond the vehicle's motion
  (:func:`~dem_graph.datasets.checks.plausible_increments`) left out;
- an ``Imu`` sample with a value not finite is skipped;
- in every stream, a message whose stamp is not after the last one kept is skipped.

Each skip is counted by stream and kind (:meth:`LiveStreams.skipped_messages`, the counters of
``metrics.json``) and warned about once per kind, then every hundredth time. Unlike a bag, a live
stream is never refused for its share of bad messages: one bad message costs that message.

:class:`MessageLog` holds the first messages of a live source with the interface of a bag reader
that :func:`~dem_graph.datasets.bag_rig.derive_rig` reads, so that the rig of a live source is
derived as a bag's is.
"""

from __future__ import annotations

import logging
from collections import Counter
from dataclasses import dataclass

import numpy as np

from dem_graph.datasets.bag_rig import BagTopics
from dem_graph.datasets.base import Sequence
from dem_graph.datasets.checks import (
    NONFINITE,
    STAMP_NOT_AFTER,
    WRONG_SHAPE,
    InputChecks,
    TextureWatch,
    check_image_size,
    plausible_increments,
)
from dem_graph.datasets.events import CameraFrame, ImuSample, LaserScan, Odometry
from dem_graph.datasets.rosbag import (
    TransformTree,
    _pose_from_msg,
    _pose_problem,
    image_depth_bits,
    image_from_message,
    ranges_from_scan,
    raw_image_problem,
    stamp_s,
)
from dem_graph.errors import DatasetError
from dem_graph.geometry.rig import OdometrySpec, PlanarBeams, SensorRig
from dem_graph.geometry.se3 import invert, nearest_pose

log = logging.getLogger(__name__)

CAMERA, LASER, ODOMETRY, IMU = "camera", "laser", "odometry", "imu"
"""The streams, as the counters name them (``camera_wrong_shape``, ``laser_stamp_not_after``, ...)."""


@dataclass(frozen=True)
class Connection:
    """A topic and its message type (what a bag reader's connection gives :mod:`~dem_graph.datasets.bag_rig`)."""

    topic: str
    msgtype: str


class MessageLog:
    """Decoded messages by topic, in arrival order, read as a bag reader is read (``connections``,
    ``messages``, ``deserialize``) by :func:`~dem_graph.datasets.bag_rig.derive_rig`. Times are the
    messages' header stamps, ns (a message without a header: its arrival time)."""

    def __init__(self):
        self._messages: dict[str, list[tuple[int, object]]] = {}
        self._connections: dict[str, Connection] = {}

    def add(self, topic: str, msgtype: str, t_ns: int, message) -> None:
        self._connections.setdefault(topic, Connection(topic, msgtype))
        self._messages.setdefault(topic, []).append((int(t_ns), message))

    def count(self, topic: str) -> int:
        return len(self._messages.get(topic, ()))

    def first(self, topic: str):
        entries = self._messages.get(topic)
        return entries[0][1] if entries else None

    def stamps_ns(self, topic: str) -> np.ndarray:
        return np.array([t for t, _ in self._messages.get(topic, ())], dtype=np.int64)

    @property
    def connections(self) -> list[Connection]:
        return list(self._connections.values())

    def messages(self, connections=None, start: int | None = None, stop: int | None = None):
        topics = [c.topic for c in (connections if connections is not None else self.connections)]
        for topic in topics:
            conn = self._connections[topic]
            for t_ns, message in self._messages.get(topic, ()):
                if (start is None or t_ns >= start) and (stop is None or t_ns < stop):
                    yield conn, t_ns, message

    @staticmethod
    def deserialize(raw, msgtype: str):
        """The message itself: it was decoded when it arrived."""
        return raw


class _Tally:
    """The skipped messages of one stream, by kind: counted, and warned about at the first and every hundredth."""

    def __init__(self, where: str, stream: str):
        self.where, self.stream = where, stream
        self.counts: Counter = Counter()

    def skip(self, kind: str, why: str) -> None:
        self.counts[kind] += 1
        n = self.counts[kind]
        if n == 1 or n % 100 == 0:
            log.warning("%s: %s: skipped (%d such messages so far)", self.where, why, n)


class LiveStreams:
    """Messages to events, one at a time, by the bag readers' rules (see the module). Each method
    returns the event, or None for a message that gives none (skipped; the first odometry message)."""

    def __init__(self, rig: SensorRig, topics: BagTopics, tree: TransformTree, body_frame: str | None, checks: InputChecks | None = None, where: str = "ros2"):
        self.rig, self.topics, self.tree, self.body_frame = rig, topics, tree, body_frame
        self.checks = checks or InputChecks()
        self.where = where
        self._tallies = {s: _Tally(f"{where} {t}", s) for s, t in ((CAMERA, topics.image_topic), (LASER, topics.scan_topic), (ODOMETRY, topics.odometry_topic), (IMU, topics.imu_topic)) if t}
        self._last_t = {CAMERA: -np.inf, LASER: -np.inf, ODOMETRY: -np.inf, IMU: -np.inf}
        self._kept = Counter()
        self._texture = TextureWatch(f"{where} {topics.image_topic}", self.checks)
        self._depth_bits: int | None = None
        self._depth_known = False
        self._odometry_prev: tuple[float, np.ndarray] | None = None
        self._odometry_spec = rig.odometry or OdometrySpec()
        beams = rig.laser.beams
        self._layout = (beams.angle_min_rad, beams.angle_increment_rad, beams.count) if isinstance(beams, PlanarBeams) else None

    # --- per stream -------------------------------------------------------------------------
    def image(self, msg, msgtype: str) -> CameraFrame | None:
        t_s = stamp_s(msg.header)
        where = f"{self.where} {self.topics.image_topic}"
        compressed = msgtype.endswith("CompressedImage")
        if not compressed:
            problem = raw_image_problem(msg, where)
            camera = self.rig.camera
            if problem is None and (int(msg.width), int(msg.height)) != (camera.width_px, camera.height_px):
                problem = f"image is {int(msg.width)}x{int(msg.height)} px but the rig's camera is {camera.width_px}x{camera.height_px} px"
            if problem is not None:
                return self._skip(CAMERA, WRONG_SHAPE, f"image at {t_s:.6f} s: {problem}")
        if not self._in_order(CAMERA, t_s):
            return None
        if not self._depth_known:
            self._depth_bits = image_depth_bits(msg, msgtype, where)
            self._depth_known = True
        try:
            image = image_from_message(msg, msgtype, where, self._depth_bits)
            if compressed:
                check_image_size(where, image, self.rig.camera)
        except DatasetError as exc:
            return self._skip(CAMERA, WRONG_SHAPE, f"image at {t_s:.6f} s: {exc.problem}")
        self._last_t[CAMERA] = t_s
        return self._texture.frame(CameraFrame(t_s, image, self._next(CAMERA)))

    def scan(self, msg) -> LaserScan | None:
        t_s = stamp_s(msg.header)
        layout = self._layout
        n, a_min, a_inc = len(msg.ranges), float(msg.angle_min), float(msg.angle_increment)
        if layout is not None and (n != layout[2] or not np.isclose(a_min, layout[0], rtol=0, atol=1e-5) or not np.isclose(a_inc, layout[1], rtol=1e-5, atol=0)):
            return self._skip(
                LASER, WRONG_SHAPE,
                f"scan at {t_s:.6f} s has {n} beams from {a_min:.6f} rad every {a_inc:.6f} rad; the rig's laser {layout[2]} from {layout[0]:.6f} every {layout[1]:.6f}",
            )
        if not self._in_order(LASER, t_s):
            return None
        self._last_t[LASER] = t_s
        return LaserScan(t_s, ranges_from_scan(msg), self._next(LASER))

    def odometry(self, msg) -> Odometry | None:
        t_s = stamp_s(msg.header)
        problem = _pose_problem(msg.pose.pose)
        if problem is not None:
            return self._skip(ODOMETRY, NONFINITE, f"odometry at {t_s:.6f} s: {problem}")
        if not self._in_order(ODOMETRY, t_s):
            return None
        self._last_t[ODOMETRY] = t_s
        pose = _pose_from_msg(msg.pose.pose)
        prev, self._odometry_prev = self._odometry_prev, (t_s, pose)
        if prev is None:
            return None
        T_inc = invert(prev[1]) @ pose
        child = str(msg.child_frame_id)
        T_body_base = self.tree.lookup(self.body_frame, child) if self.body_frame is not None and child else None
        if T_body_base is not None:
            T_inc = T_body_base @ T_inc @ invert(T_body_base)
        T_inc = nearest_pose(T_inc)
        if not plausible_increments(f"{self.where} {self.topics.odometry_topic}", T_inc[None], np.array([t_s - prev[0]]), self.checks)[0]:
            return None
        return Odometry(t_s, prev[0], T_inc, self._odometry_spec.covariance_of(T_inc), self._next(ODOMETRY))

    def imu(self, msg) -> ImuSample | None:
        t_s = stamp_s(msg.header)
        w, a = msg.angular_velocity, msg.linear_acceleration
        gyro, accel = np.array([w.x, w.y, w.z], dtype=float), np.array([a.x, a.y, a.z], dtype=float)
        if not self._in_order(IMU, t_s):
            return None
        self._last_t[IMU] = t_s  # (a bag's order check counts the samples not finite too)
        if not (np.all(np.isfinite(gyro)) and np.all(np.isfinite(accel))):
            return self._skip(IMU, NONFINITE, f"IMU sample at {t_s:.6f} s is not finite")
        return ImuSample(t_s, gyro, accel, self._next(IMU))

    # --- bookkeeping ------------------------------------------------------------------------
    def skipped_messages(self) -> dict[str, int]:
        """The messages skipped by stream and kind (``camera_wrong_shape``, ...), as a bag run counts them."""
        out = {f"{t.stream}_{kind}": n for t in self._tallies.values() for kind, n in t.counts.items()}
        return dict(sorted(out.items()))

    def _in_order(self, stream: str, t_s: float) -> bool:
        if np.isfinite(t_s) and t_s > self._last_t[stream]:
            return True
        self._skip(stream, STAMP_NOT_AFTER, f"stamp {t_s:.6f} s is not after the last message kept, {self._last_t[stream]:.6f} s")
        return False

    def _skip(self, stream: str, kind: str, why: str) -> None:
        self._tallies[stream].skip(kind, why)
        return None

    def _next(self, stream: str) -> int:
        i = self._kept[stream]
        self._kept[stream] += 1
        return i


class RecordedLive(Sequence):
    """A live source as a :class:`Sequence`: its rig and start, and what it delivered so far
    (laser scans, odometry and IMU samples; no images), for the run's configuration, metrics and
    DEM once it stops. :meth:`events` gives the recorded events (no camera frame)."""

    def __init__(self, rig: SensorRig, t_start_s: float, has_odometry: bool, has_imu: bool, name: str, streams: LiveStreams | None = None):
        self._rig, self._t_start_s, self._has_odometry, self._has_imu = rig, float(t_start_s), bool(has_odometry), bool(has_imu)
        self.name = name
        self.streams = streams
        self._scan_t: list[float] = []
        self._scan_ranges: list[np.ndarray] = []
        self._others: list = []

    def record(self, event) -> None:
        """Keep a scan (for the DEM), an odometry increment or an IMU sample given to the run."""
        if isinstance(event, LaserScan):
            self._scan_t.append(event.t_s)
            self._scan_ranges.append(np.asarray(event.ranges_m, dtype=np.float32))
        elif isinstance(event, (Odometry, ImuSample)):
            self._others.append(event)

    @property
    def rig(self) -> SensorRig:
        return self._rig

    @property
    def t_start_s(self) -> float:
        return self._t_start_s

    @property
    def T_world_body_initial(self) -> np.ndarray:
        return np.eye(4)

    @property
    def has_odometry(self) -> bool:
        return self._has_odometry

    @property
    def has_imu(self) -> bool:
        return self._has_imu

    def skipped_messages(self) -> dict[str, int]:
        return self.streams.skipped_messages() if self.streams is not None else {}

    def laser_scans(self) -> tuple[np.ndarray, np.ndarray]:
        beams = self._rig.laser.beams.count
        if not self._scan_t:
            return np.zeros(0), np.zeros((0, beams))
        return np.array(self._scan_t), np.array(self._scan_ranges, dtype=float)

    def event_count(self) -> int:
        return len(self._scan_t) + len(self._others)

    def events(self):
        scans = [LaserScan(t, r.copy(), i) for i, (t, r) in enumerate(zip(self._scan_t, self._scan_ranges))]
        return iter(sorted([*scans, *self._others], key=lambda e: e.t_s))


__all__ = ["CAMERA", "IMU", "LASER", "ODOMETRY", "Connection", "LiveStreams", "MessageLog", "RecordedLive"]
