"""ROS 1 and ROS 2 bags as a :class:`Sequence`, read with the ``rosbags`` package (``pip install rosbags``).

The user names the topics and gives the rig (a rig YAML, :func:`~dem_graph.geometry.rig.load_rig`):

- ``image_topic``: ``sensor_msgs/Image`` (encodings mono8, bgr8, rgb8, bgra8, rgba8; colour becomes
  BGR) or ``sensor_msgs/CompressedImage`` (decoded by OpenCV);
- ``scan_topic``: ``sensor_msgs/LaserScan``; its ``angle_min``, ``angle_increment`` and beam count
  must be the rig's planar beams (else a :class:`DatasetError` naming the topic). A range that is not
  finite or lies outside ``[range_min, range_max]`` becomes NaN (no return);
- ``odometry_topic`` (optional): ``nav_msgs/Odometry``; each message after the first gives the
  increment ``inv(T_odom_base_prev) @ T_odom_base_curr`` of its ``child_frame_id``, moved into the body
  frame when tf knows ``body_frame`` -> child frame, else taken as the body's own; its covariance is
  the rig's odometry model for the distance travelled. The messages' own covariances are of the
  absolute pose in the odometry frame, often placeholders, and are not used: one warning says how
  many are not covariances at all (all-zero ones, ROS's "unknown", are fine);
- ``imu_topic`` (optional): ``sensor_msgs/Imu``; each message is an
  :class:`~dem_graph.datasets.events.ImuSample` at its header stamp, ``angular_velocity`` its gyro
  (rad/s) and ``linear_acceleration`` its specific force (m/s^2), in the messages' ``header.frame_id``
  frame (message 0's; a warning when others name another). The rig must have an ``imu`` section (its noise figures; else a :class:`DatasetError`). The
  orientation and the covariances are not used (ROS's all-zero "unknown" and -1 "not provided" are
  fine). A message with a value that is not finite is skipped, with one warning counting them;
- ``/tf_static`` and ``/tf``: when ``body_frame`` with ``camera_frame`` and/or ``laser_frame`` are given
  and the transforms link them, ``T_body_cam`` / ``T_body_laser`` come from there instead of the rig;
  likewise ``T_body_imu`` when they link ``body_frame`` to the IMU messages' frame.

Times are the messages' header stamps, seconds. Every stream must be in increasing time order, with
no jump forward longer than :attr:`~dem_graph.datasets.checks.InputChecks.max_gap_s` between two
messages (a clock fault: refused). Odometry increments beyond the vehicle's motion are skipped and
camera frames without texture marked (:mod:`dem_graph.datasets.checks`), each with a warning; a bag
with no laser scan is warned of. The bag has no ground truth; the initial pose is the identity at
the first event's time. Scans, odometry and IMU samples are read when the bag is opened, images (with their stamps) once then again lazily while
:meth:`RosbagSequence.events` iterates; at equal times the events come odometry, laser, camera, then IMU.
"""

from __future__ import annotations

import logging
from collections import deque
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import cv2
import numpy as np

from dem_graph.datasets.base import (
    CAMERA_STREAM,
    IMU_STREAM,
    LASER_STREAM,
    ODOMETRY_STREAM,
    Sequence,
    first_not_increasing,
    merged_order,
)
from dem_graph.datasets.checks import (
    InputChecks,
    TextureWatch,
    check_image_size,
    check_time_jumps,
    covariance_problems,
    plausible_increments,
    unknown_covariances,
    warn_if_no_laser,
)
from dem_graph.datasets.events import CameraFrame, Event, ImuSample, LaserScan, Odometry
from dem_graph.errors import DatasetError, MissingDependencyError
from dem_graph.geometry.rig import OdometrySpec, PlanarBeams, SensorRig, rig_from_dict
from dem_graph.geometry.se3 import invert, make_pose, matrix_from_quat_xyzw, nearest_pose
from dem_graph.optional import import_rosbags_highlevel

log = logging.getLogger(__name__)

IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
SCAN_TYPE = "sensor_msgs/msg/LaserScan"
ODOMETRY_TYPE = "nav_msgs/msg/Odometry"
IMU_TYPE = "sensor_msgs/msg/Imu"  # AnyReader gives ROS 1's sensor_msgs/Imu this name too
TF_TOPICS = ("/tf_static", "/tf")


def _anyreader():
    return import_rosbags_highlevel().AnyReader


def stamp_s(header) -> float:
    """A header's stamp in seconds (ROS 1 and ROS 2 stamps both have ``sec`` and ``nanosec`` in rosbags)."""
    return float(header.stamp.sec) + 1e-9 * float(header.stamp.nanosec)


def image_from_message(msg, msgtype: str, where: str) -> np.ndarray:
    """(H,W) grey or (H,W,3) BGR uint8 image of an Image or CompressedImage message."""
    if msgtype.endswith("CompressedImage"):
        image = cv2.imdecode(np.frombuffer(bytes(msg.data), dtype=np.uint8), cv2.IMREAD_UNCHANGED)
        if image is None:
            raise DatasetError(where, f"compressed image ({msg.format}) cannot be decoded")
        if image.ndim == 3 and image.shape[2] == 4:
            image = cv2.cvtColor(image, cv2.COLOR_BGRA2BGR)
        if image.dtype != np.uint8:
            raise DatasetError(where, f"8-bit images only, got {image.dtype}")
        return image
    channels = {"mono8": 1, "8UC1": 1, "bgr8": 3, "rgb8": 3, "8UC3": 3, "bgra8": 4, "rgba8": 4}
    enc = str(msg.encoding)
    if enc not in channels:
        raise DatasetError(where, f"image encoding {enc!r} is not supported (mono8, bgr8, rgb8, bgra8, rgba8)")
    c, h, w, step = channels[enc], int(msg.height), int(msg.width), int(msg.step)
    data = np.frombuffer(bytes(msg.data), dtype=np.uint8)
    if step < w * c or data.size < h * step:
        raise DatasetError(where, f"image data of {data.size} bytes is too short for {w}x{h} {enc} with step {step}")
    rows = data[: h * step].reshape(h, step)[:, : w * c]
    image = rows.reshape(h, w) if c == 1 else rows.reshape(h, w, c)
    if enc == "rgb8":
        image = image[:, :, ::-1]
    elif enc == "bgra8":
        image = image[:, :, :3]
    elif enc == "rgba8":
        image = image[:, :, 2::-1]
    return np.ascontiguousarray(image)


def ranges_from_scan(msg) -> np.ndarray:
    """(B,) float32 ranges, NaN where not finite or outside ``[range_min, range_max]``."""
    r = np.array(msg.ranges, dtype=np.float32)
    with np.errstate(invalid="ignore"):
        bad = ~np.isfinite(r) | (r < np.float32(msg.range_min)) | (r > np.float32(msg.range_max))
    r[bad] = np.nan
    return r


@contextmanager
def open_bag(path: str | Path) -> Iterator:
    """An open ``rosbags`` AnyReader on the ROS 1 or ROS 2 bag at ``path``; a bag it cannot open is a
    :class:`DatasetError` naming the path."""
    path = Path(path)
    if not path.exists():
        raise DatasetError(path, "bag not found")
    AnyReader = _anyreader()
    try:
        reader_cm = AnyReader([path])
        reader = reader_cm.__enter__()
    except MissingDependencyError:
        raise
    except Exception as exc:  # rosbags raises its own types for a bag it cannot read
        raise DatasetError(path, f"cannot open the bag ({type(exc).__name__}: {' '.join(str(exc).split())})") from None
    try:
        yield reader
    finally:
        reader_cm.__exit__(None, None, None)


def topic_where(path: str | Path, topic: str) -> str:
    """How errors name a topic of a bag."""
    return f"{path} topic {topic}"


def check_topic(reader, path: str | Path, topic: str, types: tuple[str, ...]) -> str:
    """The message type of ``topic``, which must be in the bag and one of ``types`` (else a :class:`DatasetError`)."""
    connections = [c for c in reader.connections if c.topic == topic]
    if not connections:
        present = ", ".join(sorted({c.topic for c in reader.connections})) or "none"
        raise DatasetError(path, f"no topic {topic!r} in the bag (topics: {present})")
    msgtype = connections[0].msgtype
    if msgtype not in types:
        raise DatasetError(topic_where(path, topic), f"has type {msgtype}, expected {' or '.join(types)}")
    return msgtype


def topic_messages(reader, topic: str, start_ns: int | None = None, stop_ns: int | None = None) -> Iterator[tuple[int, object]]:
    """``(bag time ns, deserialised message)`` of ``topic`` in bag order, between ``start_ns`` and ``stop_ns`` (excluded) when given."""
    connections = [c for c in reader.connections if c.topic == topic]
    for connection, t_ns, raw in reader.messages(connections=connections, start=start_ns, stop=stop_ns):
        yield t_ns, reader.deserialize(raw, connection.msgtype)


def check_increasing(t_s: np.ndarray, where: str) -> None:
    """A :class:`DatasetError` at ``where`` naming the first message whose stamp is not after the one before."""
    i = first_not_increasing(t_s)
    if i is not None:
        raise DatasetError(where, f"message {i}: time {t_s[i]!r} is not after the previous {t_s[i - 1]!r}")


def read_scan_topic(reader, topic: str, where: str, layout: tuple[float, float, int] | None = None, layout_name: str = "scan 0") -> tuple[np.ndarray, np.ndarray, tuple[float, float, int] | None]:
    """Every LaserScan of ``topic``: stamps (s, increasing), ranges (S, B; NaN where no return) and the
    beam layout ``(angle_min_rad, angle_increment_rad, count)``. Every scan must have ``layout`` (named
    ``layout_name`` in the error), or when it is None the first scan's; else a :class:`DatasetError` at ``where``."""
    times, ranges = [], []
    for _, msg in topic_messages(reader, topic):
        r = ranges_from_scan(msg)
        a_min, a_inc = float(msg.angle_min), float(msg.angle_increment)
        if layout is None:
            if not (np.isfinite(a_min) and np.isfinite(a_inc)) or a_inc <= 0 or len(r) < 2:
                raise DatasetError(where, f"scan 0 has {len(r)} beams from {a_min} rad every {a_inc} rad: not a scan")
            layout = (a_min, a_inc, len(r))
        elif len(r) != layout[2] or not np.isclose(a_min, layout[0], rtol=0, atol=1e-5) or not np.isclose(a_inc, layout[1], rtol=1e-5, atol=0):
            raise DatasetError(
                where,
                f"scan {len(times)} has {len(r)} beams from {a_min:.6f} rad every {a_inc:.6f} rad; "
                f"{layout_name} has {layout[2]} from {layout[0]:.6f} every {layout[1]:.6f}",
            )
        times.append(stamp_s(msg.header))
        ranges.append(r)
    t_s = np.array(times)
    check_increasing(t_s, where)
    return t_s, (np.stack(ranges) if ranges else np.zeros((0, layout[2] if layout else 0), dtype=np.float32)), layout


def _pose_from_msg(pose) -> np.ndarray:
    q = np.array([pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w], dtype=float)
    return make_pose(matrix_from_quat_xyzw(q / np.linalg.norm(q)), [pose.position.x, pose.position.y, pose.position.z])


def _transform_from_msg(t) -> np.ndarray:
    q = np.array([t.rotation.x, t.rotation.y, t.rotation.z, t.rotation.w], dtype=float)
    return make_pose(matrix_from_quat_xyzw(q / np.linalg.norm(q)), [t.translation.x, t.translation.y, t.translation.z])


class TransformTree:
    """Fixed transforms ``T_parent_child`` by frame names; :meth:`lookup` chains them either way."""

    def __init__(self):
        self._edges: dict[str, dict[str, np.ndarray]] = {}

    def add(self, parent: str, child: str, T_parent_child: np.ndarray) -> None:
        parent, child = parent.lstrip("/"), child.lstrip("/")
        if child in self._edges.get(parent, {}):
            return  # the first one seen stands
        self._edges.setdefault(parent, {})[child] = T_parent_child
        self._edges.setdefault(child, {})[parent] = invert(T_parent_child)

    def lookup(self, target: str, source: str) -> np.ndarray | None:
        """``T_target_source`` (maps ``source`` coordinates into ``target``), None when not linked."""
        target, source = target.lstrip("/"), source.lstrip("/")
        if target == source:
            return np.eye(4)
        seen = {target: np.eye(4)}
        queue = deque([target])
        while queue:
            frame = queue.popleft()
            for nxt, T in self._edges.get(frame, {}).items():
                if nxt not in seen:
                    seen[nxt] = seen[frame] @ T
                    if nxt == source:
                        return nearest_pose(seen[nxt])
                    queue.append(nxt)
        return None


class RosbagSequence(Sequence):
    """A ROS 1 (``.bag``) or ROS 2 (folder) bag read through ``rosbags``' AnyReader. See the module."""

    def __init__(
        self,
        path: str | Path,
        rig: SensorRig,
        image_topic: str,
        scan_topic: str,
        odometry_topic: str | None = None,
        body_frame: str | None = None,
        camera_frame: str | None = None,
        laser_frame: str | None = None,
        checks: InputChecks | None = None,
        imu_topic: str | None = None,
    ):
        self.input_checks = checks if checks is not None else InputChecks()
        self.path = Path(path)
        self.name = self.path.stem
        self._image_topic, self._scan_topic, self._odometry_topic = image_topic, scan_topic, odometry_topic
        self._imu_topic = imu_topic
        with open_bag(self.path) as reader:
            self._image_type = check_topic(reader, self.path, image_topic, IMAGE_TYPES)
            check_topic(reader, self.path, scan_topic, (SCAN_TYPE,))
            if odometry_topic is not None:
                check_topic(reader, self.path, odometry_topic, (ODOMETRY_TYPE,))
            if imu_topic is not None:
                check_topic(reader, self.path, imu_topic, (IMU_TYPE,))
                if rig.imu is None:
                    raise DatasetError(self._where(imu_topic), _NO_IMU_SECTION)
            tree = self._read_tf(reader)
            # every message's stamp (the checks), the finite samples, the messages' frame
            self._imu_msg_t_s, self._imu, imu_frame = self._read_imu(reader) if imu_topic is not None else (np.zeros(0), _no_imu(), None)
            rig = self._rig_with_tf(rig, tree, body_frame, camera_frame, laser_frame, imu_frame)
            self._rig = rig
            self._scan_t_s, self._scan_ranges = self._read_scans(reader)
            self._odometry = self._read_odometry(reader, tree, body_frame) if odometry_topic is not None else []
            self._frame_t_s = np.array([t for t, _ in self._iter_images(reader, decode=False)])
        self._check_time_jumps()
        warn_if_no_laser(self._where(scan_topic), self._scan_ranges, self._rig.laser)
        firsts = [a[0] for a in (self._frame_t_s, self._scan_t_s, self._imu["t_s"]) if len(a)] + [o.t_prev_s for o in self._odometry[:1]]
        self._t_start_s = float(min(firsts)) if firsts else 0.0

    def _check_time_jumps(self) -> None:
        """Refuse a clock fault in any stream (a jump forward beyond ``max_gap_s`` between two messages)."""
        streams = [(self._image_topic, self._frame_t_s), (self._scan_topic, self._scan_t_s)]
        if self._odometry_topic is not None:
            streams.append((self._odometry_topic, np.array([o.t_s for o in self._odometry])))
        if self._imu_topic is not None:
            streams.append((self._imu_topic, self._imu_msg_t_s))
        for topic, t_s in streams:
            check_time_jumps(self._where(topic), t_s, None, self.input_checks, lambda i: f"message {i}: time")

    # --------------------------------------------------------------------------------------------

    def _where(self, topic: str) -> str:
        return topic_where(self.path, topic)

    def _messages(self, reader, topic: str):
        for _, msg in topic_messages(reader, topic):
            yield msg

    def _read_tf(self, reader) -> TransformTree:
        tree = TransformTree()
        for topic in TF_TOPICS:
            if not any(c.topic == topic for c in reader.connections):
                continue
            for msg in self._messages(reader, topic):
                for tr in msg.transforms:
                    tree.add(tr.header.frame_id, tr.child_frame_id, _transform_from_msg(tr.transform))
        return tree

    def _rig_with_tf(
        self, rig: SensorRig, tree: TransformTree, body: str | None, camera: str | None, laser: str | None, imu: str | None = None
    ) -> SensorRig:
        """``rig`` with the extrinsics tf gives; ``imu``: the IMU messages' frame_id ("" when they name none)."""
        if body is None:
            return rig
        camera_spec, laser_spec, imu_spec = rig.camera, rig.laser, rig.imu
        if camera is not None:
            T = tree.lookup(body, camera)
            if T is None:
                log.warning("tf does not link %s to %s: T_body_cam from the rig", body, camera)
            else:
                camera_spec = camera_spec.model_copy(update={"T_body_cam": T})
        if laser is not None:
            T = tree.lookup(body, laser)
            if T is None:
                log.warning("tf does not link %s to %s: T_body_laser from the rig", body, laser)
            else:
                laser_spec = laser_spec.model_copy(update={"T_body_laser": T})
        if imu is not None and imu_spec is not None:
            T = tree.lookup(body, imu) if imu else None
            if T is None:
                log.warning("tf does not link %s to %s: T_body_imu from the rig", body, imu or f"the frame of {self._imu_topic} (its messages name none)")
            else:
                imu_spec = imu_spec.model_copy(update={"T_body_imu": T})
        return rig_from_dict(
            {
                **rig.model_dump(),
                "camera": camera_spec.model_dump(),
                "laser": laser_spec.model_dump(),
                "imu": imu_spec.model_dump() if imu_spec is not None else None,
            },
            f"{self.path} tf {body}",
        )

    def _read_scans(self, reader) -> tuple[np.ndarray, np.ndarray]:
        beams = self._rig.laser.beams
        where = self._where(self._scan_topic)
        if not isinstance(beams, PlanarBeams):
            raise DatasetError(where, "a LaserScan needs the rig's laser to have planar beams")
        layout = (beams.angle_min_rad, beams.angle_increment_rad, beams.count)
        t, ranges, _ = read_scan_topic(reader, self._scan_topic, where, layout, "the rig's laser")
        return t, ranges

    def _read_odometry(self, reader, tree: TransformTree, body: str | None) -> list[Odometry]:
        """The increments between consecutive messages, those beyond the vehicle's motion left out."""
        spec = self._rig.odometry or OdometrySpec()
        out: list[Odometry] = []
        prev = None
        times, covariances = [], []
        for msg in self._messages(reader, self._odometry_topic):
            t, T = stamp_s(msg.header), _pose_from_msg(msg.pose.pose)
            times.append(t)
            covariances.append(np.asarray(msg.pose.covariance, dtype=float).reshape(6, 6))
            if prev is not None:
                T_inc = invert(prev[1]) @ T
                T_body_base = tree.lookup(body, msg.child_frame_id) if body is not None and msg.child_frame_id else None
                if T_body_base is not None:
                    T_inc = T_body_base @ T_inc @ invert(T_body_base)
                T_inc = nearest_pose(T_inc)
                out.append(Odometry(t, prev[0], T_inc, spec.covariance_of(T_inc), len(out)))
            prev = (t, T)
        where = self._where(self._odometry_topic)
        self._check_increasing(np.array(times), self._odometry_topic)
        _warn_unused_covariances(where, np.array(covariances).reshape(-1, 6, 6))
        if not out:
            return out
        dt_s = np.array([o.t_s - o.t_prev_s for o in out])
        keep = plausible_increments(where, np.array([o.T_prev_curr for o in out]), dt_s, self.input_checks)
        return [o for o, k in zip(out, keep) if k]

    def _read_imu(self, reader) -> tuple[np.ndarray, dict[str, np.ndarray], str]:
        """Every message's stamp (increasing), the samples of those whose values are all finite (the
        others skipped, with one warning) and the messages' frame_id (message 0's; "" when it names none)."""
        where = self._where(self._imu_topic)
        times, values, frames = [], [], {}
        for i, msg in enumerate(self._messages(reader, self._imu_topic)):
            times.append(stamp_s(msg.header))
            w, a = msg.angular_velocity, msg.linear_acceleration
            values.append((w.x, w.y, w.z, a.x, a.y, a.z))
            frames.setdefault(str(msg.header.frame_id).lstrip("/"), i)
        t_s = np.array(times, dtype=float)
        self._check_increasing(t_s, self._imu_topic)
        v = np.array(values, dtype=float).reshape(-1, 6)
        frame = next(iter(frames), "")
        if len(frames) > 1:
            others = ", ".join(f"{f!r} from message {i}" for f, i in list(frames.items())[1:])
            log.warning("%s: the messages name %d frames (%r, then %s): all are taken to be in %r", where, len(frames), frame, others, frame)
        finite = np.all(np.isfinite(v), axis=1)
        if not np.all(finite):
            bad = np.flatnonzero(~finite)
            log.warning(
                "%s: %d of %d messages have an angular velocity or linear acceleration that is not finite (first: message %d): skipped",
                where,
                len(bad),
                len(v),
                int(bad[0]),
            )
        return t_s, {"t_s": t_s[finite], "gyro_rad_s": v[finite, :3], "accel_mps2": v[finite, 3:]}, frame

    def _iter_images(self, reader, decode: bool = True):
        where = self._where(self._image_topic)
        previous = -np.inf
        for i, msg in enumerate(self._messages(reader, self._image_topic)):
            t = stamp_s(msg.header)
            if not t > previous:
                raise DatasetError(where, f"message {i}: time {t!r} is not after the previous {previous!r}")
            previous = t
            yield t, (image_from_message(msg, self._image_type, where) if decode else None)

    def _check_increasing(self, t: np.ndarray, topic: str) -> None:
        check_increasing(t, self._where(topic))

    # --------------------------------------------------------------------------------------------

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
        return bool(self._odometry)

    @property
    def has_imu(self) -> bool:
        """Whether an IMU topic was given and holds a sample (in the rig's ``imu`` frame)."""
        return bool(len(self._imu["t_s"]))

    def event_count(self) -> int:
        return len(self._frame_t_s) + len(self._scan_t_s) + len(self._odometry) + len(self._imu["t_s"])

    def laser_scans(self) -> tuple[np.ndarray, np.ndarray]:
        return self._scan_t_s.copy(), self._scan_ranges.astype(float)

    def events(self) -> Iterator[Event]:
        """Odometry, scans, images and IMU samples merged by time (odometry, then laser, camera and IMU at equal times)."""
        with open_bag(self.path) as reader:
            # in the order of _frame_t_s; decoded here, not read ahead in a thread (base.read_ahead): the
            # ROS 2 bag's SQLite connection refuses to be used from another thread
            images = self._iter_images(reader)
            texture = TextureWatch(self._where(self._image_topic), self.input_checks)
            imu = self._imu
            for kind, i in merged_order([o.t_s for o in self._odometry], self._scan_t_s, self._frame_t_s, imu["t_s"]):
                if kind == ODOMETRY_STREAM:
                    yield self._odometry[i]
                elif kind == LASER_STREAM:
                    yield LaserScan(float(self._scan_t_s[i]), self._scan_ranges[i].copy(), i)
                elif kind == CAMERA_STREAM:
                    t, image = next(images)
                    check_image_size(f"{self._where(self._image_topic)} message {i}", image, self.rig.camera)
                    yield texture.frame(CameraFrame(t, image, i))
                elif kind == IMU_STREAM:
                    yield ImuSample(float(imu["t_s"][i]), imu["gyro_rad_s"][i].copy(), imu["accel_mps2"][i].copy(), i)

    def __repr__(self) -> str:
        return f"RosbagSequence({str(self.path)!r}, frames={len(self._frame_t_s)}, scans={len(self._scan_t_s)}, odometry={len(self._odometry)}, imu={len(self._imu['t_s'])})"


_NO_IMU_SECTION = (
    "an IMU topic needs the rig to have an imu section: add one to the rig YAML with T_body_imu, rate_hz, "
    "gyro_noise_density, accel_noise_density, gyro_bias_random_walk, accel_bias_random_walk, gyro_bias_sigma, accel_bias_sigma"
)


def _no_imu() -> dict[str, np.ndarray]:
    return {"t_s": np.zeros(0), "gyro_rad_s": np.zeros((0, 3)), "accel_mps2": np.zeros((0, 3))}


def _warn_unused_covariances(where: str, covariance: np.ndarray) -> None:
    """One warning when odometry messages carry pose covariances that are not covariances (all-zero
    ones, ROS's "unknown", are fine): they are not used, but say something of the driver."""
    known = np.flatnonzero(~unknown_covariances(covariance))
    bad = covariance_problems(covariance[known])
    if bad is None:
        return
    i, problem, count = bad
    log.warning(
        "%s: %d of %d messages carry a pose covariance that is not one (first: message %d, it %s); "
        "not used: the increments' covariances are the rig's odometry model",
        where,
        count,
        len(covariance),
        int(known[i]),
        problem,
    )


__all__ = [
    "RosbagSequence",
    "TransformTree",
    "check_increasing",
    "check_topic",
    "image_from_message",
    "open_bag",
    "ranges_from_scan",
    "read_scan_topic",
    "stamp_s",
    "topic_messages",
    "topic_where",
]
