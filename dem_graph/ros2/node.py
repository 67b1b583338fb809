"""The ROS 2 node: the robot's topics in, the map its navigation reads out, with no ROS installation.

:class:`Ros2Node` makes its estimator's compiled kernels ready (:mod:`~dem_graph.pipeline.warm_up`:
a few seconds, once a minute on a new installation), joins the robot's ROS 2 graph as a DDS
participant (:mod:`~dem_graph.ros2.dds`) and goes through three phases:

1. **Start**: it subscribes to the image (``CompressedImage`` when the topic ends in
   ``/compressed``), its CameraInfo, the scan, the odometry and IMU when named, ``/tf_static`` and
   ``/tf``, and keeps what comes. Once images and scans span ``startup_s`` of their stamps and the
   CameraInfo and tf have come (or ``topic_timeout_s`` has passed since the first image), it derives
   the rig from those messages as for a bag (:func:`~dem_graph.datasets.bag_rig.rig_of_bag`;
   ``rig_file`` over it field by field) and writes it to the run folder. A topic that never comes
   is named in one warning; the run is refused in one line only when that topic carries the rig and
   the rig file does not give what it would have.
2. **Run**: every message becomes an event by the bag readers' rules
   (:class:`~dem_graph.datasets.ros_stream.LiveStreams`), the events go back into time order in a
   :class:`~dem_graph.ros2.reorder.ReorderBuffer`, and the live pipeline takes them; after each
   frame :class:`~dem_graph.ros2.publisher.MapPublisher` publishes the map. Between messages the
   pipeline's idle work is done, the global map and the diagnostics are published when due.
3. **Stop** (Ctrl-C, SIGTERM, :meth:`Ros2Node.stop`): the events held are given, the estimator
   finishes, and the run folder is written as ``dem-graph run`` writes one (the map as GeoTIFF, the
   trajectory as TUM, ``metrics.json`` with the streams' health in ``live_source``). The folder is
   kept current while the node runs (the trajectory, the map points and the saved live maps), so a
   SIGKILL loses at most the last seconds.

A source whose clock goes back (a player restarted, a robot rebooted) by more than
``clock_back_s`` ends the run there: with ``on_clock_back="new-map"`` the node writes it and starts
a new map in the next folder (``RUN-2``, ``RUN-3``, ...); with ``"stop"`` it writes it and stops,
saying why in one line.
"""

from __future__ import annotations

import logging
import math
import signal
import threading
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
from threadpoolctl import threadpool_limits

from dem_graph.datasets.bag_rig import BagTopics, camera_info_candidates, fixed_transforms, rig_of_bag
from dem_graph.datasets.events import CameraFrame, ImuSample, Odometry
from dem_graph.datasets.ros_stream import CAMERA, IMU, LASER, ODOMETRY, LiveStreams, MessageLog, RecordedLive
from dem_graph.datasets.rosbag import _transform_from_msg, stamp_s
from dem_graph.errors import DatasetError, DemGraphError, one_line
from dem_graph.evaluation.timing import TimingStats
from dem_graph.pipeline.checkpoint import RunCheckpoint
from dem_graph.pipeline.config import RunConfig, RunOverrides, run_config
from dem_graph.pipeline.live import LivePipeline
from dem_graph.pipeline.live_run import LiveRun
from dem_graph.pipeline.metrics import LiveSourceMetrics, StreamHealth, compute_metrics
from dem_graph.pipeline.result import RunResult
from dem_graph.pipeline.run import IDLE_MIN_WAIT_S, run_dem, with_dataset_speed
from dem_graph.pipeline.run_folder import prepare_run_folder, write_run, write_run_config, write_run_rig
from dem_graph.pipeline.warm_up import warm_up
from dem_graph.ros2 import outputs
from dem_graph.ros2.dds import Participant, Reader
from dem_graph.ros2.messages import Codec, MessageError
from dem_graph.ros2.outputs import CostLimits, Frames
from dem_graph.ros2.publisher import MapPublisher, OutputTopics, RobotOdometry
from dem_graph.ros2.qos import LISTENER, SENSOR_DATA, TF_STATIC
from dem_graph.ros2.reorder import ReorderBuffer

log = logging.getLogger(__name__)

IMAGE_MSG, COMPRESSED_MSG, INFO_MSG = "sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage", "sensor_msgs/msg/CameraInfo"
SCAN_MSG, ODOMETRY_MSG, IMU_MSG, TF_MSG = "sensor_msgs/msg/LaserScan", "nav_msgs/msg/Odometry", "sensor_msgs/msg/Imu", "tf2_msgs/msg/TFMessage"
CAMERA_INFO, TF_STREAM, TF_STATIC_STREAM = "camera_info", "tf", "tf_static"
# a reader's own history: what Cyclone keeps while the node's thread is busy, 20 s of a 25 Hz camera, a 50 Hz
# laser, 100 Hz odometry, a 400 Hz IMU (the first start of a new installation compiles the kernels: 15 s
# more for a run of `smoke` here, in bursts at their first use); memory only while it fills
READER_DEPTH = {CAMERA: 512, CAMERA_INFO: 512, LASER: 1024, ODOMETRY: 2048, IMU: 8192, TF_STREAM: 4096, TF_STATIC_STREAM: 64}


@dataclass
class NodeOptions:
    """What ``dem-graph ros2 node`` takes (each field its option)."""

    topics: BagTopics
    out_dir: Path
    rig_file: Path | None = None
    config_file: Path | None = None
    overrides: RunOverrides = field(default_factory=lambda: RunOverrides(realtime=True))
    outputs: OutputTopics = field(default_factory=OutputTopics)
    map_frame: str = "map"
    odom_frame: str = "odom"
    heading_frame: str = "dem_graph_heading"
    cost_limits: CostLimits = field(default_factory=CostLimits)
    reorder_window_s: float = 0.1  # an event waits at most this long for the other streams
    max_frame_lag_s: float | None = 0.2  # a frame this far behind the newest image received is skipped (the map stays current on a machine slower than the camera); None: every frame
    startup_s: float = 1.0  # seconds of images and scans kept before the rig is derived (their rates)
    topic_timeout_s: float = 5.0  # a topic silent this long from the start is reported (and refused if the rig needs it)
    global_map_period_s: float = 10.0  # the whole map: 12.6 MB and 60-80 ms of work after 60 m here, off the frames' path
    cost_map_period_s: float = 0.2  # Nav2's local costmaps update at 5 Hz by default
    cost_map_half_size_m: float = 8.0  # the cost map covers this far around the vehicle, each way
    diagnostics_period_s: float = 1.0
    clock_back_s: float = 1.0  # a stamp this far before its stream's newest: the source's clock went back
    on_clock_back: Literal["new-map", "stop"] = "new-map"
    domain_id: int | None = None  # None: ROS_DOMAIN_ID
    overwrite: bool = False
    warm_up: bool = True  # the estimator's kernels compiled (or loaded) before subscribing (pipeline.warm_up)


@dataclass
class NodeRun:
    """A map the node made: its folder and how it ended."""

    out_dir: Path
    frames: int
    error: str | None = None
    paths: dict = field(default_factory=dict)


@dataclass
class _Arrival:
    stream: str
    topic: str
    msgtype: str
    message: object
    received_ns: int
    source_ns: int


@dataclass
class _Subscription:
    stream: str
    topic: str
    msgtype: str
    reader: Reader


class Inbox:
    """Every subscription's messages, taken off the readers and decoded (rosbags' CDR) in the node's
    own thread: between events the node blocks in :meth:`get` until one comes. While the estimator
    works, Cyclone's threads keep what arrives in each reader's history (:data:`READER_DEPTH`, some
    seconds of each stream); a thread of ours taking them meanwhile would only contend for the GIL
    (measured: a frame twice as long on two cores)."""

    def __init__(self, participant: Participant, subscriptions: list[_Subscription]):
        self.participant, self.subscriptions = participant, subscriptions
        self.seconds = 0.0  # taking and decoding, in all
        self.received = Counter()
        self.undecodable = Counter()

    def wake(self) -> None:
        """End a :meth:`get` that waits (from a signal handler or another thread)."""
        self.participant.wake()

    def get(self, timeout_s: float) -> list[_Arrival]:
        """The messages waiting, oldest first in each topic; when none, wait at most ``timeout_s`` for one."""
        got = self._take()
        if not got and timeout_s > 0:
            self.participant.wait(timeout_s)
            got = self._take()
        return got

    def _take(self) -> list[_Arrival]:
        codec = self.participant.codec
        got = []
        t0 = time.perf_counter()
        for sub in self.subscriptions:
            for rec in sub.reader.take_all():
                try:
                    message = codec.decode(rec.data, sub.msgtype)
                except MessageError as exc:
                    self.undecodable[sub.stream] += 1
                    if self.undecodable[sub.stream] in (1, 100, 1000):
                        log.warning("%s: %s: skipped (%d such messages so far)", sub.topic, exc, self.undecodable[sub.stream])
                    continue
                self.received[sub.stream] += 1
                got.append(_Arrival(sub.stream, sub.topic, sub.msgtype, message, rec.received_ns, rec.source_ns))
        self.seconds += time.perf_counter() - t0
        return got


class _Drain:
    """A thread taking the readers' messages into a list while the node's own thread is busy for long
    (:meth:`_Session._begin`); :meth:`stop` ends it and gives them, oldest first."""

    def __init__(self, inbox: Inbox, period_s: float = 0.005):
        self.inbox, self.period_s = inbox, period_s
        self.arrivals: list = []
        self._running = True
        self._thread = threading.Thread(target=self._loop, name="dem_graph-ros2-drain", daemon=True)
        self._thread.start()

    def _loop(self) -> None:
        while self._running:
            self.arrivals.extend(self.inbox.get(0.0))
            time.sleep(self.period_s)

    def stop(self) -> list:
        self._running = False
        self._thread.join(timeout=5.0)
        return self.arrivals + self.inbox.get(0.0)


class _ClockWentBack(Exception):
    """A source's stamps went back by more than ``clock_back_s``; ``pending``: the arrivals from the
    one that told it on, for the next map."""

    pending: list = []


class Ros2Node:
    """The node (see the module): ``Ros2Node(options).run()`` until stopped; :meth:`stop` from any thread."""

    def __init__(self, options: NodeOptions, participant: Participant | None = None):
        self.options = options
        self.topics = options.topics
        if options.warm_up:
            from dem_graph.pipeline.config import configured_estimator

            warm_up(configured_estimator(options.config_file, options.overrides))
        self.participant = participant or Participant(options.domain_id, Codec())
        self._stop = threading.Event()
        self._stop_reason: str | None = None
        self.runs: list[NodeRun] = []
        self.incompatible_qos: list[str] = []
        self._carry: list[_Arrival] = []  # arrivals the last map did not take (its source had restarted)
        self._static: list[_Arrival] = []  # every /tf_static message: latched, sent once to this node's reader, valid for every map
        self._subscribe()
        self.inbox = Inbox(self.participant, self.subscriptions)

    # --- the graph ----------------------------------------------------------------------------
    def _subscribe(self) -> None:
        t = self.topics
        p = self.participant
        image_type = COMPRESSED_MSG if t.image_topic.rstrip("/").endswith("/compressed") else IMAGE_MSG
        self.image_type = image_type
        subs = [(CAMERA, t.image_topic, image_type, SENSOR_DATA), (LASER, t.scan_topic, SCAN_MSG, SENSOR_DATA)]
        info_topics = [t.camera_info_topic] if t.camera_info_topic else camera_info_candidates(t.image_topic)[:1]
        subs += [(CAMERA_INFO, topic, INFO_MSG, SENSOR_DATA) for topic in info_topics]
        if t.odometry_topic:
            subs.append((ODOMETRY, t.odometry_topic, ODOMETRY_MSG, SENSOR_DATA))
        if t.imu_topic:
            subs.append((IMU, t.imu_topic, IMU_MSG, SENSOR_DATA))
        subs += [(TF_STATIC_STREAM, "/tf_static", TF_MSG, TF_STATIC), (TF_STREAM, "/tf", TF_MSG, LISTENER)]
        self.subscriptions = []
        for stream, topic, msgtype, qos in subs:
            depth = READER_DEPTH.get(stream, qos.depth)
            self.subscriptions.append(_Subscription(stream, topic, msgtype, p.reader(topic, msgtype, qos.with_depth(max(depth, qos.depth)))))
        self.info_topic = info_topics[0]

    def stop(self, reason: str | None = None) -> None:
        """Ask the node to stop after the event it is on (safe from a signal handler or another thread)."""
        if self._stop_reason is None:
            self._stop_reason = reason
        self._stop.set()
        self.inbox.wake()

    # --- the whole life -----------------------------------------------------------------------
    def run(self) -> list[NodeRun]:
        """Map until stopped (a new map after each clock reset with ``on_clock_back="new-map"``); the maps made."""
        previous = self._install_signals()
        try:
            n = 0
            while not self._stop.is_set():
                n += 1
                out_dir = self._out_dir(n)
                try:
                    self.runs.append(self._one_map(out_dir))
                except _ClockWentBack as exc:
                    self.runs.append(exc.args[0])
                    if self.options.on_clock_back == "stop":
                        raise DemGraphError(f"{exc.args[1]}: the run up to there is in {exc.args[0].out_dir}; stopped (--on-clock-back stop)") from None
                    log.warning("%s: the run up to there is in %s; a new map starts in %s", exc.args[1], exc.args[0].out_dir, self._out_dir(n + 1))
        finally:
            self._restore_signals(previous)
            self.incompatible_qos = list(self.participant.incompatible)
        return self.runs

    def close(self) -> None:
        self.participant.close()

    def arrivals(self, timeout_s: float) -> list[_Arrival]:
        """The messages to take next: those a map before left, else the inbox's."""
        if self._carry:
            got, self._carry = self._carry, []
        else:
            got = self.inbox.get(timeout_s)
        self._static.extend(a for a in got if a.stream == TF_STATIC_STREAM)
        return got

    def _out_dir(self, n: int) -> Path:
        base = Path(self.options.out_dir)
        return base if n == 1 else base.with_name(f"{base.name}-{n}")

    def _install_signals(self):
        if threading.current_thread() is not threading.main_thread():
            return None

        def handle(signum, _frame):
            name = signal.Signals(signum).name
            if self._stop.is_set():
                raise KeyboardInterrupt(f"second {name}")
            log.warning("%s: stopping, writing the run folder (again to stop at once)", name)
            self.stop(name)

        return {sig: signal.signal(sig, handle) for sig in (signal.SIGINT, signal.SIGTERM)}

    @staticmethod
    def _restore_signals(previous) -> None:
        for sig, handler in (previous or {}).items():
            signal.signal(sig, handler)

    # --- one map ------------------------------------------------------------------------------
    def _one_map(self, out_dir: Path) -> NodeRun:
        prepare_run_folder(out_dir, self.options.overwrite)
        session = _Session(self, out_dir)
        try:
            session.start()
            if session.pipeline is None:  # stopped before the rig came
                return NodeRun(out_dir, 0, self._stop_reason or "stopped before the rig could be derived")
            with threadpool_limits(limits=session.config.blas_threads, user_api="blas"):  # as a run does: the same sums, and no core taken from the graph
                session.run()
        except _ClockWentBack as exc:
            self._carry = list(exc.pending)
            raise _ClockWentBack(session.finish(str(exc)), str(exc)) from None
        except DemGraphError:
            if session.pipeline is not None:
                session.finish("stopped by an error")
            raise
        except KeyboardInterrupt as exc:
            if session.pipeline is not None:
                return session.finish(f"interrupted ({exc})")
            raise
        except Exception as exc:  # noqa: BLE001 - a fault late in a long day must not lose the map: written, then one line
            error = f"stopped by an internal error: {type(exc).__name__}: {one_line(exc)}"
            log.debug("internal error", exc_info=True)
            if session.pipeline is not None:
                session.finish(error)
            raise DemGraphError(f"{error} (the run up to there is in {out_dir}; please report it, -vv shows where)") from None
        return session.finish(None, drain_s=5.0)


class _Session:
    """One map: from the first message to the written run folder."""

    def __init__(self, node: Ros2Node, out_dir: Path):
        self.node, self.out_dir = node, out_dir
        self.o = node.options
        self.log = MessageLog()
        self.backlog: list[_Arrival] = []
        self.pipeline: LivePipeline | None = None
        self.high: dict[str, float] = {}  # each stream's newest stamp (the clock check)
        self.first_heard: dict[str, float] = {}  # wall time each stream was first heard
        self.started_wall = time.monotonic()
        self.silent_warned: set[str] = set()
        self.tree = None
        self.clock_resets = 0
        self._gaps = Counter()
        self._bad = Counter()  # messages whose conversion failed, by stream
        self._last_stamp: dict[str, float] = {}
        self._frame_transport_s: list[float] = []
        self._transport_s_at_frame = 0.0
        self.exact_stamps: dict[float, tuple[int, int]] = {}  # the frames' times: their images' stamps, for the outputs'
        self._image_times: dict[float, list] = {}  # the frames' times: their images' write (the publisher's clock), take and release, ns
        self._last_image_ns: int | None = None
        self._last_frame_wall = time.monotonic()  # when the last frame's outputs went
        self._wire_s: list[float] = []  # each frame: its image from the publisher's write to the node's take
        self._order_wait_s: list[float] = []  # ... from its take to the pipeline (the reorder buffer's wait)
        self._in_node_s: list[float] = []  # ... from its take to its outputs written
        self.frames_skipped = 0  # frames behind the newest image by more than max_frame_lag_s, not given to the pipeline

    # --- start --------------------------------------------------------------------------------
    def start(self) -> None:
        node = self.node
        first = [a for a in node._static if a not in node._carry]  # the static transforms an earlier map had
        while not node._stop.is_set():
            got, first = first + node.arrivals(0.05), []
            for a in got:
                try:
                    self._check_clock(a)
                except _ClockWentBack as exc:  # before the rig: what was kept is of the old clock
                    log.warning("%s: the messages kept so far are dropped, the rig is derived from the new ones", exc)
                    self.log, self.backlog, self.high = MessageLog(), [], {}
                    continue
                self.first_heard.setdefault(a.stream, time.monotonic())
                stamp = getattr(getattr(a.message, "header", None), "stamp", None)
                t_ns = int(stamp.sec) * 10**9 + int(stamp.nanosec) if stamp is not None else a.received_ns  # exact: a float of epoch seconds is not
                self.log.add(a.topic, a.msgtype, t_ns, a.message)
                if a.stream in (CAMERA, LASER, ODOMETRY, IMU):
                    self.backlog.append(a)
            self._warn_silent()
            if self._ready():
                rig = self._derive_rig()
                if rig is not None:
                    self._begin(rig)
                    return

    def _span_s(self, topic: str | None) -> float:
        t = self.log.stamps_ns(topic) if topic else np.zeros(0)
        return float(t.max() - t.min()) * 1e-9 if len(t) >= 2 else 0.0

    def _ready(self) -> bool:
        t = self.node.topics
        if self.log.count(t.image_topic) < 2 or self.log.count(t.scan_topic) < 2:
            return False
        if min(self._span_s(t.image_topic), self._span_s(t.scan_topic)) < self.o.startup_s:
            return False
        waited = time.monotonic() - self.first_heard.get(CAMERA, time.monotonic())
        optional = [x for x in (t.odometry_topic, t.imu_topic) if x]
        have_all = self.log.count(self.node.info_topic) > 0 and self.log.count("/tf_static") > 0 and all(self.log.count(x) > 0 for x in optional)
        return have_all or self.o.rig_file is not None or waited >= self.o.topic_timeout_s

    # what a topic silent from the start means (a warning each, once)
    _SILENT = {
        CAMERA: "no map without it: waiting for it", LASER: "no map without it: waiting for it",
        CAMERA_INFO: "the rig needs the camera's intrinsics from it, unless --rig gives them", TF_STATIC_STREAM: "the rig needs the sensors' mounts from it, unless --rig gives them",
        ODOMETRY: "going on without it", IMU: "going on without it",
    }

    def _warn_silent(self) -> None:
        """One warning for each topic that has given nothing ``topic_timeout_s`` after the first
        message of any (the robot's drivers up), or after the start when nothing at all came."""
        heard = min(self.first_heard.values()) if self.first_heard else None
        now = time.monotonic()
        if heard is None:
            if now - self.started_wall >= self.o.topic_timeout_s and "*" not in self.silent_warned:
                self.silent_warned.add("*")
                topics = ", ".join(s.topic for s in self.node.subscriptions if s.stream != TF_STREAM)
                log.warning(
                    "no message on any topic in %.0f s (%s): is the robot on ROS_DOMAIN_ID=%d and this machine on its network? "
                    "(`ros2 topic list` there names its topics)", self.o.topic_timeout_s, topics, self.node.participant.domain_id,
                )
            return
        if now - heard < self.o.topic_timeout_s:
            return
        for sub in self.node.subscriptions:
            if sub.stream == TF_STREAM or self.log.count(sub.topic) or sub.topic in self.silent_warned:
                continue
            self.silent_warned.add(sub.topic)
            matched = sub.reader.matched()
            who = f"{matched} publisher(s) matched, none has sent" if matched else "no publisher on it"
            log.warning("no message on %s (%s) in %.0f s, %s: %s", sub.topic, sub.msgtype, self.o.topic_timeout_s, who, self._SILENT[sub.stream])

    def _derive_rig(self):
        """The rig from the messages kept (a bag's rules), or None to wait longer. Refused (a
        DatasetError) once ``topic_timeout_s`` has passed and a topic the rig needs has not come."""
        t = self.node.topics
        topics = BagTopics(**vars(t))
        waited = time.monotonic() - self.first_heard.get(CAMERA, time.monotonic())
        timed_out = waited >= self.o.topic_timeout_s
        for name in ("odometry_topic", "imu_topic"):
            topic = getattr(topics, name)
            if topic and not self.log.count(topic):
                if not timed_out:
                    return None
                if topic not in self.silent_warned:
                    self.silent_warned.add(topic)
                    log.warning("no message on %s in %.0f s: going on without it", topic, self.o.topic_timeout_s)
                setattr(topics, name, None)
        where = f"ROS 2 domain {self.node.participant.domain_id}"
        try:
            rig, derived = rig_of_bag(self.log, where, topics, self.o.rig_file)
        except DatasetError:
            if not timed_out:
                return None
            raise
        self.topics = topics
        self.derived = derived
        self.tree, _moving = fixed_transforms(self.log)
        return rig

    def _begin(self, rig) -> None:
        """The pipeline, its listeners and the run folder, then the messages kept so far; what comes
        meanwhile is taken off the readers in a thread (the estimator's start, its graph process and
        the first compiles of its kernels take seconds: more than the readers' histories hold), and
        is the first the run takes."""
        drain = _Drain(self.node.inbox)
        try:
            self._begin_pipeline(rig)
        finally:
            self.node._carry = drain.stop() + self.node._carry

    def _begin_pipeline(self, rig) -> None:
        o, t = self.o, self.topics
        body = t.body_frame or (self.derived.body_frame if self.derived.from_tf else None)
        self.frames = Frames(o.map_frame, o.odom_frame, self.derived.body_frame or "base_link", o.heading_frame)
        self.streams = LiveStreams(rig, t, self.tree, body, where=f"ROS 2 domain {self.node.participant.domain_id}")
        events = [(a, self._event(a)) for a in self.backlog if a.stream in (CAMERA, LASER, ODOMETRY, IMU)]
        firsts = [e.t_s for _, e in events if e is not None and not isinstance(e, Odometry)]
        firsts += [e.t_prev_s for _, e in events if isinstance(e, Odometry)][:1]
        t_start = min(firsts) if firsts else 0.0
        has_odometry = any(isinstance(e, Odometry) for _, e in events)
        has_imu = any(isinstance(e, ImuSample) for _, e in events)
        self.sequence = RecordedLive(rig, t_start, has_odometry, has_imu, f"ros2-domain-{self.node.participant.domain_id}", self.streams)
        config = with_dataset_speed(self.sequence, run_config(self.sequence, o.config_file, o.overrides))
        self.config: RunConfig = config
        write_run_config(self.out_dir, config)
        self.rig_path = write_run_rig(self.out_dir, rig)
        self.pipeline = LivePipeline(rig, np.eye(4), t_start, has_odometry, config)
        self.live = LiveRun.attach(self.pipeline, None, config.local_error, run_dir=self.out_dir)
        self.robot_odometry = RobotOdometry(self.frames)
        self.publisher = MapPublisher(self.node.participant, self.pipeline, o.outputs, self.frames, o.cost_limits, self.robot_odometry, self.exact_stamps)
        self.pipeline.listeners.insert(0, self.publisher)  # first: the map goes out before anything else is done
        self.checkpoint = RunCheckpoint(self.pipeline, self.out_dir, config.checkpoint_every_s)
        self.pipeline.listeners.append(self.checkpoint)
        self.reorder = ReorderBuffer(o.reorder_window_s, periods_s={s: 1.0 / r for s in (CAMERA, LASER, ODOMETRY, IMU) if (r := self._rate(s))})
        self.started = time.perf_counter()
        self.next_global = time.monotonic() + o.global_map_period_s
        self.next_cost = time.monotonic()
        self.next_diagnostics = time.monotonic() + o.diagnostics_period_s
        for msg in (m for topic in ("/tf",) for _, _, m in self.log.messages([c for c in self.log.connections if c.topic == topic])):
            self.robot_odometry.add(msg, self.tree)
        log.warning(
            "%s: the rig derived (%s); mapping with %s from %.3f s, the run folder %s",
            f"ROS 2 domain {self.node.participant.domain_id}", self.rig_path, config.estimator, t_start, self.out_dir,
        )
        for a, event in events:
            if event is not None:
                self._give(self.reorder.push(a.stream, event.t_s, event, a.received_ns * 1e-9))
        self._give(self.reorder.pop_ready(time.time()))
        self.reorder.waited_out.clear()
        self.backlog = []

    # --- run ----------------------------------------------------------------------------------
    def run(self) -> None:
        node = self.node
        while not node._stop.is_set():
            if self.config.max_frames and self.pipeline.updates >= self.config.max_frames:
                node.stop(f"{self.config.max_frames} frames (--max-frames)")
                break
            deadline = self.reorder.next_deadline_s()
            timeout = 0.05 if deadline is None else min(max(deadline - time.time(), 0.0), 0.05)
            arrivals = node.arrivals(timeout)
            for i, a in enumerate(arrivals):
                try:
                    self._take(a)
                except _ClockWentBack as exc:
                    exc.pending = arrivals[i:]
                    raise
            self._give(self.reorder.pop_ready(time.time()))
            self._between_frames()

    def _take(self, a: _Arrival) -> None:
        self._check_clock(a)
        if a.stream == TF_STREAM:
            self.robot_odometry.add(a.message, self.tree)
            return
        if a.stream == TF_STATIC_STREAM:
            for tr in a.message.transforms:
                self.tree.add(str(tr.header.frame_id), str(tr.child_frame_id), _transform_from_msg(tr.transform))
            return
        if a.stream == CAMERA_INFO:
            return
        try:
            event = self._event(a)
        except Exception as exc:  # noqa: BLE001 - one bad message costs that message (a field of a type no reader expects)
            self._bad[a.stream] += 1
            if self._bad[a.stream] in (1, 100, 1000):
                log.warning("%s: a message that cannot be used (%s: %s): skipped (%d so far)", a.topic, type(exc).__name__, one_line(exc, 160), self._bad[a.stream])
            return
        if event is not None:
            self._give(self.reorder.push(a.stream, event.t_s, event, a.received_ns * 1e-9))

    def _event(self, a: _Arrival):
        s = self.streams
        msg = a.message
        self._count_gap(a.stream, stamp_s(msg.header))
        if a.stream == CAMERA:
            frame = s.image(msg, a.msgtype)
            if frame is not None:
                self.exact_stamps[frame.t_s] = (int(msg.header.stamp.sec), int(msg.header.stamp.nanosec))
                self._image_times[frame.t_s] = [a.source_ns, a.received_ns, None]  # written, taken, given to the pipeline
                self._last_image_ns = a.received_ns
            return frame
        if a.stream == LASER:
            return s.scan(msg)
        if a.stream == ODOMETRY:
            return s.odometry(msg)
        if a.stream == IMU:
            return s.imu(msg)
        return None

    def _give(self, events: list) -> None:
        for event in events:
            if isinstance(event, CameraFrame) and self._behind(event):
                continue
            if isinstance(event, CameraFrame):
                if event.t_s in self._image_times:
                    self._image_times[event.t_s][2] = time.time_ns()
                frames_before = self.pipeline.updates
                self.pipeline.on_frame(event)
                if self.pipeline.updates > frames_before:
                    self._frame_published()
                continue
            self.sequence.record(event)
            before = self.pipeline.updates
            self.pipeline.on_event(event)
            if self.pipeline.updates > before:  # a frame held for its odometry went with it
                self._frame_published()

    def _behind(self, frame: CameraFrame) -> bool:
        """Whether ``frame`` is skipped: a newer image has come and ``frame`` is more than
        ``max_frame_lag_s`` before it (by their stamps). When the machine keeps up, the newest image
        is at most a reorder window ahead and nothing is skipped; when it falls behind the camera,
        the frames in between go and the next map is of a current image (the motion between the
        frames given is larger: the estimators' prediction covers it)."""
        lag = self.o.max_frame_lag_s
        newest = self.reorder.newest(CAMERA)
        if lag is None or newest is None or newest - frame.t_s <= lag:
            return False
        self.frames_skipped += 1
        self._image_times.pop(frame.t_s, None)
        if self.frames_skipped in (1, 100, 1000) or self.frames_skipped % 10000 == 0:
            log.warning("the node is behind the camera: a frame %.0f ms older than the newest image was skipped (%d so far; --max-frame-lag-s)", (newest - frame.t_s) * 1e3, self.frames_skipped)
        return True

    def _frame_published(self) -> None:
        """The frame's outputs are out: the transport's cost since the last frame (messages taken and
        decoded, outputs encoded and written), and where the frame's time went from its image's write."""
        now_ns = time.time_ns()
        total_s = self.node.inbox.seconds + self.publisher.transport_s
        self._frame_transport_s.append(total_s - self._transport_s_at_frame)
        self._transport_s_at_frame = total_s
        times = self._image_times.pop(self.pipeline.latest.t_s, None)
        for t in [t for t in self._image_times if t < self.pipeline.latest.t_s]:  # (frames skipped by the pipeline)
            del self._image_times[t]
        self._last_frame_wall = time.monotonic()
        self._periodic_outputs()
        if times is not None and times[2] is not None:
            written, taken, given = times
            self._wire_s.append((taken - written) * 1e-9)
            self._order_wait_s.append((given - taken) * 1e-9)
            self._in_node_s.append((now_ns - taken) * 1e-9)

    def _between_frames(self) -> None:
        """After the events that came were given, when no frame waits (for its odometry or in the
        reorder buffer) and the next image is not due within ``IDLE_MIN_WAIT_S`` (a run at the
        camera's rate waits as much): the pipeline's deferred work (at the camera's rate). With no
        frame for a second, the periodic outputs go out anyway (the diagnostics say why)."""
        if time.monotonic() - self._last_frame_wall > 1.0:
            self._periodic_outputs()
        if not self.config.realtime or self.pipeline.estimator.holding_frame or self.reorder.holds(CAMERA):  # a frame waits: its work first
            return
        rate = self._rate(CAMERA)
        if self._last_image_ns is not None and rate and (self._last_image_ns * 1e-9 + 1.0 / rate) - time.time() < IDLE_MIN_WAIT_S:
            return
        self.pipeline.idle()

    def _periodic_outputs(self) -> None:
        """The cost map, the global map and the diagnostics, each when due (after a frame's outputs, or with no frame for a while)."""
        now = time.monotonic()
        t_s = self.pipeline.latest.t_s if self.pipeline.latest is not None else None
        if now >= self.next_diagnostics and t_s is not None:
            self.next_diagnostics = now + self.o.diagnostics_period_s
            self.publisher.publish_diagnostics(t_s, self._diagnostics())
        if t_s is None or now - self._last_frame_wall > 1.0:
            return
        if now >= self.next_cost:
            self.next_cost = now + self.o.cost_map_period_s
            self.publisher.publish_cost(self.o.cost_map_half_size_m)
        if now >= self.next_global and not (self.pipeline.estimator.holding_frame or self.reorder.holds(CAMERA)):
            self.next_global = now + self.o.global_map_period_s
            self.publisher.publish_global(t_s)

    # --- checks -------------------------------------------------------------------------------
    def _check_clock(self, a: _Arrival) -> None:
        if a.stream in (TF_STREAM, TF_STATIC_STREAM) or not hasattr(a.message, "header"):
            return
        t_s = stamp_s(a.message.header)
        high = self.high.get(a.stream)
        if high is not None and t_s < high - self.o.clock_back_s:
            self.clock_resets += 1
            raise _ClockWentBack(f"{a.topic}: the stamps went back from {high:.3f} s to {t_s:.3f} s (the source restarted?)")
        self.high[a.stream] = t_s if high is None else max(high, t_s)

    def _count_gap(self, stream: str, t_s: float) -> None:
        """Messages that never came: a gap of more than one and a half periods counts its whole periods."""
        last = self._last_stamp.get(stream)
        self._last_stamp[stream] = t_s if last is None else max(last, t_s)
        rate = self._rate(stream)
        if last is None or not rate or not t_s > last:
            return
        periods = (t_s - last) * rate
        if periods > 1.5:
            self._gaps[stream] += int(round(periods)) - 1

    def _rate(self, stream: str) -> float | None:
        rig = self.pipeline.rig if self.pipeline is not None else None
        if rig is None:
            return None
        spec = {CAMERA: rig.camera, LASER: rig.laser, ODOMETRY: rig.odometry, IMU: rig.imu}.get(stream)
        rate = getattr(spec, "rate_hz", None) if spec is not None else None
        return float(rate) if rate else None

    # --- reports ------------------------------------------------------------------------------
    def _stream_health(self) -> dict[str, StreamHealth]:
        out = {}
        inbox = self.node.inbox
        for sub in self.node.subscriptions:
            rate = self._rate(sub.stream)
            out[sub.stream] = StreamHealth(
                topic=sub.topic, received=int(inbox.received[sub.stream]), rate_hz=rate if rate else math.nan,
                late=int(self.reorder.late[sub.stream]) if hasattr(self, "reorder") else 0,
                waited_out=int(self.reorder.waited_out[sub.stream]) if hasattr(self, "reorder") else 0,
                missing=int(self._gaps[sub.stream]), undecodable=int(inbox.undecodable[sub.stream] + self._bad[sub.stream]),
            )
        return out

    def _diagnostics(self) -> list:
        """The node's health for ``/diagnostics``: the frame time, the graph's lag, the tracking and each stream."""
        codec = self.node.participant.codec
        p = self.pipeline
        recent = p.frame_timing_s[-100:]
        timing = TimingStats.from_seconds(recent)
        period_ms = 1e3 / self._rate(CAMERA) if self._rate(CAMERA) else math.nan
        level = outputs.OK if not timing.p95_ms > period_ms else outputs.WARN
        message = "within the camera's period" if level == outputs.OK else "p95 over the camera's period: frames wait"
        if self.frames_skipped:
            level, message = outputs.WARN, f"{message}; {self.frames_skipped} frames skipped, behind the camera"
        statuses = [outputs.diagnostic_status(codec, "dem_graph: frame time", level, message, {
            "median_ms": timing.median_ms, "p95_ms": timing.p95_ms, "camera_period_ms": period_ms, "frames": p.updates, "frames_skipped": self.frames_skipped,
        })]
        lag = p.estimator.graph_lag_keyframes
        statuses.append(outputs.diagnostic_status(codec, "dem_graph: graph", outputs.OK, "no graph" if lag is None else f"results {lag} keyframes late", {"lag_keyframes": "" if lag is None else lag, "estimator": p.name}))
        record = p.estimator.last_frame
        n_live, n_tracked = (record.n_live, record.n_tracked) if record is not None else (0, 0)
        yield_ = n_tracked / n_live if n_live else math.nan
        level = outputs.OK if yield_ >= 0.3 else outputs.WARN
        statuses.append(outputs.diagnostic_status(codec, "dem_graph: tracking", level, f"{n_tracked} of {n_live} live points tracked", {"tracked": n_tracked, "live": n_live, "yield": yield_}))
        now_ns = time.time_ns()
        for stream, h in self._stream_health().items():
            heard = self.high.get(stream)
            level = outputs.OK
            message = "ok"
            if h.received == 0:
                level, message = outputs.STALE if stream not in (TF_STREAM, TF_STATIC_STREAM) else outputs.OK, "nothing received"
            elif h.missing or h.late or h.undecodable:
                level, message = outputs.WARN, f"{h.missing} missing, {h.late} late, {h.undecodable} undecodable"
            statuses.append(outputs.diagnostic_status(codec, f"dem_graph: {h.topic}", level, message, {
                "received": h.received, "rate_hz": h.rate_hz, "missing": h.missing, "late": h.late, "waited_out": h.waited_out,
                "undecodable": h.undecodable, "newest_stamp_s": "" if heard is None else heard, "now_s": now_ns * 1e-9,
            }))
        return statuses

    # --- stop ---------------------------------------------------------------------------------
    def finish(self, error: str | None, drain_s: float = 0.0) -> NodeRun:
        """The messages received (at most ``drain_s`` of work) and the events held given, the
        estimator finished, the run folder written; the node's run."""
        with threadpool_limits(limits=self.config.blas_threads, user_api="blas"):
            return self._finish(error, drain_s)

    def _finish(self, error: str | None, drain_s: float) -> NodeRun:
        p = self.pipeline
        reason = error or self.node._stop_reason
        deadline = time.monotonic() + drain_s
        try:
            while time.monotonic() < deadline:
                got = self.node.arrivals(0.0)
                if not got:
                    break
                for i, a in enumerate(got):
                    try:
                        self._take(a)
                    except _ClockWentBack:
                        self.node._carry = got[i:]  # (what came after the source restarted is not this run's)
                        deadline = 0.0
                        break
        except Exception as exc:  # noqa: BLE001 - keep what was done
            log.error("the last messages could not be taken (%s: %s): the run is written up to there", type(exc).__name__, one_line(exc))
        try:
            self._give(self.reorder.pop_ready(time.time(), flush=True))
            p.finish()
        except Exception as exc:  # noqa: BLE001 - keep what was done
            log.error("the last events could not be processed (%s: %s): the run is written up to there", type(exc).__name__, one_line(exc))
        result = p.result()
        run = RunResult(result, self.config, error=error, interrupted=False, elapsed_s=time.perf_counter() - self.started, live=self.live)
        run.metrics = compute_metrics(self.sequence, result, error, run.elapsed_s)
        if result.frames:
            run.metrics.live_map = self.live.metrics()
            run.dem = run_dem(run, self.sequence)
        transport, in_node = TimingStats.from_seconds(self._frame_transport_s), TimingStats.from_seconds(self._in_node_s)
        run.metrics.live_source = LiveSourceMetrics(
            source=f"ROS 2 domain {self.node.participant.domain_id}", streams=self._stream_health(), transport_median_ms=transport.median_ms,
            transport_p95_ms=transport.p95_ms, camera_wire_median_ms=TimingStats.from_seconds(self._wire_s).median_ms,
            order_wait_median_ms=TimingStats.from_seconds(self._order_wait_s).median_ms, publish_median_ms=TimingStats.from_seconds(self.publisher.publish_s).median_ms,
            in_node_median_ms=in_node.median_ms, in_node_p95_ms=in_node.p95_ms, frames_published=self.publisher.frames_published, incompatible_qos=list(self.node.participant.incompatible) or None,
            clock_resets=self.clock_resets, frames_skipped=self.frames_skipped,
        )
        run.metrics.dataset = run.metrics.live_source.source
        paths = {}
        if result.frames:
            paths = {**write_run(run, self.out_dir), "rig": self.rig_path}
            self.publisher.publish_global(result.frames[-1].t_s)
        else:
            log.warning("no frame was mapped: %s holds the rig and the settings only", self.out_dir)
        lines = [f"{len(result.frames)} frames mapped{f' ({reason})' if reason else ''}; the run folder: {self.out_dir}"]
        log.warning("%s", lines[0])
        return NodeRun(self.out_dir, len(result.frames), error, paths)


def run_node(options: NodeOptions) -> list[NodeRun]:
    """What ``dem-graph ros2 node`` runs: the node until Ctrl-C or SIGTERM; the maps it made."""
    node = Ros2Node(options)
    try:
        return node.run()
    finally:
        node.close()


__all__ = ["Inbox", "NodeOptions", "NodeRun", "Ros2Node", "run_node"]
