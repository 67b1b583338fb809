"""The factor-graph estimator: frame poses and map points in an incremental fixed-lag smoother (iSAM2).

Every frame (docs/isam2_design.md):
1. predict the pose from odometry (or a constant-velocity guess) and propagate its covariance;
2. track every live point in its search region, the 2x2 innovation covariance of the predicted
   pose (relative to the map) and of the point's own covariance (its information from the
   keyframes that saw it, poses held fixed), plus the pixel noise;
3. update the pose against the points (:func:`update_pose`: points fixed, their covariance as
   pixel noise, Huber weights).

Every frame by default (``keyframe_every: 1``), and otherwise every ``keyframe_every`` frames or
sooner when the map runs short of points, the frame becomes a keyframe of the graph: a message
(:mod:`dem_graph.estimators.graph_worker`) with the pose, the odometry since the last keyframe,
the frame's inlier observations and the new points with their laser or flat-ground seeds; the
graph adds the factors and runs one iSAM2 update (:class:`KeyframeGraph`), cutting the window back
to ``lag_s`` every ``marginalize_every_s``. When its result is back (in the same frame, or some
keyframes later with ``graph_process: true``) the smoothed keyframe pose corrects the current one
and the live points take their smoothed positions. The frame's output is the pose after all this:
what was known at that frame.

With keyframes every n > 1 frames, the observations in between are used by the per-frame pose, and
reach the graph only through the weight of the next keyframe observation of the point
(``sigma_px / sqrt(n)``). That is cheaper, but it was less accurate and diverged in the turns of
the ``paper`` log (see the design notes).

``batch: true`` (``--estimator isam2-batch``) also records every observation of every frame, and at
the end smooths the whole log at once (:mod:`dem_graph.estimators.batch`). Its online pass only
associates the data, so it makes a keyframe every ``batch_keyframe_every`` (5) frames: a fifth of the
iSAM2 updates, while the batch still has a pose and the observations of every frame.
"""

from __future__ import annotations

import logging
import time
from typing import Literal

import numpy as np
from pydantic import Field

from dem_graph.config_types import StrictModel
from dem_graph.datasets.events import CameraFrame
from dem_graph.errors import DemGraphError
from dem_graph.estimators.base import EstimatorResult, FrameDrivenEstimator, FrameRecord
from dem_graph.estimators.false_matches import FalseMatches
from dem_graph.estimators.graph_worker import (
    GraphResult,
    GraphSetup,
    InProcessGraph,
    KeyframeMessage,
    NewLandmark,
    ProcessGraph,
    RestartMessage,
)
from dem_graph.estimators.keyframe_graph import KeyframeGraph
from dem_graph.estimators.measurement_log import MeasurementLog
from dem_graph.estimators.motion import constant_velocity_increment
from dem_graph.estimators.point_archive import PointArchive
from dem_graph.estimators.pose_update import project_with_jacobians, update_pose
from dem_graph.estimators.settings import SharedSettings
from dem_graph.frontend.frontend import FrontEnd, NewPoint
from dem_graph.frontend.pose_history import PoseHistory
from dem_graph.geometry.lie import adjoint, local, skew
from dem_graph.geometry.rig import SensorRig
from dem_graph.geometry.se3 import invert, nearest_pose, transform_points

log = logging.getLogger(__name__)


class Isam2Options(StrictModel):
    """What only the graph estimator has."""

    keyframe_every: int = Field(1, ge=1, description="a keyframe every this many frames (1: every frame a pose of the graph; more is faster but was less accurate and, on paper, unstable in turns)")
    keyframe_min_live_fraction: float = Field(0.8, ge=0, le=1, description="also a keyframe when the live points fall below this fraction of the cap (new points enter at keyframes)")
    lag_s: float = Field(1.5, gt=0, description="fixed lag of the smoother, seconds: older variables are marginalised")
    marginalize_every_s: float = Field(
        0.5, gt=0, description="the window is cut back to the lag once it spans lag_s + this, seconds (one batch elimination of the window)"
    )
    relinearize_threshold: float = Field(0.01, gt=0, description="iSAM2 relinearises a variable whose update exceeds this")
    relinearize_skip: int = Field(1, ge=1, description="iSAM2 checks for relinearisation every this many updates")
    optimizer: Literal["dogleg", "gauss_newton"] = Field(
        "dogleg",
        description="iSAM2's step: dogleg (a trust region) or plain Gauss-Newton. The window's absolute height and tilt are known only to a few tenths of a metre "
        "and degree (nothing observes them but the odometry), and Gauss-Newton steps oscillated along them and jumped in the turns of paper",
    )
    keyframe_weighting: bool = Field(
        True, description="a keyframe observation carries the information of the frames that tracked the point since its last keyframe observation (sigma_px / sqrt(n))"
    )
    track_correlation: float = Field(
        0.0, ge=0, lt=1, description="lag-1 autocorrelation of a track's pixel errors from frame to frame (AR(1)); n frames then carry the information of n_eff < n independent ones"
    )
    split_link_sigma_m: float = Field(
        0.005, gt=0, description="a patch refresh starts a new landmark, tied to the old one with this sigma (the ground point under the new patch is a few mm away), metres"
    )
    robust: bool = Field(True, description="Huber kernel on projection factors and per-frame pixels")
    outlier_chi2: float = Field(9.21, gt=0, description="an observation whose normalised residual after the frame's pose update exceeds this (chi-square, 2 dof; 9.21 = 99 %) stays out of the graph")
    pose_covariance_every_s: float = Field(
        1.0, ge=0, description="take a keyframe pose's marginal covariance from the smoother (15-35 ms) at most this often, seconds; in between it is carried by odometry; 0: never (the covariance relative to the map)"
    )
    graph_process: bool = Field(
        False,
        description="run the graph (iSAM2 updates, the window's cut, marginals) in a second process, on another core: a frame then costs the front end's time, "
        "and the graph's results reach the front end one or more keyframes later (a run then depends on the timing); false: each keyframe's update ends in its own frame",
    )
    graph_max_lag: int = Field(
        10,
        ge=1,
        description="graph_process: keyframes the front end may run ahead of the graph's newest result before a frame waits for it; "
        "more keep frames short while an update runs long, at the price of later corrections (a log replayed faster than the graph follows drifts more)",
    )
    batch_keyframe_every: int = Field(
        5,
        ge=1,
        description="isam2-batch: keyframe_every of its online pass, which only associates the data (the batch has a pose for every frame); "
        "at 1 the in-process pass takes longer than the 100 m paper log was driven (docs/isam2_design.md)",
    )
    batch_max_iterations: int = Field(10, ge=1, description="isam2-batch: Levenberg-Marquardt iterations at most")
    batch_relative_error_tol: float = Field(1e-3, gt=0, description="isam2-batch: stop when the error falls by less than this fraction")


class Isam2Config(SharedSettings, Isam2Options):
    """The graph estimator's options with the settings every estimator shares."""

    batch: bool = Field(False, description="record every observation and smooth the whole log at the end (isam2-batch)")

    @property
    def keyframe_spacing(self) -> int:
        """Frames between keyframes in this run: ``batch_keyframe_every`` for the batch's online pass, else ``keyframe_every``."""
        return self.batch_keyframe_every if self.batch else self.keyframe_every


def effective_sample_size(n: np.ndarray, rho: float) -> np.ndarray:
    """How many independent samples the mean of ``n`` consecutive AR(1) samples with lag-1
    correlation ``rho`` is worth: ``n / (1 + 2 sum_{k<n} (1 - k/n) rho^k)``; ``n`` when ``rho`` is 0."""
    n = np.asarray(n, dtype=float)
    if rho == 0.0:
        return n
    k = np.arange(1, int(n.max()) if n.size else 1)
    terms = (1.0 - k[None, :] / n[:, None]) * rho ** k[None, :]
    inflation = 1.0 + 2.0 * np.sum(np.where(k[None, :] < n[:, None], terms, 0.0), axis=1)
    return n / inflation


class LivePoints:
    """The points being tracked: ids, world positions and each one's 3x3 information
    (its seed's plus its keyframe observations', poses held fixed); the graph landmark each one
    follows now and the patch segment it belongs to."""

    def __init__(self):
        self.ids = np.zeros(0, dtype=np.int64)
        self.landmark = np.zeros(0, dtype=np.int64)
        self.segment = np.zeros(0, dtype=np.int64)
        self.X = np.zeros((0, 3))
        self.info = np.zeros((0, 3, 3))
        self.n_since_keyframe = np.zeros(0, dtype=np.int64)  # inlier frames since the last keyframe observation

    def __len__(self) -> int:
        return len(self.ids)

    def add(self, ids, landmarks, X_world, Sigma_world) -> None:
        self.ids = np.concatenate([self.ids, np.asarray(ids, dtype=np.int64)])
        self.landmark = np.concatenate([self.landmark, np.asarray(landmarks, dtype=np.int64)])
        self.segment = np.concatenate([self.segment, np.zeros(len(ids), dtype=np.int64)])
        self.X = np.concatenate([self.X, np.asarray(X_world, dtype=float).reshape(-1, 3)])
        self.info = np.concatenate([self.info, np.linalg.inv(np.asarray(Sigma_world, dtype=float).reshape(-1, 3, 3))])
        self.n_since_keyframe = np.concatenate([self.n_since_keyframe, np.zeros(len(ids), dtype=np.int64)])

    def keep(self, mask: np.ndarray) -> None:
        self.ids, self.X, self.info = self.ids[mask], self.X[mask], self.info[mask]
        self.landmark, self.segment = self.landmark[mask], self.segment[mask]
        self.n_since_keyframe = self.n_since_keyframe[mask]

    def covariances(self) -> np.ndarray:
        return np.linalg.inv(self.info) if len(self) else np.zeros((0, 3, 3))


class Isam2Slam(FrameDrivenEstimator):
    """Keyframe iSAM2 smoothing with the shared front end; feed it events in time order."""

    def __init__(self, rig: SensorRig, T_world_body_initial: np.ndarray, t_start_s: float, has_odometry: bool, config: Isam2Config | None = None):
        self.config = config or Isam2Config()
        c = self.config
        self.name = "isam2-batch" if c.batch else "isam2"
        self.rig = rig
        self.frontend = FrontEnd(c.frontend, rig)
        super().__init__(c.motion, has_odometry, t_start_s)
        self._sigma_px = c.frontend.sigma_px
        self._gate = self.frontend.tracker.gate_chi2
        self.T = np.array(T_world_body_initial, dtype=float)
        P0 = np.eye(6) * c.motion.initial_sigma_pose**2
        self._T0, self._P0 = self.T.copy(), P0
        self.P_loc = P0.copy()  # pose covariance relative to the map (search regions)
        setup = GraphSetup(
            self.T.copy(), P0, self.t_s, c.lag_s, c.relinearize_threshold, c.relinearize_skip, c.marginalize_every_s, c.optimizer,
            rig.camera_model, np.array(rig.T_body_cam, dtype=float), c.frontend.camera_point_sigma_px, c.split_link_sigma_m, c.robust,
        )  # fmt: skip
        self._graph = ProcessGraph(setup, c.graph_max_lag) if c.graph_process else InProcessGraph(setup)
        # what the front end knows of the graph: every keyframe's time and the latest estimates of
        # keyframes and landmarks
        self.keyframe_t_s: list[float] = [self.t_s]
        self.poses: dict[int, np.ndarray] = {0: self.T.copy()}
        self.points: dict[int, np.ndarray] = {}
        self._landmark_keyframe: dict[int, int] = {}  # landmark -> the keyframe whose message started it
        # keyframes sent whose result is not back: the front end's pose for each (moved with every
        # correction since) and the motion covariance since it
        self._sent_T: dict[int, np.ndarray] = {}
        self._Q_since: dict[int, np.ndarray] = {}
        self._graph_lag: list[int] = []  # per result: keyframes sent since the one it answers
        self.T_kf = self.T.copy()  # the last keyframe's pose
        self.U_kf, self.Q_kf = np.eye(4), np.zeros((6, 6))  # motion since the last keyframe
        # the output covariance rides on the latest keyframe whose marginal is known: its pose, its
        # marginal and the motion covariance since
        self._anchor_T, self._anchor_P, self._anchor_Q = self.T.copy(), P0.copy(), np.zeros((6, 6))
        self._anchor_t_s = self.t_s
        self._marginal_asked = False  # a keyframe's marginal has been asked for and is not back
        self.frames_since_kf = 0
        self.live = LivePoints()
        self.history = PoseHistory(window=c.keyframe_spacing + 5)
        self.history.append(self.t_s, self.T)
        self._v_body = np.zeros(6)  # constant-velocity model: [angular, linear] per second
        self._v_body[3] = c.motion.initial_speed_mps
        self._speed_mps: float | None = None
        self._frames: list[FrameRecord] = []
        self._frame_anchor: list[tuple[int, np.ndarray]] = []  # per frame: (keyframe, T_keyframe_frame)
        self._archived = PointArchive(self.frontend)  # the graph's latest estimate of each landmark is asked for in result()
        self._false_matches = FalseMatches(c.false_matches, self.frontend.counters)
        self.log = MeasurementLog() if c.batch else None
        self._next_landmark = 0  # graph variable L(j): one per patch segment of a point
        self._landmark_of: dict[int, int] = {}  # point id -> its current landmark
        self._pending_links: list[tuple[int, int, np.ndarray]] = []  # (old, new landmark, old covariance)
        self.batch_result = None
        self.keyframe_hooks: list = []  # called as hook(self) after each keyframe's result is taken, in-process graph only (studies)

    @property
    def graph(self) -> KeyframeGraph:
        """The smoother itself, when it runs in this process (studies and tests)."""
        if not isinstance(self._graph, InProcessGraph):
            raise DemGraphError("the graph runs in a second process (graph_process: true); its smoother is not reachable from here")
        return self._graph.worker.graph

    def finish(self) -> None:
        super().finish()
        pending, (poses, points) = self._graph.finish()
        self._take_results(pending, restart=False)
        self.poses.update(poses)
        self.points.update(points)
        self._graph.close()
        if self.log is not None and self._frames:
            from dem_graph.estimators.batch import smooth_batch

            c = self.config
            self.batch_result = smooth_batch(
                # every frame's observation, with AR(1) errors: each carries (1 - rho) / (1 + rho) of an independent one's information
                self.log, self.rig, self._T0, self._P0, self.smoothed_poses(), self.points,
                self._sigma_px * np.sqrt((1 + c.track_correlation) / (1 - c.track_correlation)), c.frontend.camera_point_sigma_px,
                robust=c.robust, max_iterations=c.batch_max_iterations, relative_error_tol=c.batch_relative_error_tol,
            )

    # --- one frame ---------------------------------------------------------------------------
    def _process(self, event: CameraFrame) -> FrameRecord:
        self._pending_frame = None
        timing = {}
        t0 = time.perf_counter()
        T_pred = self._predict(event.t_s)
        t1 = time.perf_counter()
        idx, uv = self._track(event.image, event.t_s, T_pred)
        t2 = time.perf_counter()
        inlier = self._update_pose(T_pred, idx, uv)
        t3 = time.perf_counter()
        timing["prediction"], timing["tracking"], timing["update"] = t1 - t0, t2 - t1, t3 - t2
        split_old = self._split_refreshed(idx)
        self.live.n_since_keyframe[idx[inlier]] += 1
        if self.log is not None:
            # a refreshed point's match is an observation of the landmark before (matched with the
            # old patch) and defines the one after
            old = split_old[inlier]
            both = old >= 0
            landmarks = np.concatenate([self.live.landmark[idx[inlier]], old[both]])
            self.log.add_frame(event.t_s, self._U_frame, self._Q_frame, landmarks, np.concatenate([uv[inlier], uv[inlier][both]]))
        self.frames_since_kf += 1
        is_keyframe = self.frames_since_kf >= self.config.keyframe_spacing or len(self.live) < self.config.keyframe_min_live_fraction * self.config.frontend.max_points
        graph_s = 0.0
        if is_keyframe:
            tg = time.perf_counter()
            observations = self._keyframe_observations(idx[inlier], uv[inlier], self._H_point[inlier], self._residual_px[inlier])
            graph_s = time.perf_counter() - tg
        tm = time.perf_counter()
        self.history.append(event.t_s, self.T)
        live_uv = self._drop_points()
        map_s = time.perf_counter() - tm
        if is_keyframe:
            tg = time.perf_counter()
            new = self._new_points(event.image, event.t_s, live_uv)
            tn = time.perf_counter()
            self._send_keyframe(event.t_s, observations, new)
            graph_s += time.perf_counter() - tn
            map_s += tn - tg
        tg = time.perf_counter()
        timing["graph_worker"] = self._take_results(self._graph.results())
        graph_s += time.perf_counter() - tg
        if is_keyframe and isinstance(self._graph, InProcessGraph):
            for hook in self.keyframe_hooks:
                hook(self)
        timing["map"], timing["graph"] = map_s, graph_s
        timing["total"] = time.perf_counter() - t0
        k = len(self.keyframe_t_s) - 1
        self._frame_anchor.append((k, invert(self.T_kf) @ self.T))
        record = FrameRecord(event.t_s, self.T.copy(), self._output_covariance(), len(self.live), int(len(idx)), timing)
        self._frames.append(record)
        return record

    # --- prediction --------------------------------------------------------------------------
    def _predict(self, t_s: float) -> np.ndarray:
        dt, increment = self._motion.advance(t_s)
        # without odometry: constant velocity from the last two frames' poses
        U, Q = increment if increment is not None else constant_velocity_increment(self._v_body, dt, self._motion.sigma_acc)
        A = adjoint(invert(U))
        self.P_loc = A @ self.P_loc @ A.T + Q
        self.U_kf = self.U_kf @ U
        self.Q_kf = A @ self.Q_kf @ A.T + Q
        self._anchor_Q = A @ self._anchor_Q @ A.T + Q
        for k, Q_k in self._Q_since.items():
            self._Q_since[k] = A @ Q_k @ A.T + Q
        self._U_frame, self._Q_frame = U, Q
        self._dt = dt
        return self.T @ U

    # --- tracking ----------------------------------------------------------------------------
    def _track(self, image, t_s: float, T_pred: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Indices of the live points matched in this frame and their pixels (m,2)."""
        live = self.live
        if len(live) == 0:
            return np.zeros(0, dtype=int), np.zeros((0, 2))
        fe = self.frontend
        T_body_cam = self.rig.T_body_cam
        self._Sigma = live.covariances()  # this frame's, also for the pose update
        uv, S, in_front = self.search_regions(T_pred, self._Sigma)
        T_wc = T_pred @ T_body_cam
        warps = fe.template_warps(live.ids, live.X, T_wc)
        sel = np.flatnonzero(in_front)
        ids = live.ids[sel]
        templates = fe.templates(ids, None if warps is None else warps[sel])
        batch = fe.track_many(image, ids, templates, uv[sel], S_px2=S[sel], t_s=t_s, T_world_cam=T_wc)
        # an injected match must pass the point's chi-square gate
        return self._false_matches.screen_batch(sel, batch, uv, lambda i, y: y @ np.linalg.solve(S[i], y) <= self._gate)

    def search_regions(self, T_world_body: np.ndarray, Sigma: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Predicted pixels (n,2) of the live points from ``T_world_body``, their 2x2 innovation
        covariances (n,2,2) and the in-front mask: the pose covariance relative to the map
        (``P_loc``) and each point's own covariance, carried to the pixel, plus the pixel noise."""
        uv, Hp, Hx, in_front = project_with_jacobians(T_world_body, self.live.X, self.rig.camera_model, self.rig.T_body_cam)
        Sigma = self.live.covariances() if Sigma is None else Sigma
        S = Hp @ self.P_loc @ np.swapaxes(Hp, 1, 2) + Hx @ Sigma @ np.swapaxes(Hx, 1, 2) + self._sigma_px**2 * np.eye(2)
        return uv, S, in_front

    def _update_pose(self, T_pred: np.ndarray, idx: np.ndarray, uv: np.ndarray) -> np.ndarray:
        """The frame's pose from its matches; returns which matches are inliers after it."""
        live = self.live
        T_prev = self.T
        if len(idx) == 0:
            self.T = T_pred
            inlier = np.zeros(0, dtype=bool)
            self._H_point = np.zeros((0, 2, 3))
            self._residual_px = np.zeros((0, 2))
        else:
            Sigma = self._Sigma[idx]
            cam, T_body_cam = self.rig.camera_model, self.rig.T_body_cam
            self.T, self.P_loc = update_pose(T_pred, self.P_loc, live.X[idx], Sigma, uv, cam, T_body_cam, self._sigma_px, robust=self.config.robust)
            pred, _, Hx, _ = project_with_jacobians(self.T, live.X[idx], cam, T_body_cam)
            self._H_point = Hx  # d pixel / d point at the frame's pose, also for the keyframe's information
            R = self._sigma_px**2 * np.eye(2) + Hx @ Sigma @ np.swapaxes(Hx, 1, 2)
            r = uv - pred
            self._residual_px = r
            d2 = np.einsum("ni,nij,nj->n", r, np.linalg.inv(R), r)
            inlier = d2 <= self.config.outlier_chi2
            self.frontend.counters["outlier_rejected"] += int(np.sum(~inlier))
        if self._dt > 0:
            self._v_body = local(T_prev, self.T) / self._dt
            self._speed_mps = float(np.linalg.norm(self._v_body[3:]))
        return inlier

    def _split_refreshed(self, idx: np.ndarray) -> np.ndarray:
        """Points whose patch was refreshed in this frame now follow a new landmark (tied to the
        old one at the next keyframe); returns, per match, the old landmark or -1."""
        live, tracks = self.live, self.frontend.tracks
        old = np.full(len(idx), -1, dtype=np.int64)
        sigma2 = self.config.split_link_sigma_m**2
        for j, i in enumerate(idx):
            segment = tracks[int(live.ids[i])].segment
            if segment == live.segment[i]:
                continue
            old[j] = live.landmark[i]
            new = self._next_landmark
            self._next_landmark += 1
            Sigma_old = np.linalg.inv(live.info[i])
            self._pending_links.append((int(old[j]), new, Sigma_old))
            self.points[new] = self.points[int(old[j])].copy()  # its estimate until the graph has it
            live.landmark[i], live.segment[i] = new, segment
            live.info[i] = np.linalg.inv(Sigma_old + sigma2 * np.eye(3))
            live.n_since_keyframe[i] = 0
            self._landmark_of[int(live.ids[i])] = new
            if self.log is not None:
                self.log.add_link(int(old[j]), new, self.config.split_link_sigma_m)
        return old

    # --- keyframes ---------------------------------------------------------------------------
    def _keyframe_observations(self, idx: np.ndarray, uv: np.ndarray, H_point: np.ndarray, residual_px: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """This keyframe's inlier observations (live indices ``idx``, pixels ``uv``, pixel Jacobians
        ``H_point`` w.r.t. the points, residuals at the frame's pose) of landmarks still in the
        graph, as (landmarks, pixels, sigma_px). (A point whose landmark the graph has marginalised
        was archived when the front end heard of it; the graph skips any it hears of first.)

        Each also updates its point at once, the pose held fixed (one Gauss-Newton step of the
        point's information form), so that a point's estimate and covariance stay together until
        the graph's smoothed estimate replaces them: in the same frame by default, keyframes later
        with the graph in a second process. (Holding the information back until then instead
        kept new points' search regions at their seed's size: 14 % of tracks refused as too large
        to search, 150 frames of `demo`.)"""
        live = self.live
        n = np.maximum(live.n_since_keyframe[idx], 1) if self.config.keyframe_weighting else np.ones(len(idx), dtype=np.int64)
        sigma = self._sigma_px / np.sqrt(effective_sample_size(n, self.config.track_correlation))
        live.n_since_keyframe[idx] = 0
        Ht = np.swapaxes(H_point, 1, 2) / (sigma**2)[:, None, None]
        live.info[idx] += Ht @ H_point
        live.X[idx] += np.linalg.solve(live.info[idx], np.einsum("nij,nj->ni", Ht, residual_px)[..., None])[..., 0]
        return live.landmark[idx].copy(), uv.copy(), sigma

    def _new_points(self, image, t_s: float, live_uv: np.ndarray) -> list[NewPoint]:
        return self.frontend.new_points(image, t_s, self.T, self._scans.take_until(t_s), self.history, self.live.X, live_uv, self._speed_mps)

    def _send_keyframe(self, t_s: float, observations: tuple[np.ndarray, np.ndarray, np.ndarray], new: list[NewPoint]) -> None:
        """The keyframe's message to the graph: its pose, the motion since the last one, its
        observations, the new points with their seeds and the refreshed patches' links."""
        c = self.config
        k = len(self.keyframe_t_s) - 1
        if t_s > self.keyframe_t_s[-1]:  # else: the first frame, at the start pose's time
            k += 1
            self.keyframe_t_s.append(t_s)
        new_landmarks = []
        if new:
            R = self.T[:3, :3]
            ids = np.array([p.point_id for p in new])
            X_world = transform_points(self.T, np.array([p.p_body for p in new]))
            Sigma_world = R @ np.array([p.Sigma_body for p in new]) @ R.T
            landmarks = np.arange(self._next_landmark, self._next_landmark + len(new))
            self._next_landmark += len(new)
            for p, lm, Xw in zip(new, landmarks, X_world):
                new_landmarks.append(NewLandmark(int(lm), Xw, p.kind, np.asarray(p.p_body, dtype=float), np.asarray(p.Sigma_body, dtype=float)))
                self._landmark_of[p.point_id] = int(lm)
                self.points[int(lm)] = Xw
            self.live.add(ids, landmarks, X_world, Sigma_world)
            if self.log is not None:
                self.log.add_seeds(len(self._frames), new, landmarks)
        links, self._pending_links = self._pending_links, []
        for lm in [p.landmark for p in new_landmarks] + [new_lm for _, new_lm, _ in links]:
            self._landmark_keyframe[lm] = k
        every = c.pose_covariance_every_s
        want_marginal = every > 0 and not self._marginal_asked and t_s - self._anchor_t_s >= every
        self._marginal_asked |= want_marginal
        self._graph.send(KeyframeMessage(k, t_s, self.T.copy(), self.U_kf, self.Q_kf, *observations, links, new_landmarks, want_marginal))
        self._sent_T[k] = self.T.copy()
        self._Q_since[k] = np.zeros((6, 6))
        self.poses.setdefault(k, self.T.copy())  # until the graph's estimate is back
        self.T_kf = self.T.copy()
        self.U_kf, self.Q_kf = np.eye(4), np.zeros((6, 6))
        self.frames_since_kf = 0
        if every <= 0:
            self._anchor_T, self._anchor_P, self._anchor_Q = self.T.copy(), self.P_loc.copy(), np.zeros((6, 6))

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
                        self._restart_graph()
                    else:
                        log.warning("%s (at the end of the run: the estimates before it are kept)", r.failure)
                    continue
                self._apply_result(r)
            results = self._graph.results()  # a restart's answer, in-process at once
        return worker_s

    def _apply_result(self, r: GraphResult) -> None:
        """The graph's smoothed keyframe ``r.k`` moves the current pose and the keyframes sent since
        with it (a world-frame correction); the live points take the graph's estimates, and those it
        has marginalised are archived."""
        k = r.k
        self.poses.update(r.poses)
        self.points.update(r.points)
        self._graph_lag.append(len(self.keyframe_t_s) - 1 - k)
        C = np.eye(4)
        if k in self._sent_T:
            # kept on SE(3): corrections compose, and invert() assumes orthonormal rotations
            correction = r.poses[k] @ invert(self._sent_T[k])
            C = nearest_pose(correction)
            self.T = nearest_pose(correction @ self.T)  # the smoothed keyframe and the motion since
            self.T_kf = C @ self.T_kf
            self.history.correct(C)
            self._sent_T = {j: C @ T for j, T in self._sent_T.items() if j > k}
        if r.marginal is not None:
            self._anchor_T, self._anchor_P, self._anchor_Q = r.poses[k].copy(), r.marginal, self._Q_since[k].copy()
            self._anchor_t_s = self.keyframe_t_s[k]
            self._marginal_asked = False
        self._Q_since = {j: Q for j, Q in self._Q_since.items() if j > k}
        live = self.live
        keep = np.ones(len(live), dtype=bool)
        for i, lm in enumerate(live.landmark):
            lm = int(lm)
            X_lm = r.points.get(lm)
            if X_lm is not None:
                live.X[i] = X_lm
            elif self._landmark_keyframe.get(lm, -1) > k:  # started after keyframe k: placed from a pose the correction has moved
                live.X[i] = transform_points(C, live.X[i][None])[0]
                self.points[lm] = live.X[i].copy()
            else:
                keep[i] = False
                self._archive(i, "marginalized")
        live.keep(keep)

    def _restart_graph(self) -> None:
        """A new smoother at the newest keyframe, from the front end's estimates."""
        self.frontend.counters["graph_restarts"] += 1
        live = self.live
        k = len(self.keyframe_t_s) - 1
        priors = {int(lm): (live.X[i].copy(), self._point_covariance_world(i)) for i, lm in enumerate(live.landmark)}
        for lm in priors:
            self._landmark_keyframe[lm] = k
        self._pending_links = []
        self._marginal_asked = False
        self._sent_T = {k: self.T_kf.copy()}
        self._graph.send(RestartMessage(k, self.T_kf.copy(), self._output_covariance(), priors))

    def _output_covariance(self) -> np.ndarray:
        """The current pose's covariance: the anchor keyframe's marginal carried to it, plus the
        motion covariance since (6x6, right perturbation)."""
        A = adjoint(invert(invert(self._anchor_T) @ self.T))
        P = A @ self._anchor_P @ A.T + self._anchor_Q
        return 0.5 * (P + P.T)

    # --- map management ----------------------------------------------------------------------
    def _point_covariance_world(self, i: int) -> np.ndarray:
        """Point ``i``'s covariance: its own (relative to the keyframes) plus the last keyframe
        pose's marginal carried to it (first order)."""
        live = self.live
        p_body = transform_points(invert(self._anchor_T), live.X[i][None])[0]
        R = self._anchor_T[:3, :3]
        J = np.concatenate([-R @ skew(p_body), R], axis=1)
        return np.linalg.inv(live.info[i]) + J @ self._anchor_P @ J.T

    def _archive(self, i: int, reason: str) -> None:
        self._archived.archive(int(self.live.ids[i]), reason, self._point_covariance_world(i))

    def _drop_points(self) -> np.ndarray:
        keep, uv = self._archived.drop_points(self.live.ids, self.live.X, self.T, lambda i: (self._point_covariance_world(i), None))
        self.live.keep(keep)
        return uv

    # --- results -----------------------------------------------------------------------------
    def smoothed_poses(self) -> np.ndarray:
        """Every frame's pose from the latest keyframe estimates (each frame rides on the keyframe before it)."""
        poses = self.poses
        return np.array([poses[k] @ T_rel for k, T_rel in self._frame_anchor]).reshape(-1, 4, 4)

    def result(self) -> EstimatorResult:
        pts, live = self.points, self.live
        res = self._archived.result(
            self.name, self._frames, live.ids, lambda i: live.X[i], self._point_covariance_world, archived_xyz=lambda pid: pts[self._landmark_of[pid]]
        )
        res.counters["keyframes"] = len(self.keyframe_t_s)
        if self._graph_lag:
            res.counters["graph_lag_keyframes_median"] = int(np.median(self._graph_lag))
            res.counters["graph_lag_keyframes_max"] = int(np.max(self._graph_lag))
        if self.batch_result is not None:
            return self.batch_result.apply_to(res, self._landmark_of)
        if self._frames:
            res.extra_poses["trajectory_smoothed"] = self.smoothed_poses()
        return res


__all__ = ["Isam2Config", "Isam2Options", "Isam2Slam", "LivePoints"]
