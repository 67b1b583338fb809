"""ROS 1 and ROS 2 bags as a :class:`Sequence`, read with the ``rosbags`` package (``pip install rosbags``).

The user names the topics and gives the rig (a rig YAML, :func:`~dem_graph.geometry.rig.load_rig`):

- ``image_topic``: ``sensor_msgs/Image`` (mono8, bgr8, rgb8, bgra8, rgba8, colour becoming BGR; mono16,
  bayer_* and yuv422 made grey, 16-bit ones on the stream's bit depth; a depth or float encoding
  refused naming it) or ``sensor_msgs/CompressedImage`` (decoded by OpenCV; compressedDepth refused);
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

Times are the messages' header stamps, seconds. One bad message costs one message: a message with a
value that is not finite, a stamp not after its predecessor's (a duplicate, a message delivered
late) or not the stream's shape is skipped, one warning per kind, counted in
:meth:`RosbagSequence.skipped_messages` (``metrics.json``); a stream with more than
:attr:`~dem_graph.datasets.checks.InputChecks.max_skipped_fraction` of its messages skipped, or whose
clock jumps as a whole (forward beyond ``max_gap_s``, back for more than ``max_reordered_run``
messages), is refused. A ROS 1 bag without its index and an MCAP file without its summary are read
up to the damage (:mod:`~dem_graph.datasets.bag_salvage`). See ``docs/ros_bags.md``. Odometry increments beyond the vehicle's motion are skipped and
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

from dem_graph.datasets.bag_salvage import salvage_bag
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
    NONFINITE,
    STAMP_NOT_AFTER,
    WRONG_SHAPE,
    InputChecks,
    SkippedMessages,
    TextureWatch,
    check_image_size,
    check_time_jumps,
    covariance_problems,
    increasing_stamps,
    plausible_increments,
    time_text,
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


# bytes per pixel of the raw encodings read; the others are refused naming theirs
_PIXEL_BYTES = {"mono8": 1, "8UC1": 1, "bgr8": 3, "rgb8": 3, "8UC3": 3, "bgra8": 4, "rgba8": 4, "mono16": 2, "16UC1": 2, "yuv422": 2, "uyvy": 2, "yuv422_yuy2": 2, "yuyv": 2}
# ROS's bayer_rggb is the pattern of the first two rows' first two pixels; OpenCV names a Bayer
# pattern by the second row's second and third pixels: ROS rggb is OpenCV's BayerBG, and so on
_BAYER_TO_GREY = {
    "rggb": cv2.COLOR_BayerBG2GRAY,
    "bggr": cv2.COLOR_BayerRG2GRAY,
    "gbrg": cv2.COLOR_BayerGR2GRAY,
    "grbg": cv2.COLOR_BayerGB2GRAY,
}
for _pattern in _BAYER_TO_GREY:
    _PIXEL_BYTES[f"bayer_{_pattern}8"] = 1
    _PIXEL_BYTES[f"bayer_{_pattern}16"] = 2
SUPPORTED_ENCODINGS = tuple(_PIXEL_BYTES)


def pixel_bytes(encoding: str, where: str) -> int:
    """Bytes per pixel of a raw image ``encoding``; one that no estimator can use is a :class:`DatasetError` naming it."""
    if encoding not in _PIXEL_BYTES:
        raise DatasetError(
            where,
            f"image encoding {encoding!r} cannot be used (a depth or float image is not a camera's grey levels); "
            f"the encodings read: {', '.join(SUPPORTED_ENCODINGS)}",
        )
    return _PIXEL_BYTES[encoding]


def raw_image_problem(msg, where: str) -> str | None:
    """Why a raw Image message's data does not hold its declared image (too short, a step too small), None when it does."""
    c, h, w, step = pixel_bytes(str(msg.encoding), where), int(msg.height), int(msg.width), int(msg.step)
    size = len(msg.data)
    if step < w * c or size < h * step:
        return f"{size} bytes of data, too few for {w}x{h} px {msg.encoding} with a step of {step} bytes"
    return None


def grey_from_16bit(image16: np.ndarray, depth_bits: int) -> np.ndarray:
    """A 16-bit image of ``depth_bits`` significant bits (10 to 16) as 8-bit grey levels: its top 8 bits."""
    return (image16 >> np.uint16(max(depth_bits - 8, 0))).clip(0, 255).astype(np.uint8)


def depth_bits_of(image16: np.ndarray) -> int:
    """The bit depth of a 16-bit camera's images told from one of them: its largest value's, rounded
    up to 10, 12, 14 or 16 bits (what sensors give; 8 when it fits in 8)."""
    bits = int(np.max(image16, initial=0)).bit_length()
    return 8 if bits <= 8 else min(16, bits + bits % 2)


def image_from_message(msg, msgtype: str, where: str, depth_bits: int | None = None) -> np.ndarray:
    """(H,W) grey or (H,W,3) BGR uint8 image of an Image or CompressedImage message. mono16, bayer_*
    and yuv422 become grey, the same for every estimator; a 16-bit image keeps its top ``depth_bits``
    (None: told from this image, :func:`depth_bits_of`)."""
    if msgtype.endswith("CompressedImage"):
        fmt = str(msg.format)
        if "compressedDepth" in fmt:
            raise DatasetError(where, f"compressed depth image ({fmt}) cannot be used: a depth image is not a camera's grey levels")
        image = cv2.imdecode(np.frombuffer(bytes(msg.data), dtype=np.uint8), cv2.IMREAD_UNCHANGED)
        if image is None:
            raise DatasetError(where, f"compressed image ({fmt}) cannot be decoded")
        if image.ndim == 3 and image.shape[2] == 4:
            image = cv2.cvtColor(image, cv2.COLOR_BGRA2BGR)
        if image.dtype == np.uint16:
            image = grey_from_16bit(image, depth_bits or depth_bits_of(image))
        if image.dtype != np.uint8:
            raise DatasetError(where, f"compressed image ({fmt}) decodes to {image.dtype} pixels: 8- or 16-bit ones only")
        return image
    enc = str(msg.encoding)
    problem = raw_image_problem(msg, where)
    if problem is not None:
        raise DatasetError(where, f"image data: {problem}")
    c, h, w, step = pixel_bytes(enc, where), int(msg.height), int(msg.width), int(msg.step)
    data = np.frombuffer(bytes(msg.data), dtype=np.uint8)
    rows = data[: h * step].reshape(h, step)[:, : w * c]
    if c == 2 and not enc.startswith("yuv") and enc not in ("uyvy", "yuyv"):
        image16 = np.ascontiguousarray(rows).view(">u2" if int(msg.is_bigendian) else "<u2").reshape(h, w).astype(np.uint16)
        rows = grey_from_16bit(image16, depth_bits or depth_bits_of(image16))
        c = 1
    image = rows.reshape(h, w) if c == 1 else rows.reshape(h, w, c)
    if enc.startswith("bayer_"):
        image = cv2.cvtColor(np.ascontiguousarray(image), _BAYER_TO_GREY[enc[6:10]])
    elif enc in ("yuv422", "uyvy"):
        image = cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_YUV2GRAY_UYVY)
    elif enc in ("yuv422_yuy2", "yuyv"):
        image = cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_YUV2GRAY_YUY2)
    elif enc == "rgb8":
        image = image[:, :, ::-1]
    elif enc == "bgra8":
        image = image[:, :, :3]
    elif enc == "rgba8":
        image = image[:, :, 2::-1]
    return np.ascontiguousarray(image)


def image_depth_bits(msg, msgtype: str, where: str) -> int | None:
    """The bit depth of a stream of 16-bit images told from its first message (:func:`depth_bits_of`),
    None for 8-bit encodings, so that every frame of the stream is scaled alike."""
    if msgtype.endswith("CompressedImage"):
        image = cv2.imdecode(np.frombuffer(bytes(msg.data), dtype=np.uint8), cv2.IMREAD_UNCHANGED)
        return depth_bits_of(image) if image is not None and image.dtype == np.uint16 else None
    enc = str(msg.encoding)
    if pixel_bytes(enc, where) != 2 or enc.startswith("yuv") or enc in ("uyvy", "yuyv") or raw_image_problem(msg, where):
        return None
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    rows = np.frombuffer(bytes(msg.data), dtype=np.uint8)[: h * step].reshape(h, step)[:, : 2 * w]
    return depth_bits_of(np.ascontiguousarray(rows).view(">u2" if int(msg.is_bigendian) else "<u2"))


def ranges_from_scan(msg) -> np.ndarray:
    """(B,) float32 ranges, NaN where not finite or outside ``[range_min, range_max]``."""
    r = np.array(msg.ranges, dtype=np.float32)
    with np.errstate(invalid="ignore"):
        bad = ~np.isfinite(r) | (r < np.float32(msg.range_min)) | (r > np.float32(msg.range_max))
    r[bad] = np.nan
    return r


@contextmanager
def open_bag(path: str | Path, quiet: bool = False) -> Iterator:
    """An open ``rosbags`` AnyReader on the ROS 1 or ROS 2 bag (or ``.mcap`` file) at ``path``. A ROS 1
    bag without its index or an MCAP file without its summary (a recording killed, a file cut short)
    is read sequentially as far as it is whole (:mod:`~dem_graph.datasets.bag_salvage`), with a warning
    naming the byte offset (none when ``quiet``); a bag that cannot be read is a :class:`DatasetError` naming the path."""
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
        reason = f"{type(exc).__name__}: {' '.join(str(exc).split())}"
        salvaged = _salvaged(path, reason, quiet)
        if salvaged is None:
            raise DatasetError(path, f"cannot open the bag ({reason})") from None
        yield salvaged
        return
    try:
        yield reader
    finally:
        reader_cm.__exit__(None, None, None)


def _salvaged(path: Path, reason: str, quiet: bool):
    """The whole part of a damaged bag rosbags refused for ``reason`` (:func:`salvage_bag`), None when there is none."""
    try:
        bag = salvage_bag(path)
    except Exception:  # noqa: BLE001 - the damage is told by rosbags' reason, below
        log.debug("sequential reading of %s failed", path, exc_info=True)
        return None
    if bag is None:
        return None
    if not quiet:
        whole = f"whole up to byte {bag.whole_bytes:,} of {bag.size_bytes:,}" if bag.whole_bytes < bag.size_bytes else f"whole to its end ({bag.size_bytes:,} bytes)"
        if bag.ros1:
            tool = f"`rosbag reindex {path}` rebuilds the index, as this reader does on the fly"
            what = "a ROS 1 bag without a readable index (a recording that was not closed?)"
        else:
            tool = f"`mcap recover {bag.path}` writes a whole copy"
            what = "an MCAP file without its summary (cut short?)"
        log.warning("%s: %s (%s): read message by message, %s; %s", bag.path, what, reason, whole, tool)
    return bag


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
    if not connections:  # rosbags reads every topic when given none
        return
    for connection, t_ns, raw in reader.messages(connections=connections, start=start_ns, stop=stop_ns):
        yield t_ns, reader.deserialize(raw, connection.msgtype)


def check_increasing(t_s: np.ndarray, where: str) -> None:
    """A :class:`DatasetError` at ``where`` naming the first message whose stamp is not after the one before."""
    i = first_not_increasing(t_s)
    if i is not None:
        raise DatasetError(where, f"message {i}: time {time_text(t_s[i])} is not after the previous message's {time_text(t_s[i - 1])}")


def skip_unordered(t_s: np.ndarray, candidates: np.ndarray, skipped: SkippedMessages) -> np.ndarray:
    """Mask of the ``candidates`` (mask of messages not skipped yet) kept once those whose stamps
    ``t_s`` are not after their predecessors' are skipped (:func:`increasing_stamps`), each told to ``skipped``."""
    index = np.flatnonzero(candidates)
    in_order = increasing_stamps(np.asarray(t_s, dtype=float)[index])
    keep = candidates.copy()
    kept_before = -np.inf
    for i, ok in zip(index, in_order):
        if ok:
            kept_before = t_s[i]
            continue
        keep[i] = False
        skipped.skip(i, STAMP_NOT_AFTER, f"stamp {time_text(t_s[i])}, the message kept before it {time_text(kept_before)}")
    return keep


def _layout_text(count: int, a_min: float, a_inc: float) -> str:
    return f"{count} beams from {a_min:.6f} rad every {a_inc:.6f} rad"


def read_scan_topic(
    reader,
    topic: str,
    where: str,
    layout: tuple[float, float, int] | None = None,
    layout_name: str = "scan 0",
    skipped: SkippedMessages | None = None,
) -> tuple[np.ndarray, np.ndarray, tuple[float, float, int] | None]:
    """Every LaserScan of ``topic``: stamps (s, increasing), ranges (S, B; NaN where no return) and the
    beam layout ``(angle_min_rad, angle_increment_rad, count)``. Every scan must have ``layout`` (named
    ``layout_name``), or when it is None the first scan's. With ``skipped``, a scan of another layout
    or whose stamp is not after its predecessor's is skipped and told to it (the caller decides with
    :meth:`SkippedMessages.finish`); without, it is a :class:`DatasetError` at ``where``."""
    times, ranges = [], []
    for i, (_, msg) in enumerate(topic_messages(reader, topic)):
        r = ranges_from_scan(msg)
        a_min, a_inc = float(msg.angle_min), float(msg.angle_increment)
        times.append(stamp_s(msg.header))
        if layout is None:
            if not (np.isfinite(a_min) and np.isfinite(a_inc)) or a_inc <= 0 or len(r) < 2:
                raise DatasetError(where, f"scan 0 has {_layout_text(len(r), a_min, a_inc)}: not a scan")
            layout = (a_min, a_inc, len(r))
        elif len(r) != layout[2] or not np.isclose(a_min, layout[0], rtol=0, atol=1e-5) or not np.isclose(a_inc, layout[1], rtol=1e-5, atol=0):
            why = f"{_layout_text(len(r), a_min, a_inc)}; {layout_name} has {_layout_text(layout[2], layout[0], layout[1])}"
            if skipped is None:
                raise DatasetError(where, f"scan {i} has {why}")
            skipped.skip(i, WRONG_SHAPE, why)
            r = np.full(layout[2], np.nan, dtype=np.float32)  # a placeholder, left out below
        ranges.append(r)
    t_s = np.array(times, dtype=float)
    all_ranges = np.stack(ranges) if ranges else np.zeros((0, layout[2] if layout else 0), dtype=np.float32)
    if skipped is None:
        check_increasing(t_s, where)
        return t_s, all_ranges, layout
    keep = np.ones(len(t_s), dtype=bool)
    keep[list(skipped.skipped)] = False
    keep = skip_unordered(t_s, keep, skipped)
    return t_s[keep], all_ranges[keep], layout


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

    def has(self, frame: str) -> bool:
        """Whether a transform names ``frame``."""
        return frame.lstrip("/") in self._edges

    def frames(self) -> list[str]:
        """Every frame a transform names."""
        return list(self._edges)

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
        self._skipped: dict[str, SkippedMessages] = {}
        self._message_index: dict[str, np.ndarray] = {}  # by topic: the bag's message index of each message kept
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
            # the stamps of the messages in time order (the clock checks), the finite samples, the messages' frame
            self._imu_msg_t_s, self._imu, imu_frame = self._read_imu(reader) if imu_topic is not None else (np.zeros(0), _no_imu(), None)
            rig = self._rig_with_tf(rig, tree, body_frame, camera_frame, laser_frame, imu_frame)
            self._rig = rig
            self._scan_t_s, self._scan_ranges = self._read_scans(reader)
            self._odometry = self._read_odometry(reader, tree, body_frame) if odometry_topic is not None else []
            self._frame_t_s, self._frame_keep, self._depth_bits = self._read_image_stamps(reader)
        self._check_time_jumps()
        warn_if_no_laser(self._where(scan_topic), self._scan_ranges, self._rig.laser)
        firsts = [a[0] for a in (self._frame_t_s, self._scan_t_s, self._imu["t_s"]) if len(a)] + [o.t_prev_s for o in self._odometry[:1]]
        self._t_start_s = float(min(firsts)) if firsts else 0.0

    def _check_time_jumps(self) -> None:
        """Refuse a clock fault in any stream (a jump forward beyond ``max_gap_s`` between two messages)."""
        streams = [(self._image_topic, self._frame_t_s), (self._scan_topic, self._scan_t_s)]
        if self._odometry_topic is not None:
            streams.append((self._odometry_topic, self._odometry_msg_t_s))
        if self._imu_topic is not None:
            streams.append((self._imu_topic, self._imu_msg_t_s))
        for topic, t_s in streams:
            index = self._message_index.get(topic, np.arange(len(t_s)))
            check_time_jumps(self._where(topic), t_s, None, self.input_checks, lambda i, index=index: f"message {int(index[i])}: time")

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
            bad = []
            for i, msg in enumerate(self._messages(reader, topic)):
                for tr in msg.transforms:
                    q, p = tr.transform.rotation, tr.transform.translation
                    values = np.array([q.x, q.y, q.z, q.w, p.x, p.y, p.z], dtype=float)
                    if not np.all(np.isfinite(values)) or np.linalg.norm(values[:4]) < 1e-6:
                        bad.append((i, f"{tr.header.frame_id} -> {tr.child_frame_id}"))
                        continue
                    tree.add(tr.header.frame_id, tr.child_frame_id, _transform_from_msg(tr.transform))
            if bad:
                log.warning("%s: %d transforms are not finite or have a zero-length quaternion (first: message %d, %s): skipped", self._where(topic), len(bad), *bad[0])
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

    def _tally(self, topic: str, stream: str) -> SkippedMessages:
        """The record of the messages of ``topic`` skipped (its counters named ``<stream>_<kind>``)."""
        self._skipped[topic] = SkippedMessages(self._where(topic), stream)
        return self._skipped[topic]

    def _read_scans(self, reader) -> tuple[np.ndarray, np.ndarray]:
        beams = self._rig.laser.beams
        where = self._where(self._scan_topic)
        if not isinstance(beams, PlanarBeams):
            raise DatasetError(where, "a LaserScan needs the rig's laser to have planar beams")
        layout = (beams.angle_min_rad, beams.angle_increment_rad, beams.count)
        skipped = self._tally(self._scan_topic, "laser")
        t, ranges, _ = read_scan_topic(reader, self._scan_topic, where, layout, "the rig's laser", skipped)
        n_messages = len(t) + len(skipped.skipped)
        skipped.finish(n_messages, self.input_checks)
        self._message_index[self._scan_topic] = np.array(sorted(set(range(n_messages)) - skipped.skipped), dtype=int)
        return t, ranges

    def _read_odometry(self, reader, tree: TransformTree, body: str | None) -> list[Odometry]:
        """The increments between consecutive messages kept (those not finite or whose stamps are not
        after their predecessors' skipped), those beyond the vehicle's motion left out."""
        spec = self._rig.odometry or OdometrySpec()
        where = self._where(self._odometry_topic)
        skipped = self._tally(self._odometry_topic, "odometry")
        times, poses, children, covariances = [], [], [], []
        for i, msg in enumerate(self._messages(reader, self._odometry_topic)):
            times.append(stamp_s(msg.header))
            problem = _pose_problem(msg.pose.pose)
            if problem is not None:
                skipped.skip(i, NONFINITE, problem)
            poses.append(_pose_from_msg(msg.pose.pose) if problem is None else None)
            children.append(str(msg.child_frame_id))
            covariances.append(np.asarray(msg.pose.covariance, dtype=float).reshape(6, 6))
        t_s = np.array(times, dtype=float)
        keep = skip_unordered(t_s, np.array([P is not None for P in poses], dtype=bool), skipped)
        skipped.finish(len(t_s), self.input_checks)
        kept = np.flatnonzero(keep)
        self._message_index[self._odometry_topic] = kept
        self._odometry_msg_t_s = t_s[kept]
        _warn_unused_covariances(where, np.array(covariances).reshape(-1, 6, 6)[kept], kept)
        out: list[Odometry] = []
        for a, b in zip(kept[:-1], kept[1:]):
            T_inc = invert(poses[a]) @ poses[b]
            T_body_base = tree.lookup(body, children[b]) if body is not None and children[b] else None
            if T_body_base is not None:
                T_inc = T_body_base @ T_inc @ invert(T_body_base)
            T_inc = nearest_pose(T_inc)
            out.append(Odometry(float(t_s[b]), float(t_s[a]), T_inc, spec.covariance_of(T_inc), len(out)))
        if not out:
            return out
        dt_s = np.array([o.t_s - o.t_prev_s for o in out])
        plausible = plausible_increments(where, np.array([o.T_prev_curr for o in out]), dt_s, self.input_checks)
        return [o for o, k in zip(out, plausible) if k]

    def _read_imu(self, reader) -> tuple[np.ndarray, dict[str, np.ndarray], str]:
        """The stamps of the messages kept in time order, the samples of those whose values are all
        finite (the others skipped, one warning per kind) and the messages' frame_id (message 0's; "" when it names none)."""
        where = self._where(self._imu_topic)
        skipped = self._tally(self._imu_topic, "imu")
        times, values, frames = [], [], {}
        for i, msg in enumerate(self._messages(reader, self._imu_topic)):
            times.append(stamp_s(msg.header))
            w, a = msg.angular_velocity, msg.linear_acceleration
            values.append((w.x, w.y, w.z, a.x, a.y, a.z))
            frames.setdefault(str(msg.header.frame_id).lstrip("/"), i)
        t_s = np.array(times, dtype=float)
        v = np.array(values, dtype=float).reshape(-1, 6)
        frame = next(iter(frames), "")
        if len(frames) > 1:
            others = ", ".join(f"{f!r} from message {i}" for f, i in list(frames.items())[1:])
            log.warning("%s: the messages name %d frames (%r, then %s): all are taken to be in %r", where, len(frames), frame, others, frame)
        finite = np.all(np.isfinite(v), axis=1)
        for i in np.flatnonzero(~finite):
            skipped.skip(i, NONFINITE, f"angular velocity {_vector_text(v[i, :3])} rad/s, linear acceleration {_vector_text(v[i, 3:])} m/s^2")
        in_order = skip_unordered(t_s, np.ones(len(t_s), dtype=bool), skipped)  # the stamps' order, finite or not
        skipped.finish(len(t_s), self.input_checks)
        keep = in_order & finite
        self._message_index[self._imu_topic] = np.flatnonzero(in_order)
        return t_s[in_order], {"t_s": t_s[keep], "gyro_rad_s": v[keep, :3], "accel_mps2": v[keep, 3:]}, frame

    def _read_image_stamps(self, reader) -> tuple[np.ndarray, np.ndarray, int | None]:
        """The stamps of the image messages kept, the mask of those kept over all of them, and the
        stream's bit depth (16-bit images; :func:`image_depth_bits` of the first usable message). A
        raw image whose data does not hold it, or of another size than the rig's camera, and one
        whose stamp is not after its predecessor's, are skipped; an encoding no estimator can use is refused."""
        where = self._where(self._image_topic)
        skipped = self._tally(self._image_topic, "camera")
        camera = self._rig.camera
        times, usable, depth_bits = [], [], None
        for i, msg in enumerate(self._messages(reader, self._image_topic)):
            times.append(stamp_s(msg.header))
            problem = None
            if not self._image_type.endswith("/Image") and "compressedDepth" in str(msg.format):
                raise DatasetError(f"{where} message {i}", f"compressed depth image ({msg.format}) cannot be used: a depth image is not a camera's grey levels")
            if self._image_type.endswith("/Image"):
                problem = raw_image_problem(msg, f"{where} message {i}")
                if problem is None and (int(msg.width), int(msg.height)) != (camera.width_px, camera.height_px):
                    problem = f"image is {int(msg.width)}x{int(msg.height)} px but the rig's camera is {camera.width_px}x{camera.height_px} px"
            if problem is not None:
                skipped.skip(i, WRONG_SHAPE, problem)
            elif depth_bits is None and not any(usable):
                depth_bits = image_depth_bits(msg, self._image_type, f"{where} message {i}")
            usable.append(problem is None)
        t_s = np.array(times, dtype=float)
        keep = skip_unordered(t_s, np.array(usable, dtype=bool), skipped)
        skipped.finish(len(t_s), self.input_checks)
        self._message_index[self._image_topic] = np.flatnonzero(keep)
        return t_s[keep], keep, depth_bits

    def _iter_images(self, reader):
        """``(t_s, image, message index, problem)`` of the image messages kept, decoded, in bag order. A
        compressed image that does not decode, or decodes to another size than the rig's camera, has
        image None and ``problem`` saying why (its size is known only once decoded); None otherwise."""
        where = self._where(self._image_topic)
        compressed = self._image_type.endswith("CompressedImage")
        for i, msg in enumerate(self._messages(reader, self._image_topic)):
            if not (i < len(self._frame_keep) and self._frame_keep[i]):
                continue
            t = stamp_s(msg.header)
            if not compressed:
                yield t, image_from_message(msg, self._image_type, f"{where} message {i}", self._depth_bits), i, None
                continue
            try:
                image = image_from_message(msg, self._image_type, f"{where} message {i}", self._depth_bits)
                check_image_size(f"{where} message {i}", image, self._rig.camera)
            except DatasetError as exc:
                yield t, None, i, exc.problem
                continue
            yield t, image, i, None

    def _skip_frame(self, message: int, problem: str) -> None:
        """A compressed frame that cannot be used, found while replaying: skipped, one warning for the
        first; the stream refused when more than ``max_skipped_fraction`` of its messages are skipped."""
        skipped = self._skipped[self._image_topic]
        first = WRONG_SHAPE not in skipped.indices
        skipped.skip(message, WRONG_SHAPE, problem)
        n_messages = len(self._frame_keep)
        if len(skipped.skipped) > self.input_checks.max_skipped_fraction * n_messages:
            raise DatasetError(
                self._where(self._image_topic),
                f"{len(skipped.skipped)} of {n_messages} messages cannot be used (first compressed one: message {skipped.first[WRONG_SHAPE][0]}, "
                f"{skipped.first[WRONG_SHAPE][1]}): more than input_checks.max_skipped_fraction = {self.input_checks.max_skipped_fraction:.0%} of the stream",
            )
        if first:
            log.warning("%s message %d: %s: skipped (the others counted in metrics.json, skipped_messages)", self._where(self._image_topic), message, problem)

    def skipped_messages(self) -> dict[str, int]:
        """How many messages of each stream were skipped, by kind (``camera_stamp_not_after``,
        ``odometry_nonfinite``, ``laser_wrong_shape``, ...): the counters ``metrics.json`` keeps."""
        counts: dict[str, int] = {}
        for skipped in self._skipped.values():
            counts.update(skipped.counts())
        return dict(sorted(counts.items()))

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
        with open_bag(self.path, quiet=True) as reader:
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
                    t, image, message, problem = next(images)
                    if problem is not None:
                        self._skip_frame(message, problem)
                        continue
                    check_image_size(f"{self._where(self._image_topic)} message {message}", image, self.rig.camera)
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


def _vector_text(v) -> str:
    """A vector for people: ``(0.100, nan, 9.810)``."""
    return "(" + ", ".join(f"{float(x):.3f}" for x in v) + ")"


def _pose_problem(pose) -> str | None:
    """What makes an odometry message's pose unusable (a value not finite, a quaternion of zero length), None when it is usable."""
    p = np.array([pose.position.x, pose.position.y, pose.position.z], dtype=float)
    q = np.array([pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w], dtype=float)
    if np.all(np.isfinite(p)) and np.all(np.isfinite(q)) and np.linalg.norm(q) > 1e-6:
        return None
    return f"position {_vector_text(p)} m, orientation quaternion (x, y, z, w) {_vector_text(q)}"


def _warn_unused_covariances(where: str, covariance: np.ndarray, message_index: np.ndarray | None = None) -> None:
    """One warning when odometry messages carry pose covariances that are not covariances (all-zero
    ones, ROS's "unknown", are fine): they are not used, but say something of the driver.
    ``message_index``: the bag's index of each message (None: their positions)."""
    message_index = np.arange(len(covariance)) if message_index is None else np.asarray(message_index)
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
        int(message_index[known[i]]),
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
