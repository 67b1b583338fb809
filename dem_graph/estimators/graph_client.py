"""The graph estimator's side of its graph: what it sends, what it knows of the smoother's
estimates, and how the results move its own.

Each keyframe goes to the graph (:mod:`dem_graph.estimators.graph_worker`, in this process or in a
second one) as a :class:`~dem_graph.estimators.graph_worker.KeyframeMessage`: the pose, the motion
since the last keyframe, the inlier observations, the new landmarks with their seeds and the links
of refreshed patches. A :class:`~dem_graph.estimators.graph_worker.GraphResult` (in the same frame,
or keyframes later) gives the smoothed keyframe: its change since it was sent is a world-frame
correction of the current pose and of the keyframes sent since, and the live points take the
smoothed landmarks (or leave, when marginalised). A failed update restarts the smoother from the
current estimates.

The output covariance rides on the latest keyframe whose marginal is known (:class:`PoseAnchor`),
carried to the frame by the motion covariance since.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass

import numpy as np

from dem_graph.errors import DemGraphError
from dem_graph.estimators.graph_worker import (
    DelayedProcessGraph,
    GraphResult,
    GraphSetup,
    InProcessGraph,
    KeyframeMessage,
    NewLandmark,
    ProcessGraph,
    RestartMessage,
)
from dem_graph.estimators.isam2_config import Isam2Config
from dem_graph.estimators.keyframe_graph import KeyframeGraph
from dem_graph.estimators.laser_ties import NO_TIES, LaserTies
from dem_graph.estimators.live_points import LivePoints
from dem_graph.frontend.frontend import NewPoint
from dem_graph.geometry.lie import adjoint, skew
from dem_graph.geometry.rig import SensorRig
from dem_graph.geometry.se3 import invert, nearest_pose, transform_points


@dataclass
class PoseAnchor:
    """A keyframe's pose ``T`` (``T_world_body``) with its marginal covariance ``P`` from the smoother
    (or the filter's, without marginals), the motion covariance ``Q`` since it and its time."""

    T: np.ndarray
    P: np.ndarray
    Q: np.ndarray
    t_s: float

    def pose_covariance(self, T_world_body: np.ndarray) -> np.ndarray:
        """The covariance of the pose ``T_world_body``: the marginal carried to it, plus the motion
        covariance since (6x6, right perturbation)."""
        A = adjoint(invert(invert(self.T) @ T_world_body))
        P = A @ self.P @ A.T + self.Q
        return 0.5 * (P + P.T)

    def point_covariance(self, X_world: np.ndarray, info: np.ndarray) -> np.ndarray:
        """A point's world covariance: its own (the inverse of its 3x3 information ``info``, relative to
        the keyframes) plus the marginal carried to ``X_world`` (first order)."""
        p_body = transform_points(invert(self.T), X_world[None])[0]
        R = self.T[:3, :3]
        J = np.concatenate([-R @ skew(p_body), R], axis=1)
        return np.linalg.inv(info) + J @ self.P @ J.T


class Landmarks:
    """The numbering of the graph's landmarks ``L(j)``, one per patch segment of a point: which one
    each point follows now, which keyframe's message started each, and the links of refreshed
    patches waiting for the next keyframe."""

    def __init__(self):
        self._next = 0
        self.of_point: dict[int, int] = {}  # point id -> its current landmark
        self._keyframe: dict[int, int] = {}  # landmark -> the keyframe whose message started it
        self._pending_links: list[tuple[int, int, np.ndarray]] = []  # (old, new landmark, old covariance)

    def start(self, n: int) -> np.ndarray:
        """Numbers for ``n`` new landmarks."""
        landmarks = np.arange(self._next, self._next + n)
        self._next += n
        return landmarks

    def split(self, point_id: int, old: int, Sigma_old: np.ndarray) -> int:
        """Point ``point_id``'s patch was refreshed: it follows a new landmark from now, linked to
        ``old`` (covariance ``Sigma_old``) at the next keyframe; returns the new landmark."""
        new = self._next
        self._next += 1
        self._pending_links.append((old, new, Sigma_old))
        self.of_point[point_id] = new
        return new

    def take_links(self) -> list[tuple[int, int, np.ndarray]]:
        links, self._pending_links = self._pending_links, []
        return links

    def drop_links(self) -> None:
        self._pending_links = []

    def entered(self, landmarks, k: int) -> None:
        """``landmarks`` entered the graph with keyframe ``k``'s message (or its restart)."""
        for lm in landmarks:
            self._keyframe[lm] = k

    def entered_after(self, landmark: int, k: int) -> bool:
        return self._keyframe.get(landmark, -1) > k

    def continuing(self) -> dict[int, int]:
        """Each refreshed patch's new landmark whose link waits for the next keyframe, with the
        landmark it continues (the first one sent, when a patch was refreshed twice meanwhile)."""
        before = {new: old for old, new, _ in self._pending_links}
        out = {}
        for new, old in before.items():
            while old in before:
                old = before[old]
            out[new] = old
        return out


def seeds_in_world(T_world_body: np.ndarray, new: list[NewPoint]) -> tuple[np.ndarray, np.ndarray]:
    """New points' seeds carried from the body frame of ``T_world_body`` to the world: positions
    (n,3), m, and covariances (n,3,3), m^2."""
    R = T_world_body[:3, :3]
    return transform_points(T_world_body, np.array([p.p_body for p in new])), R @ np.array([p.Sigma_body for p in new]) @ R.T


def _take_window(kept: dict[int, np.ndarray], window: set[int], estimates: dict[int, np.ndarray]) -> set[int]:
    """The latest ``estimates`` (a result's window) into ``kept``; returns the new window's keys.

    A second process's estimates arrive as rows of one array per result (a view each:
    :class:`~dem_graph.estimators.graph_worker.GraphResult`). ``kept`` holds every estimate for the
    whole run, so one that has left the window (in ``window``, not in ``estimates``: marginalised,
    or dropped by a restart) is copied to an array of its own, and no result's array stays alive for
    the rows it left behind."""
    kept.update(estimates)
    for key in window.difference(estimates):
        value = kept.get(key)
        if value is not None and value.base is not None:
            kept[key] = value.copy()
    return set(estimates)


class GraphClient:
    """Sends keyframes to the graph and applies its results; keeps every keyframe's time and the
    latest estimates of keyframes (``poses``) and landmarks (``points``), the last keyframe's pose
    ``T_kf`` and the motion since it (``U_kf``, ``Q_kf``)."""

    def __init__(self, config: Isam2Config, rig: SensorRig, T_world_body: np.ndarray, P0: np.ndarray, t_s: float, counters: Counter):
        c = config
        setup = GraphSetup(
            T_world_body.copy(), P0, t_s, c.lag_s, c.relinearize_threshold, c.relinearize_skip, c.marginalize_every_s, c.optimizer,
            rig.camera_model, np.array(rig.T_body_cam, dtype=float), c.frontend.camera_point_sigma_px, c.split_link_sigma_m, c.robust,
            rig.imu if c.motion.use_imu else None, c.motion.initial_sigma_speed_mps,
        )  # fmt: skip
        in_second_process, delay = c.graph_placement
        if in_second_process and delay:
            self._graph = DelayedProcessGraph(setup, delay)
        elif in_second_process:
            self._graph = ProcessGraph(setup, c.graph_lag_limit(1), c.graph_process_nice)
        else:
            self._graph = InProcessGraph(setup, delay)
        # the results come back whenever the second process has them (no fixed delay): the run depends
        # on the timing, and nothing in a frame waits for them
        self.results_when_ready = c.results_when_ready
        self._when_behind = c.graph_when_behind or "merge"
        # per graph update taken: its time by phase, seconds ("total": the whole update)
        self.update_phases: dict[str, list[float]] = {}
        self._pose_covariance_every_s = c.pose_covariance_every_s
        self._counters = counters
        self.keyframe_t_s: list[float] = [t_s]
        self.poses: dict[int, np.ndarray] = {0: T_world_body.copy()}
        self.points: dict[int, np.ndarray] = {}
        self._window_poses: set[int] = set()  # the keyframes and landmarks of the last result's window
        self._window_points: set[int] = set()
        self.landmarks = Landmarks()
        # keyframes sent whose result is not back: the front end's pose for each (moved with every
        # correction since) and the motion covariance since it
        self._sent_T: dict[int, np.ndarray] = {}
        self._Q_since: dict[int, np.ndarray] = {}
        self._graph_lag: list[int] = []  # per result: keyframes sent since the one it answers
        self.T_kf = T_world_body.copy()  # the last keyframe's pose
        self.U_kf, self.Q_kf = np.eye(4), np.zeros((6, 6))  # motion since the last keyframe
        self.anchor = PoseAnchor(T_world_body.copy(), P0.copy(), np.zeros((6, 6)), t_s)
        self._marginal_asked = False  # a keyframe's marginal has been asked for and is not back
        self._frame_anchor: list[tuple[int, np.ndarray]] = []  # per frame: (keyframe, T_keyframe_frame)
        # keyframes sent whose result is not back: the step each of their observations gave its point
        # (landmark -> metres, world frame), taken again on top of the graph's older estimate (apply)
        self._steps_in_flight: dict[int, dict[int, np.ndarray]] = {}
        self._opened: tuple | None = None  # the keyframe opened and not yet sent: (k, t_s, T, U_kf, Q_kf, the keyframe before's time)
        self.imu_bias = np.zeros(6)  # the graph's latest IMU biases [accel m/s^2, gyro rad/s] (zero until it has some)

    @property
    def graph(self) -> KeyframeGraph:
        """The smoother itself, when it runs in this process (studies and tests)."""
        if not self.in_process:
            raise DemGraphError(
                "the graph runs in a second process (graph_process, or the batch's batch_graph_delay_keyframes above 0); its smoother is not reachable from here"
            )
        return self._graph.worker.graph

    @property
    def in_process(self) -> bool:
        return isinstance(self._graph, InProcessGraph)

    @property
    def next_keyframe(self) -> int:
        """The number the next keyframe sent will have."""
        return len(self.keyframe_t_s)

    def set_lag_limit(self, keyframes: int) -> None:
        """Keyframes the front end may run ahead of the graph's newest result from now on (a second
        process whose results come when ready; elsewhere nothing runs ahead)."""
        if self.results_when_ready:  # (the graph is then a ProcessGraph)
            self._graph.max_lag = int(keyframes)

    def ready_for_keyframe(self) -> bool:
        """The graph can take the next keyframe: in this process it always can; in a second process
        it must be within ``graph_max_lag`` keyframes of it. Past that, with ``graph_when_behind:
        wait`` the frame waits for the graph; with ``merge`` (the default outside a run replayed as
        fast as possible) it does not, and the answer is no. Until the graph has answered its first
        keyframe it is always waited for (the process is ready before the estimator is made, so its
        first answer takes one update). Results arriving meanwhile are kept for :meth:`results`."""
        k = self.next_keyframe
        if not self._graph.started or self._when_behind == "wait":
            return self._graph.wait_for(k, None)
        return self._graph.wait_for(k, 0.0)

    # --- per frame ---------------------------------------------------------------------------
    def carry(self, U: np.ndarray, Q: np.ndarray, A: np.ndarray | None = None, predicted: tuple[np.ndarray, np.ndarray] | None = None) -> None:
        """A frame's motion ``U`` (covariance ``Q``; ``A``: ``adjoint(invert(U))`` when the caller has
        it) extends the motion since the last keyframe, which goes to the graph's motion factor.
        The motion covariances since the anchor and since each keyframe whose result is not back,
        which carry the output pose covariance, take the motion the frame's pose was predicted with:
        ``predicted`` (its covariance and adjoint; None: ``U``'s). With an IMU that is the
        gyroscope's rotation, far tighter than wheel odometry's (docs/imu_study.md, "Every estimator
        on an Intel Xeon")."""
        A = adjoint(invert(U)) if A is None else A
        self.U_kf = self.U_kf @ U
        self.Q_kf = A @ self.Q_kf @ A.T + Q
        Q_pose, A_pose = (Q, A) if predicted is None else predicted
        self.anchor.Q = A_pose @ self.anchor.Q @ A_pose.T + Q_pose
        for k, Q_k in self._Q_since.items():
            self._Q_since[k] = A_pose @ Q_k @ A_pose.T + Q_pose

    def split_landmark(self, point_id: int, old: int, Sigma_old: np.ndarray) -> int:
        """A refreshed patch: point ``point_id`` continues on a new landmark (see :meth:`Landmarks.split`),
        at the old one's estimate until the graph has it; returns the new landmark."""
        new = self.landmarks.split(point_id, old, Sigma_old)
        self.points[new] = self.points[old].copy()  # its estimate until the graph has it
        return new

    def anchor_frame(self, T_world_body: np.ndarray) -> None:
        """Keep the frame's pose relative to the last keyframe, for :meth:`smoothed_poses`."""
        k = len(self.keyframe_t_s) - 1
        self._frame_anchor.append((k, invert(self.T_kf) @ T_world_body))

    # --- keyframes ---------------------------------------------------------------------------
    def open_keyframe(self, t_s: float, T_world_body: np.ndarray) -> None:
        """A keyframe at ``t_s`` with the pose ``T_world_body``: numbered, and the frames from this one
        on ride on it (:meth:`anchor_frame`); its message follows with :meth:`send_keyframe`, before
        any result is taken."""
        T = T_world_body
        t_prev = self.keyframe_t_s[-1]
        k = len(self.keyframe_t_s) - 1
        if t_s > t_prev:  # else: the first frame, at the start pose's time
            k += 1
            self.keyframe_t_s.append(t_s)
        self._opened = (k, t_s, T.copy(), self.U_kf, self.Q_kf, t_prev)
        self.poses.setdefault(k, T.copy())  # until the graph's estimate is back
        self.T_kf = T.copy()
        self.U_kf, self.Q_kf = np.eye(4), np.zeros((6, 6))

    @property
    def keyframe_open(self) -> bool:
        """A keyframe is open (:meth:`open_keyframe`) and its message not sent yet."""
        return self._opened is not None

    @property
    def open_keyframe_number(self) -> int:
        """The open keyframe's number (:meth:`open_keyframe`)."""
        if self._opened is None:
            raise DemGraphError("no keyframe is open: open_keyframe first")
        return self._opened[0]

    def window(self) -> tuple[dict[int, np.ndarray], dict[int, np.ndarray]]:
        """The keyframes (T_world_body) and landmarks (X_world) of the last result's window at their
        latest estimates, with the keyframes sent since and the open one (the front end's guesses;
        the landmarks started since are live points)."""
        sent = set(self._sent_T) | ({self._opened[0]} if self._opened is not None else set())
        poses = {k: self.poses[k] for k in self._window_poses | sent if k in self.poses}
        return poses, {lm: self.points[lm] for lm in self._window_points if lm in self.points}

    @property
    def keyframe_before_open_t_s(self) -> float:
        """The time of the keyframe before the open one (the open one's own for the first frame)."""
        if self._opened is None:
            raise DemGraphError("no keyframe is open: open_keyframe first")
        return self._opened[5]

    def send_keyframe(
        self,
        P_loc: np.ndarray,
        observations: tuple[np.ndarray, np.ndarray, np.ndarray],
        new: list[NewPoint],
        point_steps: np.ndarray | None = None,
        imu: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
        ties: LaserTies = NO_TIES,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """The open keyframe's message to the graph: its pose, the motion since the last one, its
        observations, the new points with their seeds and the refreshed patches' links. Returns the
        new points' landmarks, world positions and covariances (None without new points).
        ``point_steps`` (m,3): how far each observation moved its live point (see :meth:`apply`);
        ``imu``: the IMU samples since the last keyframe (:meth:`~dem_graph.estimators.imu_preintegration.ImuBuffer.span`);
        ``ties``: landmarks tied to the scans of their ground (:mod:`~dem_graph.estimators.laser_ties`)."""
        if self._opened is None:
            raise DemGraphError("no keyframe is open: open_keyframe first")
        k, t_s, T, U_kf, Q_kf, _ = self._opened
        self._opened = None
        new_landmarks = []
        started = None
        if new:
            X_world, Sigma_world = seeds_in_world(T, new)
            landmarks = self.landmarks.start(len(new))
            for p, lm, Xw in zip(new, landmarks, X_world):
                new_landmarks.append(NewLandmark(int(lm), Xw, p.kind, np.asarray(p.p_body, dtype=float), np.asarray(p.Sigma_body, dtype=float)))
                self.landmarks.of_point[p.point_id] = int(lm)
                self.points[int(lm)] = Xw
            started = landmarks, X_world, Sigma_world
        links = self.landmarks.take_links()
        self.landmarks.entered([p.landmark for p in new_landmarks] + [new_lm for _, new_lm, _ in links], k)
        every = self._pose_covariance_every_s
        want_marginal = every > 0 and not self._marginal_asked and t_s - self.anchor.t_s >= every
        self._marginal_asked |= want_marginal
        # keyframe k - 1 as this frame's pose was measured from: in flight as corrected since, else the graph's
        T_prev = self._sent_T.get(k - 1, self.poses.get(k - 1))
        T_prev = None if T_prev is None else T_prev.copy()
        self._graph.send(KeyframeMessage(k, t_s, T.copy(), U_kf, Q_kf, *observations, links, new_landmarks, want_marginal, imu, T_prev, ties))
        self._sent_T[k] = T.copy()
        self._Q_since[k] = np.zeros((6, 6))
        if point_steps is not None:
            self._steps_in_flight[k] = dict(zip(observations[0].tolist(), point_steps))
        if every <= 0:
            self.anchor.T, self.anchor.P, self.anchor.Q = T.copy(), P_loc.copy(), np.zeros((6, 6))
        return started

    def results(self) -> list[GraphResult]:
        """The graph's results that have arrived (in-process: every message's, at once)."""
        return self._graph.results()

    def apply(self, r: GraphResult, live: LivePoints) -> tuple[np.ndarray | None, np.ndarray, np.ndarray]:
        """Take the graph's result: the smoothed keyframe ``r.k`` moves the last keyframe and the
        keyframes sent since (a world-frame correction), its marginal (if asked for) becomes the
        anchor, and the live points take the graph's estimates (the front end's own points, beyond
        ``graph_max_landmarks``, move with the correction). Returns the correction (None when
        the keyframe was sent before a restart), its nearest pose ``C`` (identity then) and the mask
        of the live points still in the graph (the others were marginalised).

        A result keyframes late holds none of the observations sent since, while each live point's
        information does: a point set back to the graph's estimate alone would claim that information
        for an older position, and the next frames would reject its good matches as outliers (1.7-2.2 %
        of the matches with results 4-6 keyframes late, against 0.3 % in-process; docs/isam2_design.md).
        So the point takes the graph's estimate plus the steps those later observations gave it."""
        k = r.k
        self._window_poses = _take_window(self.poses, self._window_poses, r.poses)
        self._window_points = _take_window(self.points, self._window_points, r.points)
        if r.imu_bias is not None:
            self.imu_bias = r.imu_bias
        if r.recoveries:
            self._counters["graph_recoveries"] = max(self._counters["graph_recoveries"], r.recoveries)
        self._graph_lag.append(len(self.keyframe_t_s) - 1 - k)
        for phase, seconds in {"total": r.worker_s, **r.phases}.items():
            self.update_phases.setdefault(phase, []).append(seconds)
        correction, C = None, np.eye(4)
        if k in self._sent_T:
            # kept on SE(3): corrections compose, and invert() assumes orthonormal rotations
            correction = r.poses[k] @ invert(self._sent_T[k])
            C = nearest_pose(correction)
            self.T_kf = C @ self.T_kf
            self._sent_T = {j: C @ T for j, T in self._sent_T.items() if j > k}
        if r.marginal is not None:
            self.anchor.T, self.anchor.P, self.anchor.Q = r.poses[k].copy(), r.marginal, self._Q_since[k].copy()
            self.anchor.t_s = self.keyframe_t_s[k]
            self._marginal_asked = False
        self._Q_since = {j: Q for j, Q in self._Q_since.items() if j > k}
        self._steps_in_flight = {j: steps for j, steps in self._steps_in_flight.items() if j > k}
        later_steps = self._later_steps()
        continuing = self.landmarks.continuing()
        keep = np.ones(len(live), dtype=bool)
        points = r.points
        own = []  # the front end's own points (graph_max_landmarks): placed from poses the correction has moved
        for i, lm in enumerate(live.landmark.tolist()):
            if lm < 0:
                own.append(i)
                continue
            X_lm = points.get(lm)
            if X_lm is not None:
                live.X[i] = X_lm + later_steps.get(lm, 0.0)
            elif (before := continuing.get(lm)) is not None:
                # a patch refreshed since the last keyframe sent (its link goes with the next one): the
                # point is still where the landmark it continues is
                if before in points:
                    live.X[i] = points[before] + later_steps.get(before, 0.0)
            elif self.landmarks.entered_after(lm, k):  # started after keyframe k: placed from a pose the correction has moved
                live.X[i] = transform_points(C, live.X[i][None])[0]
                self.points[lm] = live.X[i].copy()
            else:
                keep[i] = False
        if own and correction is not None:
            live.X[own] = transform_points(C, live.X[own])
        return correction, C, keep

    def _later_steps(self) -> dict[int, np.ndarray]:
        """Per landmark, the sum of the steps its observations in the keyframes still in flight gave it."""
        total: dict[int, np.ndarray] = {}
        for steps in self._steps_in_flight.values():
            for lm, step in steps.items():
                total[lm] = total[lm] + step if lm in total else step.copy()
        return total

    def restart(self, live: LivePoints, T_world_body: np.ndarray) -> None:
        """A new smoother at the newest keyframe, from the front end's estimates: the live points
        and the current pose ``T_world_body``'s covariance."""
        self._counters["graph_restarts"] += 1
        k = len(self.keyframe_t_s) - 1
        priors = {int(lm): (live.X[i].copy(), self.anchor.point_covariance(live.X[i], live.info[i])) for i, lm in enumerate(live.landmark) if lm >= 0}
        self.landmarks.entered(priors, k)
        self.landmarks.drop_links()
        self._marginal_asked = False
        self._sent_T = {k: self.T_kf.copy()}
        self._steps_in_flight = {}  # the priors are the live points, with every step taken
        self._graph.send(RestartMessage(k, self.T_kf.copy(), self.anchor.pose_covariance(T_world_body), priors))

    # --- the end -----------------------------------------------------------------------------
    def finish(self) -> tuple[list[GraphResult], tuple[dict[int, np.ndarray], dict[int, np.ndarray]]]:
        """The results not yet taken, and the final estimates once the graph has applied every message."""
        return self._graph.finish()

    def close(self, final_estimates: tuple[dict[int, np.ndarray], dict[int, np.ndarray]]) -> None:
        """Keep the graph's final estimates of every keyframe and landmark, and stop it."""
        poses, points = final_estimates
        self.poses.update(poses)
        self.points.update(points)
        self._graph.close()

    @property
    def latest_lag(self) -> int | None:
        """Keyframes sent after the one the latest result answered (None before the first result)."""
        return self._graph_lag[-1] if self._graph_lag else None

    def smoothed_poses(self, last: int | None = None) -> np.ndarray:
        """Every frame's pose (or the ``last`` frames') from the latest keyframe estimates (each frame rides on the keyframe before it)."""
        poses = self.poses
        if last is None:  # the run's smoothed trajectory: one product per frame, as it always was
            return np.array([poses[k] @ T_rel for k, T_rel in self._frame_anchor]).reshape(-1, 4, 4)
        anchors = self._frame_anchor[-last:] if last > 0 else []
        if not anchors:
            return np.zeros((0, 4, 4))
        return np.array([poses[k] for k, _ in anchors]) @ np.array([T_rel for _, T_rel in anchors])  # the live map's window, at once

    def count(self, counters: Counter) -> None:
        """The keyframes made and how late the graph's results came (median and most keyframes)."""
        counters["keyframes"] = len(self.keyframe_t_s)
        if self._graph_lag:
            counters["graph_lag_keyframes_median"] = int(np.median(self._graph_lag))
            counters["graph_lag_keyframes_max"] = int(np.max(self._graph_lag))
            counters["graph_results_late"] = int(np.count_nonzero(self._graph_lag))  # taken after the next keyframe was sent


__all__ = ["GraphClient", "Landmarks", "PoseAnchor", "seeds_in_world"]
