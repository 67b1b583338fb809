"""The EKF of the paper (III-B): one pose, its velocity and the live map points in one state.

State: ``T_world_body``, the body twist ``v_body`` ([angular rad/s, linear m/s], used by the
constant-velocity model), with an IMU its gyroscope's and accelerometer's biases (IMU frame), and
``n`` world points. Covariance ``P`` has the layout ``[pose 0:6, velocity 6:12, point i at
12+3i]``, or with an IMU ``[pose, velocity, gyroscope bias 12:15, accelerometer bias 15:18, point i
at 18+3i]`` (``n_base``).

With an IMU the gyroscope's rotation over a frame replaces the prediction's rotation; a bias error
``db`` turns the body by ``-R_body_imu db dt``, which the prediction carries into every error
coordinate (:meth:`EkfState.propagate_imu_biases`). The accelerometer's mean over the frame is a
measurement of gravity's direction in the body frame, that is of roll and pitch, shared with its
bias (:meth:`EkfState.gravity_update`).

Error coordinates (why the filter stays consistent)
---------------------------------------------------
Pose and points share one world-frame ("right-invariant") error, as in the invariant EKF for SLAM
(Barrau and Bonnabel, 2015): with ``e = [omega, nu, dv, xi_1 .. xi_n]``,

    R = Exp(omega) R_hat,   t = Exp(omega) t_hat + nu,   X_i = Exp(omega) X_hat_i + xi_i,   v = v_hat + dv.

A change of the world frame (which no sensor here observes) is then the constant direction
``omega = w, nu = xi_i = u`` whatever the estimate, so the linearised filter cannot gain
information along it. With the usual body-frame pose error and independent point errors, that
direction moves with the estimate and the filter grows overconfident on long runs
(docs/isam2_design.md). The cost is that a rotation noise couples into every point: the
prediction is a rank-6 update of the full covariance.

:meth:`EkfState.pose_covariance` and :meth:`EkfState.point_covariance` convert to the package's
conventions (right perturbation of the pose, world-frame point covariance); the constructor takes
the initial pose covariance in the right-perturbation convention.

Updates come in two forms, as in the paper: a batch update with every match of an image (GM) and
sequential one-point updates (PTPM). Sequential updates keep the covariance as ``P0 - L L^T`` and
only materialise the rows they need, so a frame of ``n_t`` point updates costs about one batch
update plus ``n_t`` small products instead of ``n_t`` full ``N x N`` rewrites: the result is
the exact sequential EKF.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from dem_graph.geometry.camera import PinholeCamera
from dem_graph.geometry.lie import adjoint, local, retract, skew, so3_exp
from dem_graph.geometry.se3 import invert

POSE = slice(0, 6)
ROT = slice(0, 3)
POS = slice(3, 6)
VEL = slice(6, 12)
VEL_LIN = slice(9, 12)
N_BASE = 12
GYRO_BIAS = slice(12, 15)  # with an IMU only: the gyroscope's bias (IMU frame, rad/s), before the points
ACCEL_BIAS = slice(15, 18)  # with an IMU only: the accelerometer's bias (IMU frame, m/s^2)
RECENTER_M = 1.0  # the rotation error is centred within this distance of the vehicle, metres


def point_cols(i: int, n_base: int = N_BASE) -> slice:
    """Point ``i``'s columns in a state whose points start at ``n_base``."""
    return slice(n_base + 3 * i, n_base + 3 * i + 3)


class EkfState:
    def __init__(self, T_world_body: np.ndarray, P_pose: np.ndarray, v_body: np.ndarray, P_vel: np.ndarray, imu_bias_sigmas: tuple[float, float] | None = None):
        """``P_pose``: covariance of the right perturbation of ``T_world_body`` ([rot, trans]).
        ``imu_bias_sigmas``: with an IMU, the gyroscope's and the accelerometer's biases join the
        state (zero, these spreads per axis: rad/s and m/s^2)."""
        self.T_world_body = np.array(T_world_body, dtype=float)
        self.v_body = np.array(v_body, dtype=float)
        self.points_xyz = np.zeros((0, 3))
        self.point_ids = np.zeros(0, dtype=np.int64)
        self.origin = self.T_world_body[:3, 3].copy()  # centre of the rotation error, see recenter()
        self.has_imu_biases = imu_bias_sigmas is not None
        self.n_base = N_BASE + 6 if self.has_imu_biases else N_BASE  # where the points start
        self.gyro_bias_rad_s = np.zeros(3)  # IMU frame; both stay zero without an IMU
        self.accel_bias_mps2 = np.zeros(3)
        self.P = np.zeros((self.n_base, self.n_base))
        A = adjoint(self._T_about_origin())
        self.P[POSE, POSE] = A @ np.asarray(P_pose, dtype=float) @ A.T
        self.P[VEL, VEL] = P_vel
        if self.has_imu_biases:
            self.P[GYRO_BIAS, GYRO_BIAS] = np.eye(3) * float(imu_bias_sigmas[0]) ** 2
            self.P[ACCEL_BIAS, ACCEL_BIAS] = np.eye(3) * float(imu_bias_sigmas[1]) ** 2
        self._L: np.ndarray | None = None  # pending low-rank downdate of P (sequential mode)
        self._L_rows = 0

    # --- bookkeeping -----------------------------------------------------------------------
    @property
    def n_points(self) -> int:
        return len(self.point_ids)

    @property
    def dim(self) -> int:
        return self.n_base + 3 * self.n_points

    def cols(self, i: int) -> slice:
        """Point ``i``'s columns of ``P``."""
        return point_cols(i, self.n_base)

    def point_covariance(self, i: int) -> np.ndarray:
        """World-frame covariance of point ``i``: ``dX = xi_i - skew(X_hat) omega``."""
        c = self.cols(i)
        A = -skew(self.points_xyz[i] - self.origin)
        P = self.P
        AP = A @ P[ROT, c]
        return A @ P[ROT, ROT] @ A.T + AP + AP.T + P[c, c]

    def pose_covariance(self) -> np.ndarray:
        """Covariance of the right perturbation of ``T_world_body`` ([rot, trans], body frame)."""
        A = adjoint(invert(self._T_about_origin()))
        return A @ self.P[POSE, POSE] @ A.T

    def _T_about_origin(self) -> np.ndarray:
        T = self.T_world_body.copy()
        T[:3, 3] -= self.origin
        return T

    def recenter(self, origin: np.ndarray) -> None:
        """Move the centre of the rotation error to ``origin`` (world, metres); an exact change of
        coordinates to first order. The prediction keeps it near the vehicle so that corrections of
        the rotation do not swing positions far from it by second-order terms (which would bias a
        long run towards the starting point)."""
        self._require_batch_mode()
        d = np.asarray(origin, dtype=float) - self.origin
        if not np.any(d):
            return
        # nu and every xi gain -skew(d) omega: P <- M P M^T with M = I + C E_rot^T
        C = np.zeros((self.dim, 3))
        C[POS] = -skew(d)
        C[self.n_base :] = np.tile(C[POS], (self.n_points, 1))
        self._add_symmetric_low_rank(C, self.P[ROT, :], self.P[ROT, ROT])
        self.origin = self.origin + d

    def _keep_origin_near_vehicle(self) -> None:
        t = self.T_world_body[:3, 3]
        if np.sum((t - self.origin) ** 2) > RECENTER_M**2:
            self.recenter(t)

    def _add_symmetric_low_rank(self, C: np.ndarray, B: np.ndarray | None, D: np.ndarray) -> None:
        """``P += C B + (C B)^T + C D C^T`` as two outer products (``C`` (N,k), ``B`` (k,N) or None
        for zero, ``D`` (k,k) symmetric)."""
        V = 0.5 * D @ C.T if B is None else B + 0.5 * D @ C.T
        self.P += C @ V
        self.P += V.T @ C.T  # a second product is cheaper than adding a transposed matrix

    def _rotation_coupling(self, R_world: np.ndarray) -> np.ndarray:
        """(N,3): how a world-frame rotation error ``R_world @ a`` enters every error coordinate."""
        G = np.zeros((self.dim, 3))
        G[ROT] = R_world
        G[POS] = skew(self.T_world_body[:3, 3] - self.origin) @ R_world
        if self.n_points:
            G[self.n_base :] = (skew(self.points_xyz - self.origin) @ R_world).reshape(-1, 3)
        return G

    # --- prediction ----------------------------------------------------------------------------
    def predict_increment(self, U: np.ndarray, Q_U: np.ndarray, dt_s: float) -> None:
        """Odometry: ``T <- T U`` with ``Q_U`` the increment's covariance ([rot, trans], right perturbation).
        The velocity is set to the increment's mean twist, with the increment's uncertainty."""
        self._keep_origin_near_vehicle()
        self.T_world_body = self.T_world_body @ U
        R = self.T_world_body[:3, :3]
        # the error is invariant under the motion (F = I); only the increment's noise enters
        G = np.zeros((self.dim, 6))
        G[:, :3] = self._rotation_coupling(R)
        G[POS, 3:] = R
        self._add_symmetric_low_rank(G, None, Q_U)
        if dt_s > 0:
            self.v_body = local(np.eye(4), U) / dt_s
            P = self.P
            P[VEL, :] = 0.0
            P[:, VEL] = 0.0
            P[VEL, VEL] = Q_U / dt_s**2 + np.eye(6) * 1e-6

    def predict_constant_velocity(self, dt_s: float, sigma_acc: np.ndarray) -> None:
        """Constant-velocity model: ``T <- T Exp(v dt)``, ``v <- v + w`` with white acceleration
        ``sigma_acc`` (6,: [angular rad/s^2, linear m/s^2] per sqrt(Hz))."""
        self._keep_origin_near_vehicle()
        R_before = self.T_world_body[:3, :3]
        self.T_world_body = retract(self.T_world_body, self.v_body * dt_s)
        R = self.T_world_body[:3, :3]
        # B: how a body-velocity error (per unit time) and a right pose perturbation enter the state
        B = np.zeros((self.dim, 6))
        B[:, :3] = self._rotation_coupling(R)
        B[POS, 3:] = R_before
        P = self.P
        q = np.diag(np.asarray(sigma_acc, dtype=float) ** 2) * dt_s
        # F = I + dt B E_vel^T, then the integrated white acceleration: pose (as a right
        # perturbation) and velocity noise
        self._add_symmetric_low_rank(dt_s * B, P[VEL, :], P[VEL, VEL])
        L = np.zeros((self.dim, 12))
        L[:, :6] = B
        L[VEL, 6:] = np.eye(6)
        Qc = np.block([[q * dt_s**2 / 3.0, q * dt_s / 2.0], [q * dt_s / 2.0, q]])
        self._add_symmetric_low_rank(L, None, Qc)

    def predict_constant_velocity_gyro(self, dt_s: float, sigma_linear_acc: float, R_prev_curr: np.ndarray, var_rot_rad2: float) -> None:
        """The constant-velocity model with the rotation measured: ``T <- T [R_prev_curr, J v dt]``
        (the rotation ``R_prev_curr`` from the gyroscope, bias taken off, white-noise variance
        ``var_rot_rad2`` per axis; the translation from the linear velocity, white acceleration
        ``sigma_linear_acc`` m/s^2 per sqrt(Hz)). The angular velocity becomes the gyroscope's mean
        rate. Follow with :meth:`propagate_gyro_bias`."""
        self._keep_origin_near_vehicle()
        R_before = self.T_world_body[:3, :3]
        rotvec = Rotation.from_matrix(R_prev_curr).as_rotvec()
        self.T_world_body = retract(self.T_world_body, np.r_[rotvec, self.v_body[3:] * dt_s])
        R = self.T_world_body[:3, :3]
        P = self.P
        # only the linear velocity moves the pose here: F = I + dt C E_vlin^T
        C = np.zeros((self.dim, 3))
        C[POS] = R_before
        self._add_symmetric_low_rank(dt_s * C, P[VEL_LIN, :], P[VEL_LIN, VEL_LIN])
        q = np.eye(3) * sigma_linear_acc**2 * dt_s
        L = np.zeros((self.dim, 6))
        L[:, :3] = C
        L[VEL_LIN, 3:] = np.eye(3)
        self._add_symmetric_low_rank(L, None, np.block([[q * dt_s**2 / 3.0, q * dt_s / 2.0], [q * dt_s / 2.0, q]]))
        self._add_symmetric_low_rank(self._rotation_coupling(R), None, np.eye(3) * var_rot_rad2)
        # the angular velocity: the gyroscope's mean rate, with its white noise
        ang = slice(6, 9)
        P[ang, :] = 0.0
        P[:, ang] = 0.0
        P[ang, ang] = np.eye(3) * (var_rot_rad2 / dt_s**2 + 1e-6)
        self.v_body[:3] = rotvec / dt_s

    def propagate_imu_biases(self, R_body_imu: np.ndarray, span_s: float, gyro_random_walk: float, accel_random_walk: float) -> None:
        """After a prediction whose rotation the gyroscope measured over ``span_s`` seconds: the
        gyroscope's bias error ``db`` turned the body by ``-R_body_imu db span_s`` (right perturbation
        at the new pose), ``F = I + C E_bias^T``; then both biases walk (``gyro_random_walk`` rad/s^2
        and ``accel_random_walk`` m/s^3 per sqrt(Hz))."""
        if not self.has_imu_biases or span_s <= 0:
            return
        P = self.P
        C = -span_s * self._rotation_coupling(self.T_world_body[:3, :3] @ np.asarray(R_body_imu, dtype=float)[:3, :3])
        self._add_symmetric_low_rank(C, P[GYRO_BIAS, :], P[GYRO_BIAS, GYRO_BIAS])
        P[GYRO_BIAS, GYRO_BIAS] += np.eye(3) * gyro_random_walk**2 * span_s
        P[ACCEL_BIAS, ACCEL_BIAS] += np.eye(3) * accel_random_walk**2 * span_s

    def gravity_update(
        self, f_imu_mps2: np.ndarray, accel_body_mps2: np.ndarray, R_body_imu: np.ndarray, var_mps4: float, gravity_mps2: float, gate_chi2: float
    ) -> bool:
        """The accelerometer's mean specific force over a frame ``f_imu_mps2`` (IMU frame) as a
        measurement of the tilt, in its two horizontal components in the body frame:
        ``R_body_imu (f - b_a) = a_body + R_world_body^T g e_z`` with the accelerometer's bias
        ``b_a`` in the state, the body's own acceleration ``accel_body_mps2`` as far as it is known
        and ``var_mps4`` the noise per axis, unmodelled acceleration included. The vertical
        component, which the terrain's bumps dominate, says nothing about the tilt to first order
        and is not used. Skipped (False) when the innovation fails the chi-square gate ``gate_chi2``
        (2 degrees of freedom: the vehicle accelerating more than ``var_mps4`` allows). Only roll
        and pitch are observed (the Jacobian has no yaw), and only as far as the bias allows."""
        self._require_batch_mode()
        if not self.has_imu_biases:
            raise RuntimeError("a tilt update needs the IMU's biases in the state")
        up = np.array([0.0, 0.0, 1.0])
        R_bi = np.asarray(R_body_imu, dtype=float)[:3, :3]
        R_bw = self.T_world_body[:3, :3].T
        z = (R_bi @ (np.asarray(f_imu_mps2, dtype=float) - self.accel_bias_mps2))[:2]
        y = z - (np.asarray(accel_body_mps2, dtype=float)[:2] + gravity_mps2 * (R_bw @ up)[:2])
        H = np.zeros((2, 6))  # on [rotation error, accelerometer bias error]
        H[:, :3] = gravity_mps2 * (R_bw @ skew(up))[:2]  # R_true^T e_z = R_hat^T (e_z + skew(e_z) omega)
        H[:, 3:] = R_bi[:2]  # the measurement moves with the bias: y's model gains R_bi db_a
        cols = np.r_[0:3, ACCEL_BIAS.start : ACCEL_BIAS.stop]
        PHt = self.P[:, cols] @ H.T  # (N,2)
        S = H @ PHt[cols] + var_mps4 * np.eye(2)
        if not float(y @ np.linalg.solve(S, y)) <= gate_chi2:
            return False
        K = np.linalg.solve(S, PHt.T).T
        self.apply_correction(K @ y)
        self.P -= K @ PHt.T
        self._symmetrize()
        return True

    def reset_linear_velocity(self, v_lin_mps: np.ndarray, R_mps2: np.ndarray) -> None:
        """The body's linear velocity set to a measurement ``v_lin_mps`` (3,) with covariance
        ``R_mps2`` (3x3), what the state held of it forgotten: the ground's motion between two frames
        (:class:`~dem_graph.frontend.ground_motion.GroundMotion`) where the speed was only a guess
        (the start without odometry, or tracking lost)."""
        self._require_batch_mode()
        self.v_body[3:] = np.asarray(v_lin_mps, dtype=float)
        self.P[VEL_LIN, :] = 0.0
        self.P[:, VEL_LIN] = 0.0
        self.P[VEL_LIN, VEL_LIN] = np.asarray(R_mps2, dtype=float)

    # --- observation -------------------------------------------------------------------------
    def observe(self, indices: np.ndarray, camera: PinholeCamera, T_body_cam: np.ndarray):
        """Predicted pixels of points ``indices`` and the Jacobians w.r.t. the pose error (k,2,6) and
        the point error (k,2,3). Also returns the in-front mask and the camera-frame depths."""
        R_wb, t_wb = self.T_world_body[:3, :3], self.T_world_body[:3, 3]
        T_cam_body = invert(T_body_cam)
        R_cb = T_cam_body[:3, :3]
        p_body = (self.points_xyz[indices] - t_wb) @ R_wb  # R_wb^T (x - t)
        p_cam = p_body @ R_cb.T + T_cam_body[:3, 3]
        uv, J_uv_pc, in_front = camera.project_with_jacobian(p_cam)
        # p_body = R^T (X - t) moves by R^T (xi - nu); the rotation error cancels out
        H_point = J_uv_pc @ (R_cb @ R_wb.T)
        H_pose = np.concatenate([np.zeros((len(p_body), 2, 3)), -H_point], axis=2)
        return uv, H_pose, H_point, in_front, p_cam[:, 2]

    def innovation_covariances(self, H_pose: np.ndarray, H_point: np.ndarray, R_px2: float) -> np.ndarray:
        """(n,2,2) innovation covariances of every point, from the Jacobians of :meth:`observe` (all points)."""
        n = self.n_points
        P = self.P
        P_pp = P[POSE, POSE]
        P_pi = P[POSE, self.n_base :].reshape(6, n, 3).transpose(1, 0, 2)
        idx = self.n_base + 3 * np.arange(n)[:, None] + np.arange(3)[None, :]
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
            H[2 * j : 2 * j + 2, self.cols(int(i))] = H_point[j]
        PHt = self.P @ H.T
        S = H @ PHt + R_px2 * np.eye(2 * k)
        K = np.linalg.solve(S, PHt.T).T
        self.apply_correction(K @ innovations.reshape(-1))
        self.P -= K @ PHt.T
        self._symmetrize()

    # --- sequential update (PTPM) ------------------------------------------------------------
    # The covariance stays P0 - Lt^T Lt and the mean correction accumulates in dx until
    # end_sequential(); every point is linearised once, at the predicted state (as GM), and its
    # prediction follows the corrections made so far to first order. Lt holds one row per
    # measured coordinate, and P0 is only read by rows (contiguous; P is symmetric).
    def begin_sequential(self, max_updates: int) -> None:
        self._L = np.zeros((2 * max(max_updates, 1), self.dim))  # Lt: one row per measured coordinate
        self._L_rows = 0
        self._dx = np.zeros(self.dim)

    def correction(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """Accumulated (pose, point i) corrections of the current sequential session."""
        return self._dx[POSE], self._dx[self.cols(i)]

    def _HL(self, c: slice, H_pose: np.ndarray, H_point: np.ndarray) -> np.ndarray:
        """(2,k): the measurement Jacobian times the pending downdate factor."""
        Lt = self._L[: self._L_rows]
        return H_pose @ Lt[:, POSE].T + H_point @ Lt[:, c].T

    def sequential_innovation_covariance(self, i: int, H_pose: np.ndarray, H_point: np.ndarray, R_px2: float) -> np.ndarray:
        c = self.cols(i)
        P = self.P
        HpPpc = H_pose @ P[POSE, c]
        S = H_pose @ P[POSE, POSE] @ H_pose.T + HpPpc @ H_point.T + (HpPpc @ H_point.T).T + H_point @ P[c, c] @ H_point.T
        S[0, 0] += R_px2
        S[1, 1] += R_px2
        if self._L_rows:
            HL = self._HL(c, H_pose, H_point)
            S -= HL @ HL.T
        return S

    def sequential_update(self, i: int, innovation: np.ndarray, H_pose: np.ndarray, H_point: np.ndarray, S: np.ndarray) -> None:
        """One point's update; ``S`` from :meth:`sequential_innovation_covariance` for the same point."""
        c = self.cols(i)
        HP = H_pose @ self.P[POSE, :] + H_point @ self.P[c, :]  # (2,N) = (P H^T)^T
        k = self._L_rows
        if k:
            HP -= self._HL(c, H_pose, H_point) @ self._L[:k]
        S_inv = _inv2(S)
        self._dx += (S_inv @ innovation) @ HP
        if k + 2 > self._L.shape[0]:
            self._L = np.concatenate([self._L, np.zeros_like(self._L)], axis=0)
        self._L[k : k + 2] = _chol2(S_inv).T @ HP
        self._L_rows = k + 2

    def end_sequential(self) -> None:
        if self._L is not None and self._L_rows:
            Lt = self._L[: self._L_rows]
            self.P -= Lt.T @ Lt
            self._symmetrize()
            self.apply_correction(self._dx)
        self._L = None
        self._L_rows = 0

    # --- state changes -----------------------------------------------------------------------
    def apply_correction(self, dx: np.ndarray) -> None:
        """Move the estimate by the error-state vector ``dx`` (the group action of the module docstring)."""
        E = so3_exp(dx[ROT])
        T = self.T_world_body
        T[:3, :3] = E @ T[:3, :3]
        o = self.origin
        T[:3, 3] = E @ (T[:3, 3] - o) + o + dx[POS]
        self.v_body = self.v_body + dx[VEL]
        if self.has_imu_biases:
            self.gyro_bias_rad_s = self.gyro_bias_rad_s + dx[GYRO_BIAS]
            self.accel_bias_mps2 = self.accel_bias_mps2 + dx[ACCEL_BIAS]
        if self.n_points:
            self.points_xyz = (self.points_xyz - o) @ E.T + o + dx[self.n_base :].reshape(-1, 3)

    def add_points(self, point_ids: np.ndarray, p_body: np.ndarray, Sigma_body: np.ndarray) -> None:
        """Append points measured in the current body frame (``p_body`` (k,3)) with covariance
        ``Sigma_body`` (k,3,3); their correlation with the state follows from the pose's.
        With ``X = R p + t``, the new point's error is ``xi = nu + R dp``."""
        self._require_batch_mode()
        k = len(point_ids)
        if k == 0:
            return
        R, t = self.T_world_body[:3, :3], self.T_world_body[:3, 3]
        X = p_body @ R.T + t
        N = self.dim
        P_new = np.zeros((N + 3 * k, N + 3 * k))
        P_new[:N, :N] = self.P
        cross = np.tile(self.P[POS, :], (k, 1))  # (3k, N)
        P_new[N:, :N] = cross
        P_new[:N, N:] = cross.T
        P_new[N:, N:] = np.tile(self.P[POS, POS], (k, k))
        for j in range(k):
            s = slice(N + 3 * j, N + 3 * j + 3)
            P_new[s, s] += R @ Sigma_body[j] @ R.T
        self.P = P_new
        self.points_xyz = np.concatenate([self.points_xyz, X])
        self.point_ids = np.concatenate([self.point_ids, np.asarray(point_ids, dtype=np.int64)])

    def remove_points(self, remove_mask: np.ndarray) -> None:
        self._require_batch_mode()
        if not np.any(remove_mask):
            return
        keep_pts = ~np.asarray(remove_mask, dtype=bool)
        keep = np.concatenate([np.ones(self.n_base, dtype=bool), np.repeat(keep_pts, 3)])
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
