"""The live pipeline: events in one at a time, the estimate and the map the guidance steers by out
after every camera frame.

:class:`LivePipeline` takes events from any source (a dataset, a ROS bag, a vehicle's own driver
callbacks) through :meth:`LivePipeline.on_event` (or ``on_frame`` / ``on_scan`` / ``on_odometry``),
runs the chosen estimator and a :class:`~dem_graph.dem.live_map.LiveMap`, and after each frame the
estimator completes returns a :class:`LiveUpdate`: the time, the pose and its covariance, the
speed, and the local DEM over the focus area for that speed, in the vehicle's heading frame.

- Every laser return goes into the map when its scan arrives, placed with the best pose known for
  its time: interpolated between frames, or extrapolated at constant velocity past the latest one.
- After each frame the poses of the last ``live_map.revision_window_s`` seconds are asked again
  (a smoother revises them: in-process at once, from the graph process keyframes later) and the
  scans whose pose moved are moved in the map. The estimator's map points go in as they leave it.
- Bad input does not stop the map. A scan of the wrong length, or one with non-finite ranges, is
  skipped or thinned with a warning; an event older than the last of its kind is skipped with a
  warning (``strict_order``: raised, as a dataset run does, whose log is then broken). Every event
  checks every stream: a camera silent for ``camera_silent_s``, a laser without a single return for
  ``laser_silent_s`` (scans of NaN count as silence) or odometry silent for ``odometry_silent_s`` is
  warned about once, when it is found (also at the end of the log, for a stream that stopped for
  good) and again when the stream is back; the map goes on (scans placed by extrapolation; cells age).

Listeners (``pipeline.listeners.append(fn)``) are called with each update: the run's live Fig. 8
measure, the saved live maps and the viewer are listeners. A listener that raises is logged and
dropped; the map goes on.
"""

from __future__ import annotations

import logging
import math
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dem_graph.datasets.events import CameraFrame, ImuSample, LaserScan, Odometry
from dem_graph.dem.layers import Dem
from dem_graph.dem.live_map import LiveMap
from dem_graph.errors import DemGraphError
from dem_graph.estimators.base import Estimator, FrameDrivenEstimator
from dem_graph.estimators.ekf import EkfConfig, EkfSlam
from dem_graph.estimators.isam2 import Isam2Config, Isam2Slam
from dem_graph.estimators.odometry_only import ODOMETRY_BASELINE, OdometryOnly
from dem_graph.estimators.settings import SharedSettings
from dem_graph.frontend.focus import FocusArea
from dem_graph.geometry.lie import so3_exp_many, so3_log_many
from dem_graph.geometry.rig import SensorRig
from dem_graph.pipeline.config import ESTIMATORS, RunConfig

log = logging.getLogger(__name__)

Event = CameraFrame | LaserScan | Odometry


def make_estimator(rig: SensorRig, T_world_body_initial: np.ndarray, t_start_s: float, has_odometry: bool, config: RunConfig) -> FrameDrivenEstimator:
    """The estimator ``config.estimator`` names, with the run's settings."""
    shared = {k: getattr(config, k) for k in SharedSettings.model_fields}
    args = (rig, T_world_body_initial, t_start_s, has_odometry)
    if config.estimator in ("gm", "ptpm"):
        return EkfSlam(*args, EkfConfig(**shared, **dict(config.ekf), variant=config.estimator))
    if config.estimator in ("isam2", "isam2-batch"):
        isam2 = dict(config.isam2)
        if isam2["graph_when_behind"] is None:  # a log replayed as fast as possible may wait for the graph; at the sensors' rate it may not
            isam2["graph_when_behind"] = "merge" if config.realtime else "wait"
        return Isam2Slam(*args, Isam2Config(**shared, **isam2, batch=config.estimator == "isam2-batch"))
    if config.estimator == ODOMETRY_BASELINE:
        return OdometryOnly(*args, config.motion)
    raise DemGraphError(f"unknown estimator '{config.estimator}'; choose one of {', '.join((*ESTIMATORS, ODOMETRY_BASELINE))}")


@dataclass
class LiveUpdate:
    """What the guidance gets after a frame."""

    frame: int  # frames completed so far, this one included
    t_s: float
    T_world_body: np.ndarray  # 4x4
    covariance: np.ndarray  # 6x6 [rotation, translation], right perturbation
    speed_mps: float
    local: Dem  # the focus area in the heading frame: elevation (relative to the body origin), variance, count, age_s, traversability
    n_tracked: int  # points the estimator tracked in the frame
    estimator_s: float  # time the estimator spent on the events since the last update
    map_s: float  # time the live map spent (scans placed, revisions, the local map)
    timing_s: dict[str, float] = field(default_factory=dict)  # the estimator's own phases for the frame
    image: np.ndarray | None = field(default=None, repr=False)  # the frame's image


class PoseWindow:
    """The best poses known for the last seconds, at any time: between two poses, rotation slerp
    and linear translation (as :class:`~dem_graph.geometry.trajectory.Trajectory`) and a linear
    blend of the covariances; past the newest, the last two poses' motion carried on (constant
    velocity) with the newest covariance; before the oldest, the oldest."""

    def __init__(self, t_s: np.ndarray, T: np.ndarray, P: np.ndarray):
        self.t_s, self.T, self.P = np.asarray(t_s, dtype=float), np.asarray(T, dtype=float), np.asarray(P, dtype=float)
        if len(self.t_s) > 1:
            R = self.T[:, :3, :3]
            self._step_rotvec = so3_log_many(np.einsum("nji,njk->nik", R[:-1], R[1:]))  # each step's rotation, once per window

    def at(self, t_query: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        t = np.atleast_1d(np.asarray(t_query, dtype=float))
        n = len(self.t_s)
        if n == 1:
            return np.repeat(self.T, len(t), axis=0), np.repeat(self.P, len(t), axis=0)
        hi = np.clip(np.searchsorted(self.t_s, t, side="right"), 1, n - 1)
        lo = hi - 1
        a = np.maximum((t - self.t_s[lo]) / (self.t_s[hi] - self.t_s[lo]), 0.0)  # > 1 past the newest: extrapolated
        T0 = self.T[lo]
        T_out = np.empty((len(t), 4, 4))
        T_out[:, 3] = (0.0, 0.0, 0.0, 1.0)
        T_out[:, :3, :3] = T0[:, :3, :3] @ so3_exp_many(a[:, None] * self._step_rotvec[lo])
        T_out[:, :3, 3] = T0[:, :3, 3] + a[:, None] * (self.T[hi][:, :3, 3] - T0[:, :3, 3])
        b = np.minimum(a, 1.0)[:, None, None]
        return T_out, (1.0 - b) * self.P[lo] + b * self.P[hi]


class LivePipeline:
    """The estimator and the live map, fed one event at a time (see the module)."""

    def __init__(
        self,
        rig: SensorRig,
        T_world_body_initial: np.ndarray,
        t_start_s: float,
        has_odometry: bool,
        config: RunConfig | None = None,
        strict_order: bool = False,
        estimator: Estimator | None = None,
    ):
        self.config = config or RunConfig()
        c = self.config.live_map
        self.rig = rig
        self.estimator = estimator or make_estimator(rig, T_world_body_initial, t_start_s, has_odometry, self.config)
        self.name = self.estimator.name
        self.estimator.defer_keyframe_work = self.config.realtime  # (the frame's keyframe work done between frames, see idle)
        self.map = LiveMap(rig, self.config.dem.fusion, c.revision_window_s, c.tolerance_m, c.tolerance_rad, c.tile_cells, c.gate_min_count)
        self.strict_order = strict_order
        self.listeners: list[Callable[[LiveUpdate], None]] = []
        self.updates = 0
        self.latest: LiveUpdate | None = None  # the last update given
        self.map_timing_s: list[float] = []  # the live map's time per frame update (benchmarks)
        self.frame_timing_s: list[float] = []  # the whole frame: the estimator's events since the last update and the live map
        self.idle_timing_s: list[float] = []  # each :meth:`idle` that did something: its time (off the frames' path)
        self._map_due = False  # the map is still to catch up with the estimator's last frame (a run at the camera's rate)
        P0 = np.eye(6) * self.config.motion.initial_sigma_pose**2
        self._start = (float(t_start_s), np.array(T_world_body_initial, dtype=float), P0)
        self._frame_t: deque[float] = deque()  # times of the frames in the revision window
        self._window = PoseWindow(np.array([t_start_s]), self._start[1][None], P0[None])
        self._points_seen = 0
        self._last_t = {"frame": -math.inf, "scan": -math.inf, "odometry": -math.inf, "imu": -math.inf}
        self._images: deque[tuple[float, np.ndarray]] = deque(maxlen=4)  # the frames the estimator may still hold
        self._estimator_s = 0.0
        self._map_s = 0.0
        # the latest time each stream gave something usable (a scan: one valid return at least), and
        # whether its silence was warned about (once per silence)
        self._heard = {"frame": None, "scan": None, "odometry": None}
        self._silence_warned = {"frame": False, "scan": False, "odometry": False}
        self.counters = {"events_out_of_order": 0, "scans_wrong_length": 0, "scans_nonfinite": 0, "camera_silences": 0, "laser_silences": 0, "odometry_silences": 0, "scans_without_return": 0, "imu_nonfinite": 0}

    @classmethod
    def for_sequence(cls, sequence, config: RunConfig | None = None, strict_order: bool = False) -> LivePipeline:
        """A pipeline for a dataset (:class:`~dem_graph.datasets.base.Sequence`): its rig, start and odometry."""
        return cls(sequence.rig, sequence.T_world_body_initial, sequence.t_start_s, sequence.has_odometry, config, strict_order)

    # --- events ------------------------------------------------------------------------------
    def on_event(self, event: Event) -> LiveUpdate | None:
        if isinstance(event, CameraFrame):
            return self.on_frame(event)
        if isinstance(event, LaserScan):
            return self.on_scan(event)
        if isinstance(event, Odometry):
            return self.on_odometry(event)
        if isinstance(event, ImuSample):
            return self.on_imu(event)
        raise DemGraphError(f"not an event the live pipeline takes: {type(event).__name__}")

    def _in_order(self, kind: str, t_s: float, what: str) -> bool:
        last = self._last_t[kind]
        if math.isfinite(t_s) and t_s > last:
            self._last_t[kind] = t_s
            return True
        if self.strict_order and kind == "frame":
            return True  # the estimator refuses it with its own message (EventOrderError)
        self.counters["events_out_of_order"] += 1
        log.warning("%s at %.6f s is not after the last one (%.6f s): skipped", what, t_s, last)
        return False

    def on_frame(self, event: CameraFrame) -> LiveUpdate | None:
        if not self._in_order("frame", event.t_s, f"camera frame {event.index}"):
            return None
        self._heard_from("frame", event.t_s)
        self._images.append((event.t_s, event.image))
        return self._timed(self.estimator.on_frame, event)

    def on_odometry(self, event: Odometry) -> LiveUpdate | None:
        if not self._in_order("odometry", event.t_s, "odometry"):
            return None
        self._heard_from("odometry", event.t_s)
        return self._timed(self.estimator.on_odometry, event)

    def on_imu(self, event: ImuSample) -> LiveUpdate | None:
        if not self._in_order("imu", event.t_s, f"IMU sample {event.index}"):
            return None
        if not (np.all(np.isfinite(event.gyro_rad_s)) and np.all(np.isfinite(event.accel_mps2))):
            self.counters["imu_nonfinite"] += 1
            if self.counters["imu_nonfinite"] == 1 or self.counters["imu_nonfinite"] % 100 == 0:
                log.warning("IMU sample %d at %.6f s is not finite: skipped (%d such samples so far)", event.index, event.t_s, self.counters["imu_nonfinite"])
            return None
        return self._timed(self.estimator.on_imu, event)

    def on_scan(self, event: LaserScan) -> LiveUpdate | None:
        if not self._in_order("scan", event.t_s, f"laser scan {event.index}"):
            return None
        ranges = np.asarray(event.ranges_m, dtype=float).ravel()
        if len(ranges) != self.map.n_beams:
            self.counters["scans_wrong_length"] += 1
            log.warning("laser scan %d at %.6f s has %d ranges, the rig's laser %d beams: skipped", event.index, event.t_s, len(ranges), self.map.n_beams)
            return None
        n_inf = int(np.isinf(ranges).sum())
        if n_inf:  # NaN is "no return"; an infinity is worth a word
            self.counters["scans_nonfinite"] += 1
            if self.counters["scans_nonfinite"] == 1 or self.counters["scans_nonfinite"] % 100 == 0:
                log.warning("laser scan %d at %.6f s has %d infinite ranges: those beams are left out (%d such scans so far)", event.index, event.t_s, n_inf, self.counters["scans_nonfinite"])
        if self.map.rig.laser.valid_ranges(ranges).any():
            self._heard_from("scan", event.t_s)
        else:  # a scan without a single return feeds nothing: to the map, the laser is silent
            self.counters["scans_without_return"] += 1
            self._check_silence(event.t_s)
        update = self._timed(self.estimator.on_scan, event)
        t0 = time.perf_counter()
        T, P = self._window.at(np.array([event.t_s]))
        self.map.add_scan(event.t_s, ranges, T[0], P[0])
        self._map_s += time.perf_counter() - t0
        return update

    def finish(self) -> LiveUpdate | None:
        """The source has ended: the estimator processes anything it held back (the graph's last results come in)."""
        ends = [t for t in self._last_t.values() if math.isfinite(t)]
        if ends:
            self._check_silence(max(ends))  # a stream that fell silent for good
        update = self._timed(self.estimator.finish)
        if self._map_due:  # (at the camera's rate: the map's catch-up with the last frame, no idle time coming)
            self._update_map(self._frame_t[-1])
        return update

    def result(self):
        """Everything the estimator has estimated so far (:class:`~dem_graph.estimators.base.EstimatorResult`)."""
        return self.estimator.result()

    def save_map(self, path) -> Path:
        """Save everything mapped so far as a GeoTIFF (north-up, world metres, one band per layer), at any time."""
        from dem_graph.io.dem_files import write_dem_geotiff

        return write_dem_geotiff(path, self.map.global_dem(self.config.dem.traversability_window))

    def local_map(self, x_range_m: tuple[float, float], half_width_m: float) -> Dem:
        """The local map now, over any window of the heading frame (``x_range_m`` ahead,
        ``half_width_m`` each side), from the latest pose: for a guidance that reads the map at its
        own rate. :class:`DemGraphError` before the first frame."""
        if self.latest is None:
            raise DemGraphError("no frame yet: the live map has no pose to read the local map from")
        u = self.latest
        return self.map.local(u.T_world_body, x_range_m, half_width_m, u.t_s, self.config.dem.traversability_window)

    # --- after the estimator -----------------------------------------------------------------
    def _timed(self, handler, *args) -> LiveUpdate | None:
        frames_before = self.estimator.frames_done
        t0 = time.perf_counter()
        handler(*args)
        self._estimator_s += time.perf_counter() - t0
        if self.estimator.frames_done == frames_before:
            return None
        return self._frame_done()

    _SILENCES = {  # stream: (its setting, its counter, what it gives, what the map does without it)
        "frame": ("camera_silent_s", "camera_silences", "camera frame", "laser scans are placed with poses extrapolated by the motion model"),
        "scan": ("laser_silent_s", "laser_silences", "laser scan with a return", "no laser return goes into the map, its cells age"),
        "odometry": ("odometry_silent_s", "odometry_silences", "odometry", "the motion between frames is predicted at constant velocity"),
    }

    def _heard_from(self, stream: str, t_s: float) -> None:
        """A usable event of ``stream`` at ``t_s``: a silence of it ends (said once), then every stream is checked."""
        last = self._heard[stream]
        if self._silence_warned[stream] and last is not None:
            log.warning("%s again at %.3f s, after %.2f s", self._SILENCES[stream][2], t_s, t_s - last)
        self._silence_warned[stream] = False
        self._heard[stream] = t_s
        self._check_silence(t_s)

    def _check_silence(self, t_s: float) -> None:
        """Warn once about each stream that was heard from before and has been silent longer than its
        setting at ``t_s`` (a stream never heard from is not expected: a log without odometry)."""
        c = self.config.live_map
        for stream, (setting, counter, what, consequence) in self._SILENCES.items():
            last = self._heard[stream]
            if last is None or self._silence_warned[stream] or t_s - last <= getattr(c, setting):
                continue
            self._silence_warned[stream] = True
            self.counters[counter] += 1
            log.warning("no %s for %.2f s (since %.3f s): %s", what, t_s - last, last, consequence)

    def idle(self) -> bool:
        """Work done while the sensors are quiet (a run at the camera's rate calls it between events
        when there is time): the estimator's own (:meth:`Estimator.idle`: the last frame's keyframe
        work, the graph's results that came back), then the map brought up to the estimator's poses
        (see :meth:`_update_map`). True if anything was done (its time in :attr:`idle_timing_s`)."""
        t0 = time.perf_counter()
        took = self.estimator.idle()
        if not (took or self._map_due) or not self._frame_t:
            return took
        self._update_map(self._frame_t[-1])
        self.idle_timing_s.append(time.perf_counter() - t0)
        return True

    def _update_map(self, t_now: float, catch_up: bool = True) -> np.ndarray:
        """The pose window over the frames kept, from the estimator's latest poses; with ``catch_up``,
        the map's scans moved to it and the points that left the estimator added. Returns the
        window's newest pose."""
        est = self.estimator
        t, T, P = est.recent_poses(len(self._frame_t))
        if len(self._frame_t) == est.frames_done and self._start[0] < t[0]:  # the start pose is still inside the window
            t, T, P = np.r_[self._start[0], t], np.concatenate([self._start[1][None], T]), np.concatenate([self._start[2][None], P])
        self._window = PoseWindow(t, T, P)
        # every scan still open to revision lies inside the window: the oldest frame kept is before the cut
        self.map.freeze_before(t_now - self.map.window_s)
        if catch_up:
            self.map.revise(self._window.at)
            xyz, cov, created, self._points_seen = est.archived_points_since(self._points_seen)
            if len(xyz) and self.config.dem.map_points:
                self.map.add_points(xyz, cov[:, 2, 2], created)
            self._map_due = False
        return T[-1]

    def _frame_done(self) -> LiveUpdate:
        est = self.estimator
        record = est.last_frame
        t_now = record.t_s
        window_s = self.map.window_s
        t0 = time.perf_counter()
        self._frame_t.append(t_now)
        while len(self._frame_t) > 2 and self._frame_t[1] < t_now - window_s:
            self._frame_t.popleft()
        # at the camera's rate the map catches up with the estimator (scans moved, points that left
        # added) between frames, in idle time, and the frame's local map holds what was done before
        # it; a frame does it itself when no idle time came since the last one
        T_now = self._update_map(t_now, catch_up=not self.config.realtime or self._map_due)
        self._map_due = self.config.realtime
        speed = self._speed()
        area = FocusArea.for_speed(self.config.frontend.focus, self.rig, speed)
        local = self.map.local(T_now, (area.x_near_m, area.x_far_m), area.half_width_m, t_now, self.config.dem.traversability_window)
        map_s = self._map_s + time.perf_counter() - t0
        self.map_timing_s.append(map_s)
        self.frame_timing_s.append(self._estimator_s + map_s)
        self.updates += 1
        image = next((im for t, im in self._images if t == t_now), None)
        update = LiveUpdate(self.updates, t_now, T_now.copy(), record.pose_covariance, speed, local, record.n_tracked, self._estimator_s, map_s, dict(record.timing_s), image)
        self._estimator_s = self._map_s = 0.0
        self.latest = update
        for listener in list(self.listeners):
            try:
                listener(update)
            except Exception as exc:  # noqa: BLE001 - a viewer or a saver failing must not stop the map
                self.listeners.remove(listener)
                log.error("%s failed at %.3f s and is stopped (the map goes on): %s: %s", type(listener).__name__, t_now, type(exc).__name__, exc)
        return update

    def _speed(self, span_s: float = 0.5) -> float:
        """Mean speed over the last ``span_s`` of the pose window, m/s (NaN with one pose)."""
        w = self._window
        if len(w.t_s) < 2:
            return float("nan")
        i0 = int(np.searchsorted(w.t_s, w.t_s[-1] - span_s))
        i0 = min(i0, len(w.t_s) - 2)
        return float(np.linalg.norm(w.T[-1][:3, 3] - w.T[i0][:3, 3]) / (w.t_s[-1] - w.t_s[i0]))


__all__ = ["LivePipeline", "LiveUpdate", "PoseWindow", "make_estimator"]
