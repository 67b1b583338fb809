"""The EKF of the paper (III-B): one pose, its velocity and the live map points in one state.

State: ``T_world_body`` (error as a right perturbation [rotation, translation]), the body twist
``v_body`` ([angular rad/s, linear m/s], used by the constant-velocity model) and ``n`` world
points. Covariance ``P`` has the layout ``[pose 0:6, velocity 6:12, point i at 12+3i]``.

Updates come in two forms, as in the paper: a batch update with every match of an image (GM) and
sequential one-point updates (PTPM). Sequential updates keep the covariance as ``P0 - L L^T`` and
only materialise the rows they need, so a frame of ``n_t`` point updates costs about one batch
update plus ``n_t`` small products instead of ``n_t`` full ``N x N`` rewrites: the result is
the exact sequential EKF.
"""

from __future__ import annotations

import numpy as np

from dem_graph.geometry.camera import PinholeCamera
from dem_graph.geometry.lie import adjoint, local, retract, skew
from dem_graph.geometry.se3 import invert

POSE = slice(0, 6)
VEL = slice(6, 12)
N_BASE = 12


def point_cols(i: int) -> slice:
    return slice(N_BASE + 3 * i, N_BASE + 3 * i + 3)


class EkfState:
    def __init__(self, T_world_body: np.ndarray, P_pose: np.ndarray, v_body: np.ndarray, P_vel: np.ndarray):
        self.T_world_body = np.array(T_world_body, dtype=float)
        self.v_body = np.array(v_body, dtype=float)
        self.points_xyz = np.zeros((0, 3))
        self.point_ids = np.zeros(0, dtype=np.int64)
        self.P = np.zeros((N_BASE, N_BASE))
        self.P[POSE, POSE] = P_pose
        self.P[VEL, VEL] = P_vel
        self._L: np.ndarray | None = None  # pending low-rank downdate of P (sequential mode)
        self._L_cols = 0

    # --- bookkeeping -----------------------------------------------------------------------
    @property
    def n_points(self) -> int:
        return len(self.point_ids)

    @property
    def dim(self) -> int:
        return N_BASE + 3 * self.n_points

    def point_covariance(self, i: int) -> np.ndarray:
        c = point_cols(i)
        return self.P[c, c].copy()

    def pose_covariance(self) -> np.ndarray:
        return self.P[POSE, POSE].copy()

    # --- prediction ----------------------------------------------------------------------------
    def predict_increment(self, U: np.ndarray, Q_U: np.ndarray, dt_s: float) -> None:
        """Odometry: ``T <- T U`` with ``Q_U`` the increment's covariance ([rot, trans], right perturbation).
        The velocity is set to the increment's mean twist, with the increment's uncertainty."""
        self._require_batch_mode()
        A = adjoint(invert(U))
        P = self.P
        P[POSE, :] = A @ P[POSE, :]
        P[:, POSE] = P[:, POSE] @ A.T
        P[POSE, POSE] += Q_U
        self.T_world_body = self.T_world_body @ U
        if dt_s > 0:
            self.v_body = local(np.eye(4), U) / dt_s
            P[VEL, :] = 0.0
            P[:, VEL] = 0.0
            P[VEL, VEL] = Q_U / dt_s**2 + np.eye(6) * 1e-6

    def predict_constant_velocity(self, dt_s: float, sigma_acc: np.ndarray) -> None:
        """Constant-velocity model: ``T <- T Exp(v dt)``, ``v <- v + w`` with white acceleration
        ``sigma_acc`` (6,: [angular rad/s^2, linear m/s^2] per sqrt(Hz))."""
        self._require_batch_mode()
        E = retract(np.eye(4), self.v_body * dt_s)
        A = adjoint(invert(E))
        F = np.eye(N_BASE)
        F[POSE, POSE] = A
        F[POSE, VEL] = np.eye(6) * dt_s
        P = self.P
        P[:N_BASE, :] = F @ P[:N_BASE, :]
        P[:, :N_BASE] = P[:, :N_BASE] @ F.T
        q = np.diag(np.asarray(sigma_acc, dtype=float) ** 2) * dt_s
        P[POSE, POSE] += q * dt_s**2 / 3.0
        P[POSE, VEL] += q * dt_s / 2.0
        P[VEL, POSE] += q * dt_s / 2.0
        P[VEL, VEL] += q
        self.T_world_body = self.T_world_body @ E

    # --- observation -------------------------------------------------------------------------
    def observe(self, indices: np.ndarray, camera: PinholeCamera, T_body_cam: np.ndarray):
        """Predicted pixels of points ``indices`` and the Jacobians w.r.t. the pose (k,2,6) and the point (k,2,3).
        Also returns the in-front mask and the camera-frame depths."""
        R_wb, t_wb = self.T_world_body[:3, :3], self.T_world_body[:3, 3]
        T_cam_body = invert(T_body_cam)
        R_cb = T_cam_body[:3, :3]
        p_body = (self.points_xyz[indices] - t_wb) @ R_wb  # R_wb^T (x - t)
        p_cam = p_body @ R_cb.T + T_cam_body[:3, 3]
        uv, J_uv_pc, in_front = camera.project_with_jacobian(p_cam)
        J_uv_pb = J_uv_pc @ R_cb
        # right perturbation of the pose: d p_body / d [dtheta, dt] = [skew(p_body), -I]
        J_pb_pose = np.concatenate([skew(p_body), -np.broadcast_to(np.eye(3), (len(p_body), 3, 3))], axis=2)
        H_pose = J_uv_pb @ J_pb_pose
        H_point = J_uv_pb @ R_wb.T
        return uv, H_pose, H_point, in_front, p_cam[:, 2]

    def innovation_covariances(self, H_pose: np.ndarray, H_point: np.ndarray, R_px2: float) -> np.ndarray:
        """(n,2,2) innovation covariances of every point, from the Jacobians of :meth:`observe` (all points)."""
        n = self.n_points
        P = self.P
        P_pp = P[POSE, POSE]
        P_pi = P[POSE, N_BASE:].reshape(6, n, 3).transpose(1, 0, 2)
        idx = N_BASE + 3 * np.arange(n)[:, None] + np.arange(3)[None, :]
        P_ii = P[idx[:, :, None], idx[:, None, :]]
        HpP = H_pose @ P_pp
        cross = H_pose @ P_pi @ np.swapaxes(H_point, 1, 2)
        S = HpP @ np.swapaxes(H_pose, 1, 2) + cross + np.swapaxes(cross, 1, 2) + H_point @ P_ii @ np.swapaxes(H_point, 1, 2)
        return S + R_px2 * np.eye(2)

    # --- batch update (GM) -------------------------------------------------------------------
    def batch_update(self, indices: np.ndarray, innovations: np.ndarray, H_pose: np.ndarray, H_point: np.ndarray, R_px2: float) -> None:
        """One EKF update with every match: a (2k x 2k) innovation covariance."""
        self._require_batch_mode()
        k = len(indices)
        if k == 0:
            return
        N = self.dim
        H = np.zeros((2 * k, N))
        for j, i in enumerate(indices):
            H[2 * j : 2 * j + 2, POSE] = H_pose[j]
            H[2 * j : 2 * j + 2, point_cols(int(i))] = H_point[j]
        PHt = self.P @ H.T
        S = H @ PHt + R_px2 * np.eye(2 * k)
        K = np.linalg.solve(S, PHt.T).T
        self._apply_correction(K @ innovations.reshape(-1))
        self.P -= K @ PHt.T
        self._symmetrize()

    # --- sequential update (PTPM) ------------------------------------------------------------
    # The covariance stays P0 - L L^T and the mean correction accumulates in dx until
    # end_sequential(); every point is linearised once, at the predicted state (as GM), and its
    # prediction follows the corrections made so far to first order.
    def begin_sequential(self, max_updates: int) -> None:
        self._L = np.zeros((self.dim, 2 * max(max_updates, 1)))
        self._L_cols = 0
        self._dx = np.zeros(self.dim)

    def correction(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """Accumulated (pose, point i) corrections of the current sequential session."""
        return self._dx[POSE], self._dx[point_cols(i)]

    def sequential_innovation_covariance(self, i: int, H_pose: np.ndarray, H_point: np.ndarray, R_px2: float) -> np.ndarray:
        c = point_cols(i)
        P = self.P
        HpPpc = H_pose @ P[POSE, c]
        S = H_pose @ P[POSE, POSE] @ H_pose.T + HpPpc @ H_point.T + (HpPpc @ H_point.T).T + H_point @ P[c, c] @ H_point.T
        S[0, 0] += R_px2
        S[1, 1] += R_px2
        if self._L_cols:
            k = self._L_cols
            HL = H_pose @ self._L[POSE, :k] + H_point @ self._L[c, :k]
            S -= HL @ HL.T
        return S

    def sequential_update(self, i: int, innovation: np.ndarray, H_pose: np.ndarray, H_point: np.ndarray, S: np.ndarray) -> None:
        """One point's update; ``S`` from :meth:`sequential_innovation_covariance` for the same point."""
        c = point_cols(i)
        PHt = self.P[:, POSE] @ H_pose.T + self.P[:, c] @ H_point.T  # (N,2)
        k = self._L_cols
        if k:
            L = self._L[:, :k]
            PHt -= L @ (H_pose @ L[POSE] + H_point @ L[c]).T
        S_inv = _inv2(S)
        self._dx += PHt @ (S_inv @ innovation)
        if k + 2 > self._L.shape[1]:
            self._L = np.concatenate([self._L, np.zeros_like(self._L)], axis=1)
        self._L[:, k : k + 2] = PHt @ _chol2(S_inv)
        self._L_cols = k + 2

    def end_sequential(self) -> None:
        if self._L is not None and self._L_cols:
            L = self._L[:, : self._L_cols]
            self.P -= L @ L.T
            self._symmetrize()
            self._apply_correction(self._dx)
        self._L = None
        self._L_cols = 0

    # --- state changes -----------------------------------------------------------------------
    def _apply_correction(self, dx: np.ndarray) -> None:
        self.T_world_body = retract(self.T_world_body, dx[POSE])
        self.v_body = self.v_body + dx[VEL]
        if self.n_points:
            self.points_xyz = self.points_xyz + dx[N_BASE:].reshape(-1, 3)

    def add_points(self, point_ids: np.ndarray, p_body: np.ndarray, Sigma_body: np.ndarray) -> None:
        """Append points measured in the current body frame (``p_body`` (k,3)) with covariance
        ``Sigma_body`` (k,3,3); their world covariance and correlation follow from the pose's."""
        self._require_batch_mode()
        k = len(point_ids)
        if k == 0:
            return
        R, t = self.T_world_body[:3, :3], self.T_world_body[:3, 3]
        X = p_body @ R.T + t
        # d X / d pose (right perturbation) = R [-skew(p_body), I]
        J = np.einsum("ij,kjl->kil", R, np.concatenate([-skew(p_body), np.broadcast_to(np.eye(3), (k, 3, 3))], axis=2))
        N = self.dim
        P_new = np.zeros((N + 3 * k, N + 3 * k))
        P_new[:N, :N] = self.P
        P_pose_all = self.P[POSE, :]  # (6, N)
        cross = np.einsum("kij,jn->kin", J, P_pose_all).reshape(3 * k, N)
        P_new[N:, :N] = cross
        P_new[:N, N:] = cross.T
        P_pp = self.P[POSE, POSE]
        JPJ = np.einsum("kij,jl,kml->kim", J, P_pp, J)
        # correlations between the new points through the shared pose
        Jflat = J.reshape(3 * k, 6)
        P_new[N:, N:] = Jflat @ P_pp @ Jflat.T
        for j in range(k):
            s = slice(N + 3 * j, N + 3 * j + 3)
            P_new[s, s] = JPJ[j] + R @ Sigma_body[j] @ R.T
        self.P = P_new
        self.points_xyz = np.concatenate([self.points_xyz, X])
        self.point_ids = np.concatenate([self.point_ids, np.asarray(point_ids, dtype=np.int64)])

    def remove_points(self, remove_mask: np.ndarray) -> None:
        self._require_batch_mode()
        if not np.any(remove_mask):
            return
        keep_pts = ~np.asarray(remove_mask, dtype=bool)
        keep = np.concatenate([np.ones(N_BASE, dtype=bool), np.repeat(keep_pts, 3)])
        self.P = self.P[np.ix_(keep, keep)]
        self.points_xyz = self.points_xyz[keep_pts]
        self.point_ids = self.point_ids[keep_pts]

    def _symmetrize(self) -> None:
        self.P = 0.5 * (self.P + self.P.T)

    def _require_batch_mode(self) -> None:
        if self._L is not None:
            raise RuntimeError("finish the sequential updates (end_sequential) first")


def _inv2(S: np.ndarray) -> np.ndarray:
    a, b, c, d = S[0, 0], S[0, 1], S[1, 0], S[1, 1]
    det = a * d - b * c
    return np.array([[d, -b], [-c, a]]) / det


def _chol2(A: np.ndarray) -> np.ndarray:
    """Lower Cholesky factor of a symmetric positive definite 2x2 matrix."""
    l11 = np.sqrt(A[0, 0])
    l21 = 0.5 * (A[1, 0] + A[0, 1]) / l11
    return np.array([[l11, 0.0], [l21, np.sqrt(A[1, 1] - l21 * l21)]])
