"""The graph estimator's online filter: each frame's pose from the live points, between (and
without waiting for) the graph's smoothed estimates.

Per frame (docs/isam2_design.md): the pose is predicted and its covariance relative to the map
(``P_loc``) carried by the motion; every live point is searched in the region of its 2x2 innovation
covariance (that pose covariance and the point's own, carried to the pixel, plus the pixel noise);
the pose is updated against the matches (:func:`~dem_graph.estimators.pose_update.update_pose`:
points fixed, their covariance as pixel noise, Huber weights), and matches whose normalised
residual exceeds ``outlier_chi2`` are outliers. At a keyframe the inliers also update their points
(:meth:`OnlineFilter.keyframe_observations`). The filter knows nothing of the graph: the graph
client moves its pose and points when the smoother's results come back.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dem_graph.estimators.false_matches import FalseMatches
from dem_graph.estimators.isam2_config import Isam2Config
from dem_graph.estimators.live_points import LivePoints
from dem_graph.estimators.pose_update import project_with_jacobians, update_pose
from dem_graph.estimators.projection_kernel import compile_kernel as compile_pose_kernel
from dem_graph.frontend.frontend import FrontEnd, NewPoint
from dem_graph.frontend.pose_history import PoseHistory
from dem_graph.geometry.lie import adjoint, local
from dem_graph.geometry.rig import SensorRig
from dem_graph.geometry.se3 import invert, nearest_pose


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


@dataclass
class FrameMatches:
    """One frame's matches: live indices ``idx`` (m,) and pixels ``uv`` (m,2), with the live points'
    covariances ``Sigma`` as searched (None without live points); after the pose update, which
    matches are inliers, the pixel Jacobians w.r.t. the points (m,2,3) and the residuals (m,2) at the
    frame's pose."""

    idx: np.ndarray
    uv: np.ndarray
    Sigma: np.ndarray | None = None
    inlier: np.ndarray | None = None
    H_point: np.ndarray | None = None
    residual_px: np.ndarray | None = None

    def for_points(self, kept: np.ndarray) -> FrameMatches:
        """These matches (before the pose update) after the live points were cut to ``kept``, a mask
        over the live points as searched: the matches of points that left dropped, the rest renumbered."""
        new_index = np.cumsum(kept) - 1
        stay = kept[self.idx]
        return FrameMatches(new_index[self.idx[stay]], self.uv[stay], None if self.Sigma is None else self.Sigma[kept])


class OnlineFilter:
    """The current pose ``T`` (``T_world_body``) with its covariance relative to the map ``P_loc``,
    the live points, the recent poses (for the laser's Eq. 2) and the body velocity; feed it one
    frame at a time: :meth:`predict`, :meth:`track`, :meth:`update_pose`."""

    def __init__(self, config: Isam2Config, rig: SensorRig, frontend: FrontEnd, T_world_body: np.ndarray, P0: np.ndarray, t_s: float):
        self.config = config
        self.rig = rig
        self.frontend = frontend
        self._sigma_px = config.frontend.sigma_px
        self._gate = frontend.tracker.gate_chi2
        self.T = T_world_body
        self.P_loc = P0.copy()  # pose covariance relative to the map (search regions)
        self._P0 = P0.copy()
        self.live = LivePoints()
        self.history = PoseHistory(window=config.keyframe_spacing + 5)
        self.history.append(t_s, self.T)
        self.v_body = np.zeros(6)  # from the last two frames' poses: [angular, linear] per second
        self.v_body[3] = config.motion.initial_speed_mps
        self._speed_mps: float | None = None
        self._false_matches = FalseMatches(config.false_matches, frontend.counters)
        compile_pose_kernel()  # before the first frame, not in it

    # --- one frame ---------------------------------------------------------------------------
    def predict(self, U: np.ndarray, Q: np.ndarray, A: np.ndarray | None = None) -> np.ndarray:
        """Carry the pose covariance over the motion ``U`` since the last frame (covariance ``Q``;
        ``A``: ``adjoint(invert(U))`` when the caller has it); returns the predicted pose."""
        A = adjoint(invert(U)) if A is None else A
        self.P_loc = A @ self.P_loc @ A.T + Q
        return self.T @ U

    def restart_map(self) -> None:
        """Every live point is gone (a camera gap made them stale): the points seeded next are placed
        from this pose, so its covariance relative to the map restarts at the initial one. (Carried on
        instead, the gap's growth would size every later search region as if against the lost map,
        and keep it too large to search.)"""
        self.P_loc = self._P0.copy()

    def track(self, image, t_s: float, T_pred: np.ndarray) -> FrameMatches:
        """The live points matched in this frame, each searched in its region from ``T_pred``."""
        live = self.live
        if len(live) == 0:
            return FrameMatches(np.zeros(0, dtype=int), np.zeros((0, 2)))
        fe = self.frontend
        T_body_cam = self.rig.T_body_cam
        Sigma = live.covariances()  # this frame's, also for the pose update
        uv, S, in_front = self.search_regions(T_pred, Sigma)
        T_wc = T_pred @ T_body_cam
        warps = fe.template_warps(live.ids, live.X, T_wc)
        sel = np.flatnonzero(in_front)
        ids = live.ids[sel]
        templates = fe.templates(ids, None if warps is None else warps[sel])
        batch = fe.track_many(image, ids, templates, uv[sel], S_px2=S[sel], t_s=t_s, T_world_cam=T_wc)
        # an injected match must pass the point's chi-square gate
        idx, uv_found = self._false_matches.screen_batch(sel, batch, uv, lambda i, y: y @ np.linalg.solve(S[i], y) <= self._gate)
        return FrameMatches(idx, uv_found, Sigma)

    def search_regions(self, T_world_body: np.ndarray, Sigma: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Predicted pixels (n,2) of the live points from ``T_world_body``, their 2x2 innovation
        covariances (n,2,2) and the in-front mask: the pose covariance relative to the map
        (``P_loc``) and each point's own covariance, carried to the pixel, plus the pixel noise."""
        uv, Hp, Hx, in_front = project_with_jacobians(T_world_body, self.live.X, self.rig.camera_model, self.rig.T_body_cam)
        Sigma = self.live.covariances() if Sigma is None else Sigma
        S = Hp @ self.P_loc @ np.swapaxes(Hp, 1, 2) + Hx @ Sigma @ np.swapaxes(Hx, 1, 2) + self._sigma_px**2 * np.eye(2)
        return uv, S, in_front

    def update_pose(self, T_pred: np.ndarray, m: FrameMatches, dt_s: float) -> None:
        """The frame's pose from its matches ``m`` (``dt_s`` after the last frame's); sets which
        matches are inliers after it, with their Jacobians and residuals."""
        live = self.live
        idx, uv = m.idx, m.uv
        T_prev = self.T
        if len(idx) == 0:
            self.T = T_pred
            m.inlier = np.zeros(0, dtype=bool)
            m.H_point = np.zeros((0, 2, 3))
            m.residual_px = np.zeros((0, 2))
        else:
            Sigma = m.Sigma[idx]
            cam, T_body_cam = self.rig.camera_model, self.rig.T_body_cam
            self.T, self.P_loc = update_pose(T_pred, self.P_loc, live.X[idx], Sigma, uv, cam, T_body_cam, self._sigma_px, robust=self.config.robust)
            pred, _, Hx, _ = project_with_jacobians(self.T, live.X[idx], cam, T_body_cam)
            m.H_point = Hx  # d pixel / d point at the frame's pose, also for the keyframe's information
            R = self._sigma_px**2 * np.eye(2) + Hx @ Sigma @ np.swapaxes(Hx, 1, 2)
            r = uv - pred
            m.residual_px = r
            d2 = np.einsum("ni,nij,nj->n", r, np.linalg.inv(R), r)
            m.inlier = d2 <= self.config.outlier_chi2
            self.frontend.counters["outlier_rejected"] += int(np.sum(~m.inlier))
        if dt_s > 0:
            self.v_body = local(T_prev, self.T) / dt_s
            self._speed_mps = float(np.linalg.norm(self.v_body[3:]))

    def keyframe_observations(self, m: FrameMatches, k: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Keyframe ``k``'s inlier observations of landmarks still in the graph, as (landmarks,
        pixels, sigma_px), and the step (m,3, metres) each gave its point. (A point whose landmark
        the graph has marginalised was archived when the front end heard of it; the graph skips any
        it hears of first.) With ``isam2.observation_every`` n > 1, a landmark's observation goes at
        every n-th keyframe only (landmark + k divisible by n, so that the landmarks take turns); it
        then carries the frames since its last one (``sigma_px / sqrt(frames)``).

        Each also updates its point at once, the pose held fixed (one Gauss-Newton step of the
        point's information form), so that a point's estimate and covariance stay together until
        the graph's smoothed estimate replaces them: in the same frame by default, keyframes later
        with the graph in a second process. (Held back until then, new points would keep their
        seed's search regions, too large to search.)"""
        live = self.live
        every = self.config.observation_spacing
        inlier = m.inlier if every == 1 else m.inlier & ((live.landmark[m.idx] + k) % every == 0)
        idx, uv, H_point, residual_px = m.idx[inlier], m.uv[inlier], m.H_point[inlier], m.residual_px[inlier]
        n = np.maximum(live.n_since_keyframe[idx], 1) if self.config.keyframe_weighting else np.ones(len(idx), dtype=np.int64)
        sigma = self._sigma_px / np.sqrt(effective_sample_size(n, self.config.track_correlation))
        live.n_since_keyframe[idx] = 0
        Ht = np.swapaxes(H_point, 1, 2) / (sigma**2)[:, None, None]
        live.info[idx] += Ht @ H_point
        dX = np.linalg.solve(live.info[idx], np.einsum("nij,nj->ni", Ht, residual_px)[..., None])[..., 0]
        live.X[idx] += dX
        return live.landmark[idx].copy(), uv.copy(), sigma, dX

    def end_frame(self, t_s: float) -> None:
        """The frame's pose joins the recent poses (the spline that places the next scans)."""
        self.history.append(t_s, self.T)

    def new_points(self, image, t_s: float, scans: list, live_uv: np.ndarray, speed_mps: float | None = None) -> list[NewPoint]:
        """The front end's new points (laser ``scans`` and flat-ground seeds) away from the live points'
        pixels ``live_uv``, for the speed ``speed_mps`` (default: the filter's; ``math.inf``: the
        speed about to be measured, :meth:`Isam2Slam._speed_unknown_at_start`)."""
        speed = self._speed_mps if speed_mps is None else speed_mps
        return self.frontend.new_points(image, t_s, self.T, scans, self.history, self.live.X, live_uv, speed)

    # --- the graph's results -----------------------------------------------------------------
    def correct(self, correction: np.ndarray, C: np.ndarray) -> None:
        """Move the pose by the graph's world-frame ``correction`` (kept on SE(3)) and the recent poses by ``C``, its nearest pose."""
        self.T = nearest_pose(correction @ self.T)  # the smoothed keyframe and the motion since
        self.history.correct(C)


__all__ = ["FrameMatches", "OnlineFilter", "effective_sample_size"]
