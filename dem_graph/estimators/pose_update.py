"""One frame's pose from tracked points whose positions are known with some uncertainty.

The per-frame step between keyframes of the graph estimator (docs/isam2_design.md): the points stay
fixed at their current estimates, and their covariances enter as extra pixel noise,
``R_i = sigma_px^2 I + H_x,i Sigma_i H_x,i^T``. The pose prior (odometry prediction) and the
pixels are combined by Gauss-Newton on the MAP cost (an iterated EKF on the pose alone), with a
Huber weight per point. The pose error is the package's right perturbation ``[rot, trans]``.
"""

from __future__ import annotations

import numpy as np

from dem_graph.estimators.projection_kernel import normal_equations
from dem_graph.geometry.camera import PinholeCamera
from dem_graph.geometry.lie import local, retract, skew
from dem_graph.geometry.se3 import invert

HUBER_K = 1.345


def project_with_jacobians(T_world_body: np.ndarray, X_world: np.ndarray, camera: PinholeCamera, T_body_cam: np.ndarray):
    """Pixels (n,2), Jacobians w.r.t. the right pose perturbation (n,2,6) and the point (n,2,3), in-front mask."""
    R, t = T_world_body[:3, :3], T_world_body[:3, 3]
    T_cam_body = invert(T_body_cam)
    p_body = (X_world - t) @ R
    p_cam = p_body @ T_cam_body[:3, :3].T + T_cam_body[:3, 3]
    uv, J_uv_pc, in_front = camera.project_with_jacobian(p_cam)
    J_uv_pb = J_uv_pc @ T_cam_body[:3, :3]
    n = len(p_body)
    H_pose = J_uv_pb @ np.concatenate([skew(p_body), -np.broadcast_to(np.eye(3), (n, 3, 3))], axis=2)
    H_point = J_uv_pb @ R.T
    return uv, H_pose, H_point, in_front


def update_pose(
    T_world_body_prior: np.ndarray,
    P_prior: np.ndarray,
    X_world: np.ndarray,
    Sigma_world: np.ndarray,
    uv_px: np.ndarray,
    camera: PinholeCamera,
    T_body_cam: np.ndarray,
    sigma_px: float,
    iterations: int = 4,
    robust: bool = True,
) -> tuple[np.ndarray, np.ndarray]:
    """MAP pose from the prior ``(T_world_body_prior, P_prior)`` and the pixels ``uv_px`` (n,2) of
    points ``X_world`` (n,3) with covariances ``Sigma_world`` (n,3,3). Returns the pose and its
    6x6 covariance (right perturbation)."""
    X = np.asarray(X_world, dtype=float).reshape(-1, 3)
    z = np.asarray(uv_px, dtype=float).reshape(-1, 2)
    Sig = np.asarray(Sigma_world, dtype=float).reshape(-1, 3, 3)
    if not (len(X) == len(z) == len(Sig)):
        raise ValueError(f"points, pixels and covariances must have the same length, got {len(X)}, {len(z)}, {len(Sig)}")
    P0_inv = np.linalg.inv(P_prior)
    T = np.array(T_world_body_prior, dtype=float)
    T_cam_body = invert(T_body_cam)
    R_cam_body, t_cam_body = np.ascontiguousarray(T_cam_body[:3, :3]), np.ascontiguousarray(T_cam_body[:3, 3])
    intrinsics = camera.intrinsics_array
    X, Sig, z = np.ascontiguousarray(X), np.ascontiguousarray(Sig), np.ascontiguousarray(z)
    for _ in range(max(iterations, 1)):
        # the points' terms (pixels, Jacobians, innovation covariances, Huber weights) in one compiled loop
        HtWH, HtWr, _ = normal_equations(
            np.ascontiguousarray(T[:3, :3]), np.ascontiguousarray(T[:3, 3]), X, Sig, z, R_cam_body, t_cam_body, intrinsics, float(sigma_px), HUBER_K if robust else 0.0
        )
        # Gauss-Newton on |xi_0 + dx|^2_P0 + sum |r - H dx|^2_R, with xi_0 = local(prior, T)
        xi0 = local(T_world_body_prior, T)
        info = P0_inv + HtWH
        g = -P0_inv @ xi0 + HtWr
        dx = np.linalg.solve(info, g)
        T = retract(T, dx)
        if np.max(np.abs(dx)) < 1e-8:  # radians and metres: far below any pixel
            break
    P = np.linalg.inv(info)
    return T, 0.5 * (P + P.T)
