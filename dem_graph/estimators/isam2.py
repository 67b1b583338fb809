"""The factor-graph estimator: frame poses and map points in an incremental fixed-lag smoother (iSAM2).

Every frame (docs/isam2_design.md):
1. predict the pose from odometry (or a constant-velocity guess) and propagate its covariance;
2. track every live point in its search region, the 2x2 innovation covariance of the predicted
   pose (relative to the map) and of the point's own covariance (its information from the
   keyframes that saw it, poses held fixed), plus the pixel noise;
3. update the pose against the points (:func:`~dem_graph.estimators.pose_update.update_pose`: points fixed, their covariance as
   pixel noise, Huber weights).

Every frame by default, and otherwise every ``keyframe_every`` frames or sooner when the map runs
short of points, the frame becomes a keyframe of the graph (on the vehicle, with the graph in a
second process, every ``ceil(live points / graph_landmarks_per_frame)`` frames unless
``keyframe_every`` is set, so that many live points do not outrun the graph): a message
(:mod:`dem_graph.estimators.graph_worker`) with the pose, the odometry since the last keyframe,
the frame's inlier observations and the new points with their laser or flat-ground seeds; the
graph adds the factors and runs one iSAM2 update (:class:`~dem_graph.estimators.keyframe_graph.KeyframeGraph`), cutting the window back
to ``lag_s`` every ``marginalize_every_s``. When its result is back (in the same frame, or some
keyframes later with ``graph_process: true``) the smoothed keyframe pose corrects the current one
and the live points take their smoothed positions. The frame's output is the pose after all this:
what was known at that frame.

With keyframes every n > 1 frames, the observations in between are used by the per-frame pose, and
reach the graph only through the weight of the next keyframe observation of the point
(``sigma_px / sqrt(n)``). That is cheaper and less accurate (the design notes compare them).

``batch: true`` (``--estimator isam2-batch``) also records every observation of every frame, and at
the end smooths the whole log at once (:mod:`dem_graph.estimators.batch`). Its online pass only
associates the data, so it makes a keyframe every ``batch_keyframe_every`` (5; 1 with the laser tied) frames: a fifth of the
iSAM2 updates, while the batch still has a pose and the observations of every frame.

:class:`Isam2Slam` drives three parts, each with its own state:

- :class:`~dem_graph.estimators.online_filter.OnlineFilter`: the per-frame pose, the live points,
  tracking in search regions and the pose update;
- :class:`~dem_graph.estimators.graph_client.GraphClient`: the keyframe messages, the graph's
  results applied, restarts, the pose covariance's anchor and the landmarks' numbering;
- :class:`~dem_graph.estimators.batch_log.BatchLog` (``batch: true`` only): the measurement log and
  its smoothing at the end;

and keeps the points that left (:class:`~dem_graph.estimators.point_archive.PointArchive`).
"""

from __future__ import annotations

import logging
import math
import time

import numpy as np

from dem_graph.datasets.events import CameraFrame, ImuSample
from dem_graph.estimators.base import SMOOTHED_TRAJECTORY, EstimatorResult, FrameDrivenEstimator, FrameRecord
from dem_graph.estimators.batch_log import BatchLog
from dem_graph.estimators.graph_client import GraphClient, seeds_in_world
from dem_graph.estimators.graph_worker import GraphResult
from dem_graph.estimators.imu_preintegration import ImuBuffer, gyro_rotation, with_rotation
from dem_graph.estimators.isam2_config import Isam2Config, Isam2Options
from dem_graph.estimators.keyframe_graph import KeyframeGraph
from dem_graph.estimators.laser_ties import NO_TIES, LaserTieMaker, LaserTies, level_start_covariance
from dem_graph.estimators.live_points import LivePoints
from dem_graph.estimators.measurement_log import MeasurementLog
from dem_graph.estimators.motion import constant_velocity_increment
from dem_graph.estimators.online_filter import FrameMatches, OnlineFilter
from dem_graph.estimators.point_archive import PointArchive
from dem_graph.frontend.frontend import FrontEnd, NewPoint
from dem_graph.geometry.ground_view import laser_view
from dem_graph.geometry.lie import adjoint
from dem_graph.geometry.rig import SensorRig
from dem_graph.geometry.se3 import invert

log = logging.getLogger(__name__)

ONLINE_PASS_ONLY = "isam2-batch (online pass only: stopped before the batch smoothing)"


class Isam2Slam(FrameDrivenEstimator):
    """Keyframe iSAM2 smoothing with the shared front end; feed it events in time order."""

    def __init__(self, rig: SensorRig, T_world_body_initial: np.ndarray, t_start_s: float, has_odometry: bool, config: Isam2Config | None = None):
        c = config or Isam2Config()
        # the laser tied to the landmarks over its ground, when the camera never sees its line (laser_ties):
        # the start's ground then levels the world, the start pose's roll, pitch and height let free in the graph,
        # and the batch's online pass makes every frame a keyframe unless told otherwise
        ties_on = c.laser_ties == "on" or (c.laser_ties == "auto" and not laser_view(rig).in_view)
        if ties_on and c.batch and c.batch_keyframe_every is None:
            c = c.model_copy(update={"batch_keyframe_every": 1})
        self.config = c
        self.name = "isam2-batch" if c.batch else "isam2"
        self.rig = rig
        self.frontend = FrontEnd(c.frontend, rig)
        super().__init__(c.motion, has_odometry, t_start_s)
        self._start_speed(c.motion, self.frontend)  # without odometry: measured from the ground on the first frames (_measure_speed)
        T0 = np.array(T_world_body_initial, dtype=float)
        P0 = np.eye(6) * c.motion.initial_sigma_pose**2
        self._filter = OnlineFilter(c, rig, self.frontend, T0.copy(), P0, self.t_s)
        self._ties = LaserTieMaker(rig, T0, P0, self.t_s, self.frontend.counters) if ties_on else None
        P0_graph = level_start_covariance(P0) if ties_on else P0
        self._client = GraphClient(c, rig, T0, P0_graph, self.t_s, self.frontend.counters)
        self._batch = BatchLog(c, rig, T0.copy(), P0_graph) if c.batch else None
        self._archived = PointArchive(self.frontend)  # the graph's latest estimate of each landmark is asked for in result()
        self._frames: list[FrameRecord] = []
        self._frames_since_keyframe = 0
        # defer_keyframe_work (a live pipeline at the camera's rate), with the graph in a second process
        # whose results come when ready: a frame's keyframe work (drops, seeds, the graph's message)
        # waits for idle time (at a fixed delay the run stays the in-process run with that delay)
        self._after_frame: tuple | None = None  # that work, for the last frame: (its event, its keyframe observations or None, its timing, its number)
        # the IMU's samples until the graph has them (motion.use_imu and a rig with an imu section)
        self._imu = ImuBuffer(rig.imu) if c.motion.use_imu and rig.imu is not None else None
        self.keyframe_hooks: list = []  # called as hook(self) after each keyframe's result is taken, in-process graph only (studies)

    # --- what studies and tests read ----------------------------------------------------------
    @property
    def graph(self) -> KeyframeGraph:
        """The smoother itself, when it runs in this process (studies and tests)."""
        return self._client.graph

    @property
    def T(self) -> np.ndarray:
        """The current pose, ``T_world_body``."""
        return self._filter.T

    @property
    def live(self) -> LivePoints:
        return self._filter.live

    @property
    def log(self) -> MeasurementLog | None:
        """Every measurement of the online pass (``batch: true`` only)."""
        return self._batch.log if self._batch is not None else None

    def search_regions(self, T_world_body: np.ndarray, Sigma: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The live points' predicted pixels, 2x2 innovation covariances and in-front mask from ``T_world_body`` (:meth:`OnlineFilter.search_regions`)."""
        return self._filter.search_regions(T_world_body, Sigma)

    def smoothed_poses(self) -> np.ndarray:
        """Every frame's pose from the latest keyframe estimates (each frame rides on the keyframe before it)."""
        return self._client.smoothed_poses()

    def on_imu(self, event: ImuSample) -> None:
        """An IMU sample: kept until the keyframe whose span it measures goes to the graph."""
        if self._imu is not None:
            self._imu.take(event)

    @property
    def graph_lag_keyframes(self) -> int | None:
        return self._client.latest_lag

    def idle(self) -> bool:
        """The last frame's keyframe work if it waited (``defer_keyframe_work``), then the graph's
        results that came back from the second process since: done now rather than first in the next
        frame, in the same order (no frame runs between), off the frame's path. Nothing here in a run
        whose results come at fixed points (in this process, or a fixed delay: each frame does its
        own keyframe work and takes them all)."""
        did = self._finish_frame()
        results = self._client.results()
        if results:  # (their graph time kept with the last frame's, as that frame's own results')
            self._frames[-1].timing_s["graph_worker"] += self._take_results(results)
        return did or bool(results)

    def finish(self) -> None:
        super().finish()
        self._finish_frame()
        pending, final = self._client.finish()
        self._take_results(pending, restart=False)
        self._client.close(final)
        if self._batch is not None and self._frames:
            self._batch.smooth(self.smoothed_poses(), self._client.points)

    # --- one frame ---------------------------------------------------------------------------
    def _process(self, event: CameraFrame) -> FrameRecord:
        self._pending_frame = None
        filt, client, c = self._filter, self._client, self.config
        timing = {}
        t0 = time.perf_counter()
        self._finish_frame()  # the last frame's keyframe work, when no idle time came for it
        # results that came back since the last frame (a second process's): taken before this frame's search
        timing["graph_worker"] = self._take_results(client.results())
        tp = time.perf_counter()
        graph_s = tp - t0
        if self.frontend.begin_frame(event.t_s, event.textureless):
            self._drop_points()  # after a camera gap: the points it made stale
            if not len(self.live):
                filt.restart_map()
        dt, U_odo, Q_odo = self._motion_since_last_frame(event)
        A_odo = adjoint(invert(U_odo))  # carries every covariance over the frame's motion
        U, Q, A, imu_span = U_odo, Q_odo, A_odo, None
        if self._imu is not None:  # the frame's prediction: its rotation by the gyro (the samples go to the batch's log too)
            imu_span = self._imu.span(event.t_s - dt, event.t_s) if dt > 0 else None
            U, Q = self._gyro_rotation(imu_span, event.t_s - dt, event.t_s, U, Q)
            A = adjoint(invert(U))
        # the graph's motion factor: the odometry (the gyro reaches the graph in its own factor); the
        # output pose covariance: the prediction's (the odometry's too without an IMU)
        client.carry(U_odo, Q_odo, A_odo, predicted=(Q, A))
        T_pred = filt.predict(U, Q, A)
        t1 = time.perf_counter()
        # a frame without texture (the reader marked it) is not searched: its pose is the prediction
        n_live = len(self.live)
        m = FrameMatches(np.zeros(0, dtype=int), np.zeros((0, 2))) if event.textureless else filt.track(event.image, event.t_s, T_pred)
        self._note_tracking(event.textureless, n_live, len(m.idx))
        t2 = time.perf_counter()
        m, T_pred = self._take_results_before_update(m, T_pred, U, timing)
        t2g = time.perf_counter()
        graph_s += t2g - t2
        filt.update_pose(T_pred, m, dt)
        t3 = time.perf_counter()
        timing["prediction"], timing["tracking"], timing["update"] = t1 - tp, t2 - t1, t3 - t2g
        idx, inlier = m.idx, m.inlier
        split_old = self._split_refreshed(idx)
        self.live.n_since_keyframe[idx[inlier]] += 1
        if self._batch is not None:
            self._batch.add_frame(event.t_s, U_odo, Q_odo, self.live.landmark[idx[inlier]], m.uv[inlier], split_old[inlier], imu_span)
        self._frames_since_keyframe += 1
        spacing = c.keyframe_spacing_for(len(self.live))
        is_keyframe = self._frames_since_keyframe >= spacing or len(self.live) < c.keyframe_min_live_fraction * c.frontend.max_points
        client.set_lag_limit(c.graph_lag_limit(spacing))
        if is_keyframe and not client.ready_for_keyframe():
            # the graph is graph_max_lag keyframes behind (graph_when_behind: merge): this frame's
            # observations go with the next keyframe (their weight with them), so that no frame waits
            # for the graph
            is_keyframe = False
            self.frontend.counters["keyframes_merged"] += 1
        if is_keyframe:
            tg = time.perf_counter()
            landmarks, uv, sigma_px, point_steps = filt.keyframe_observations(m, client.next_keyframe)
            in_graph = landmarks >= 0  # (the front end's own points were updated all the same)
            landmarks, uv, sigma_px, point_steps = landmarks[in_graph], uv[in_graph], sigma_px[in_graph], point_steps[in_graph]
            graph_s += time.perf_counter() - tg
        tm = time.perf_counter()
        filt.end_frame(event.t_s)
        self.frontend.end_frame(event.t_s, event.image, event.textureless)
        map_s = time.perf_counter() - tm
        observations = (landmarks, uv, sigma_px, point_steps) if is_keyframe else None
        if self.defer_keyframe_work and client.results_when_ready:
            # the vehicle: the frame ends here, its keyframe numbered so that it rides on it; the
            # points' drops and seeds, and the keyframe's message, wait for idle time (or the next frame)
            if is_keyframe:
                client.open_keyframe(event.t_s, filt.T)
            self._after_frame = (event, observations, timing, len(self._frames))
        else:
            map_s_after, graph_s_after = self._keyframe_work(event, observations, timing, len(self._frames))
            map_s, graph_s = map_s + map_s_after, graph_s + graph_s_after
        timing["map"], timing["graph"] = map_s, graph_s
        timing["total"] = time.perf_counter() - t0
        client.anchor_frame(filt.T)
        record = FrameRecord(event.t_s, filt.T.copy(), client.anchor.pose_covariance(filt.T), len(self.live), int(len(idx)), timing)
        self._frames.append(record)
        return record

    def _keyframe_work(self, event: CameraFrame, observations: tuple | None, timing: dict, frame: int) -> tuple[float, float]:
        """Frame number ``frame``'s work on the points and the graph once its pose is known: the
        points it lost dropped; at a keyframe (``observations``: its landmarks, pixels, sigmas and
        steps), new points seeded and the keyframe's message sent; the results that came back taken.
        Returns the time on the points and on the graph, seconds."""
        client, filt = self._client, self._filter
        tm = time.perf_counter()
        live_uv = None if event.textureless else self._drop_points()  # nothing is lost in a frame that could not show it
        map_s, graph_s = time.perf_counter() - tm, 0.0
        if observations is not None:
            tg = time.perf_counter()
            # no point starts in a frame without texture; its scans wait for the next frame
            any_speed = self._speed_unknown_at_start(self.frontend, frame)  # seeded over the focus area's whole depth
            scans = [] if event.textureless else self._scans.take_until(event.t_s)
            new = filt.new_points(event.image, event.t_s, scans, live_uv, math.inf if any_speed else None) if not event.textureless else []
            tn = time.perf_counter()
            landmarks, uv, sigma_px, point_steps = observations
            self._send_keyframe(event.t_s, (landmarks, uv, sigma_px), new, point_steps, frame, scans)
            graph_s += time.perf_counter() - tn
            map_s += tn - tg
        tg = time.perf_counter()
        timing["graph_worker"] += self._take_results(client.results())
        graph_s += time.perf_counter() - tg
        if observations is not None and client.in_process:
            for hook in self.keyframe_hooks:
                hook(self)
        return map_s, graph_s

    def _finish_frame(self) -> bool:
        """The last frame's keyframe work, if it waited (``defer_keyframe_work``): done now, its time
        kept in that frame's record (``after_frame``, seconds). True if there was any."""
        if self._after_frame is None:
            return False
        event, observations, timing, frame = self._after_frame
        self._after_frame = None
        t0 = time.perf_counter()
        self._keyframe_work(event, observations, timing, frame)
        timing["after_frame"] = time.perf_counter() - t0
        return True

    def _take_results_before_update(self, m: FrameMatches, T_pred: np.ndarray, U: np.ndarray, timing: dict) -> tuple[FrameMatches, np.ndarray]:
        """The graph's results that came back while this frame was searched (a second process's), taken
        before its pose update: the update then starts from the smoothed keyframe and points. Returns
        the matches without the points the graph has marginalised, and the prediction moved with the
        correction."""
        results = self._client.results()
        if not results:
            return m, T_pred
        ids, T_before = self.live.ids.copy(), self._filter.T.copy()
        timing["graph_worker"] += self._take_results(results)
        if len(self.live) != len(ids):
            m = m.for_points(np.isin(ids, self.live.ids))
        if not np.array_equal(self._filter.T, T_before):
            T_pred = self._filter.T @ U
        return m, T_pred

    def _motion_since_last_frame(self, event: CameraFrame) -> tuple[float, np.ndarray, np.ndarray]:
        """The time since the last frame, seconds, and the motion over it with its covariance:
        the odometry's, or (without) constant velocity from the last two frames' poses; across a
        camera gap, refined by the images on either side (:class:`~dem_graph.frontend.gap_bridge.GapBridge`)."""
        dt, increment = self._motion.advance(event.t_s)
        if increment is not None:
            U, Q = increment
        else:
            R_speed = self._measure_speed(event) if dt > 0 and self._speed_unknown else None
            U, Q = constant_velocity_increment(self._filter.v_body, dt, self._motion.sigma_acc)
            if R_speed is not None:  # the measured speed's uncertainty over the frame, on the translation
                Q = Q.copy()
                Q[3:, 3:] += R_speed * dt**2
        U, Q = self.frontend.gap_bridge.refine(event.t_s, event.image, event.textureless, U, Q)
        return dt, U, Q

    def _measure_speed(self, event: CameraFrame) -> np.ndarray | None:
        """Without odometry, at the start or after a frame that tracked nothing: the filter's velocity
        taken from the ground's motion since the last image (the speed held was a guess); returns the
        measurement's covariance (3x3), m^2/s^2, or None when nothing was measured."""
        measured = self._ground_velocity(self.frontend, event)
        if measured is None:
            return None
        self._filter.v_body[3:], R = measured
        return R

    def _gyro_rotation(self, samples, t_a_s: float, t_b_s: float, U: np.ndarray, Q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The frame's motion with its rotation measured by the gyroscope (the graph's latest bias
        taken off; its covariance the gyro's, uncorrelated with the translation): a hundred times
        tighter than wheel odometry's over a frame, so the search regions shrink where the vehicle
        turns or pitches. Unchanged when the ``samples`` (:meth:`ImuBuffer.span`) do not cover the frame (None)."""
        if samples is None:
            self.frontend.counters["imu_frames_without_gyro"] += 1
            return U, Q
        return with_rotation(U, Q, *gyro_rotation(self._imu.spec, samples, t_a_s, t_b_s, self._client.imu_bias[3:]))

    def _split_refreshed(self, idx: np.ndarray) -> np.ndarray:
        """Points whose patch was refreshed in this frame now follow a new landmark (tied to the
        old one at the next keyframe), their covariance widened by the link's; a point of the front
        end's own (beyond ``graph_max_landmarks``) keeps its number and is only widened. Returns, per
        match, the old landmark or -1."""
        live, tracks = self.live, self.frontend.tracks
        old = np.full(len(idx), -1, dtype=np.int64)
        sigma2 = self.config.split_link_sigma_m**2
        for j, i in enumerate(idx):
            segment = tracks[int(live.ids[i])].segment
            if segment == live.segment[i]:
                continue
            Sigma_old = np.linalg.inv(live.info[i])
            landmark = int(live.landmark[i])
            if landmark >= 0:
                old[j] = landmark
                landmark = self._client.split_landmark(int(live.ids[i]), landmark, Sigma_old)
                if self._batch is not None:
                    self._batch.add_link(int(old[j]), landmark)
            live.follow(i, landmark, segment, np.linalg.inv(Sigma_old + sigma2 * np.eye(3)))
        return old

    def _send_keyframe(self, t_s: float, observations: tuple[np.ndarray, np.ndarray, np.ndarray], new: list[NewPoint], point_steps: np.ndarray, frame: int, scans: list) -> None:
        """The keyframe (opened here unless it was in its frame, number ``frame``) to the graph, with
        the laser's ties when they are on (``scans``: those since the last keyframe); its new points
        join the live ones (and the batch's log)."""
        if not self._client.keyframe_open:
            self._client.open_keyframe(t_s, self._filter.T)
        ties = self._laser_ties(t_s, frame, scans) if self._ties is not None else NO_TIES
        imu = None
        if self._imu is not None:
            t_prev = self._client.keyframe_before_open_t_s
            if t_s > t_prev:
                imu = self._imu.span(t_prev, t_s)
                if imu is None:
                    self.frontend.counters["imu_spans_missing"] += 1
            self._imu.drop_before(t_s)
        budget = self.config.graph_landmark_budget
        own: list[NewPoint] = []
        if budget is not None and new:
            room = max(0, budget - int(np.count_nonzero(self.live.landmark >= 0)))
            new, own = new[:room], new[room:]
        started = self._client.send_keyframe(self._filter.P_loc, observations, new, point_steps, imu, ties)
        if self._batch is not None and (len(ties) or len(ties.level_landmarks) or ties.pin_start is not None):
            self._batch.add_ties(ties)
        if started is not None:
            landmarks, X_world, Sigma_world = started
            self.live.add(np.array([p.point_id for p in new]), landmarks, X_world, Sigma_world)
            if self._batch is not None:
                self._batch.add_seeds(frame, new, landmarks)
        if own:
            self._keep_in_front_end(own)
        self._frames_since_keyframe = 0

    def _laser_ties(self, t_s: float, frame: int, scans: list) -> LaserTies:
        """The open keyframe's scans kept, and the landmarks of the window (live ones where they are
        now) tied to the kept scans of their ground."""
        client, live = self._client, self.live
        k = client.open_keyframe_number
        self._ties.add_scans(k, frame, t_s, client.poses[k], scans, self._filter.history)
        poses, points = client.window()
        in_graph = live.landmark >= 0
        points.update(zip(live.landmark[in_graph].tolist(), live.X[in_graph]))
        landmarks = np.fromiter(points, dtype=np.int64, count=len(points))
        return self._ties.ties(poses, landmarks, np.array([points[lm] for lm in landmarks.tolist()]).reshape(-1, 3), t_s)

    def _keep_in_front_end(self, new: list[NewPoint]) -> None:
        """New points beyond ``graph_max_landmarks``: live points of the front end only, numbered
        ``-1 - point_id`` where a landmark's number would be (never sent to the graph)."""
        X_world, Sigma_world = seeds_in_world(self._filter.T, new)
        ids = np.array([p.point_id for p in new], dtype=np.int64)
        self.live.add(ids, -1 - ids, X_world, Sigma_world)
        self.frontend.counters["points_front_end_only"] += len(new)

    # --- the graph's results -----------------------------------------------------------------
    def _take_results(self, results: list[GraphResult], restart: bool = True) -> float:
        """Apply the graph's results in order (a failed update restarts the graph from the current
        estimates, unless ``restart`` is false); returns the graph's time on them, seconds."""
        worker_s = 0.0
        while results:
            for r in results:
                worker_s += r.worker_s
                if r.waiting:
                    continue
                if r.failure is not None:
                    if restart:
                        log.warning("%s; restarting the smoother from the current estimates", r.failure)
                        self._client.restart(self.live, self._filter.T)
                    else:
                        log.warning("%s (at the end of the run: the estimates before it are kept)", r.failure)
                    continue
                self._apply_result(r)
            results = self._client.results()  # a restart's answer, in-process at once
        return worker_s

    def _apply_result(self, r: GraphResult) -> None:
        """The graph's smoothed keyframe ``r.k`` moves the current pose with it (a world-frame
        correction); the live points take the graph's estimates, and those it has marginalised are
        archived."""
        correction, C, keep = self._client.apply(r, self.live)
        if correction is not None:
            self._filter.correct(correction, C)
        for i in np.flatnonzero(~keep):
            self._archive(int(i), "marginalized")
        self.live.keep(keep)

    # --- map management ----------------------------------------------------------------------
    def _point_covariance_world(self, i: int) -> np.ndarray:
        """Live point ``i``'s covariance: its own (relative to the keyframes) plus the anchor
        keyframe pose's marginal carried to it (first order)."""
        return self._client.anchor.point_covariance(self.live.X[i], self.live.info[i])

    def _own_xyz(self, i: int) -> np.ndarray | None:
        """Live point ``i``'s position to archive: its own for a point of the front end's only; None
        for a landmark (the graph's latest estimate is taken when asked for)."""
        return self.live.X[i] if self.live.landmark[i] < 0 else None

    def _archive(self, i: int, reason: str) -> None:
        self._archived.archive(int(self.live.ids[i]), reason, self._point_covariance_world(i), self._own_xyz(i))

    def _drop_points(self) -> np.ndarray:
        keep, uv = self._archived.drop_points(self.live.ids, self.live.X, self._filter.T, lambda i: (self._point_covariance_world(i), self._own_xyz(i)))
        self.live.keep(keep)
        return uv

    # --- what the live map reads -------------------------------------------------------------
    def recent_poses(self, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The last ``n`` frames with the poses the smoother's latest keyframe estimates give them."""
        t, _, P = super().recent_poses(n)
        return t, self._client.smoothed_poses(last=len(t)), P

    def live_points(self) -> tuple[np.ndarray, np.ndarray]:
        return self.live.ids.copy(), self.live.X.copy()

    def archived_points_since(self, start: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
        """The points that left, each at the graph's latest estimate of its landmark (left out while it has none)."""
        pts, landmark_of = self._client.points, self._client.landmarks.of_point
        return self._archived.since(start, lambda pid: pts.get(landmark_of.get(pid, -1)))

    # --- results -----------------------------------------------------------------------------
    def result(self) -> EstimatorResult:
        pts, live, landmark_of = self._client.points, self.live, self._client.landmarks.of_point
        res = self._archived.result(
            self.name, self._frames, live.ids, lambda i: live.X[i], self._point_covariance_world, archived_xyz=lambda pid: pts[landmark_of[pid]]
        )
        self._client.count(res.counters)
        res.graph_update_s = {phase: list(seconds) for phase, seconds in self._client.update_phases.items()}
        batch_result = self._batch.result if self._batch is not None else None
        if batch_result is not None:
            return batch_result.apply_to(res, landmark_of)
        if self._batch is not None:  # stopped before the end: what there is, is the online pass
            res.name = ONLINE_PASS_ONLY
        if self._frames:
            res.extra_poses[SMOOTHED_TRAJECTORY] = self.smoothed_poses()
        return res


__all__ = ["ONLINE_PASS_ONLY", "Isam2Config", "Isam2Options", "Isam2Slam", "LivePoints"]
