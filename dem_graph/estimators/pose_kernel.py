"""The per-point arithmetic of the frame's pose update (:func:`~dem_graph.estimators.pose_update.update_pose`)
in one compiled loop.

For each tracked point: its pixel through the camera (OpenCV's radial-tangential distortion) with
the Jacobians with respect to the body pose's right perturbation ``[rot, trans]`` and to the point,
the innovation covariance ``sigma_px^2 I + H_x Sigma H_x^T``, its Huber weight, and the point's
terms of the Gauss-Newton normal equations ``sum H^T W H`` and ``sum H^T W r``. The numpy version
(:func:`~dem_graph.estimators.pose_update.project_with_jacobians` and the batched products) made
some twenty array temporaries per iteration, four iterations a frame; the arithmetic is the same,
in another order of summation (the two agree to 1e-9, tested).
"""

from __future__ import annotations

import math

import numba
import numpy as np


@numba.njit(cache=True, nogil=True)
def normal_equations(
    R_world_body: np.ndarray,
    t_world_body: np.ndarray,
    X_world: np.ndarray,
    Sigma_world: np.ndarray,
    uv_px: np.ndarray,
    R_cam_body: np.ndarray,
    t_cam_body: np.ndarray,
    intrinsics: np.ndarray,
    sigma_px: float,
    huber_k: float,
) -> tuple[np.ndarray, np.ndarray, int]:
    """``(sum H^T W H (6x6), sum H^T W r (6,), points used)`` over the points in front of the camera
    with a finite pixel. ``intrinsics``: fx, fy, cx, cy, k1, k2, p1, p2, k3 (pixels; the distortion
    OpenCV's). ``huber_k`` <= 0: no robust weight."""
    fx, fy, cx, cy = intrinsics[0], intrinsics[1], intrinsics[2], intrinsics[3]
    k1, k2, p1, p2, k3 = intrinsics[4], intrinsics[5], intrinsics[6], intrinsics[7], intrinsics[8]
    A = np.zeros((6, 6))
    b = np.zeros(6)
    H = np.zeros((2, 6))
    Hx = np.zeros((2, 3))
    J = np.zeros((2, 3))
    used = 0
    for i in range(X_world.shape[0]):
        u_obs, v_obs = uv_px[i, 0], uv_px[i, 1]
        if not (math.isfinite(u_obs) and math.isfinite(v_obs)):
            continue
        # the point in the body and camera frames
        d0, d1, d2 = X_world[i, 0] - t_world_body[0], X_world[i, 1] - t_world_body[1], X_world[i, 2] - t_world_body[2]
        pb0 = R_world_body[0, 0] * d0 + R_world_body[1, 0] * d1 + R_world_body[2, 0] * d2
        pb1 = R_world_body[0, 1] * d0 + R_world_body[1, 1] * d1 + R_world_body[2, 1] * d2
        pb2 = R_world_body[0, 2] * d0 + R_world_body[1, 2] * d1 + R_world_body[2, 2] * d2
        pc0 = R_cam_body[0, 0] * pb0 + R_cam_body[0, 1] * pb1 + R_cam_body[0, 2] * pb2 + t_cam_body[0]
        pc1 = R_cam_body[1, 0] * pb0 + R_cam_body[1, 1] * pb1 + R_cam_body[1, 2] * pb2 + t_cam_body[1]
        pc2 = R_cam_body[2, 0] * pb0 + R_cam_body[2, 1] * pb1 + R_cam_body[2, 2] * pb2 + t_cam_body[2]
        if not pc2 > 1e-9:
            continue
        # the pixel and its Jacobian with respect to the camera-frame point
        x, y = pc0 / pc2, pc1 / pc2
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        d_radial = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)
        xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
        yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
        a00 = fx * (radial + 2.0 * x * x * d_radial + 2.0 * p1 * y + 6.0 * p2 * x)
        a01 = fx * (2.0 * x * y * d_radial + 2.0 * p1 * x + 2.0 * p2 * y)
        a10 = fy * (2.0 * x * y * d_radial + 2.0 * p1 * x + 2.0 * p2 * y)
        a11 = fy * (radial + 2.0 * y * y * d_radial + 6.0 * p1 * y + 2.0 * p2 * x)
        inv_z = 1.0 / pc2
        # d uv / d p_cam = (distortion Jacobian) @ [[1/z, 0, -x/z], [0, 1/z, -y/z]]
        J[0, 0], J[0, 1], J[0, 2] = a00 * inv_z, a01 * inv_z, -(a00 * x + a01 * y) * inv_z
        J[1, 0], J[1, 1], J[1, 2] = a10 * inv_z, a11 * inv_z, -(a10 * x + a11 * y) * inv_z
        for r in range(2):
            # d uv / d p_body, then the pose's columns: rotation skew(p_body), translation -I
            jb0 = J[r, 0] * R_cam_body[0, 0] + J[r, 1] * R_cam_body[1, 0] + J[r, 2] * R_cam_body[2, 0]
            jb1 = J[r, 0] * R_cam_body[0, 1] + J[r, 1] * R_cam_body[1, 1] + J[r, 2] * R_cam_body[2, 1]
            jb2 = J[r, 0] * R_cam_body[0, 2] + J[r, 1] * R_cam_body[1, 2] + J[r, 2] * R_cam_body[2, 2]
            H[r, 0] = jb1 * pb2 - jb2 * pb1
            H[r, 1] = jb2 * pb0 - jb0 * pb2
            H[r, 2] = jb0 * pb1 - jb1 * pb0
            H[r, 3], H[r, 4], H[r, 5] = -jb0, -jb1, -jb2
            # d uv / d X_world = (d uv / d p_body) R^T
            for c in range(3):
                Hx[r, c] = jb0 * R_world_body[c, 0] + jb1 * R_world_body[c, 1] + jb2 * R_world_body[c, 2]
        # the innovation covariance and its inverse (2x2)
        s00, s01, s11 = sigma_px * sigma_px, 0.0, sigma_px * sigma_px
        for p in range(3):
            for q in range(3):
                sig = Sigma_world[i, p, q]
                s00 += Hx[0, p] * sig * Hx[0, q]
                s01 += Hx[0, p] * sig * Hx[1, q]
                s11 += Hx[1, p] * sig * Hx[1, q]
        det = s00 * s11 - s01 * s01
        w00, w01, w11 = s11 / det, -s01 / det, s00 / det
        e0 = u_obs - (fx * xd + cx)
        e1 = v_obs - (fy * yd + cy)
        if huber_k > 0.0:
            d = math.sqrt(e0 * (w00 * e0 + w01 * e1) + e1 * (w01 * e0 + w11 * e1))
            if d > huber_k:
                weight = huber_k / d  # (d > huber_k > 0)
                w00, w01, w11 = w00 * weight, w01 * weight, w11 * weight
        # H^T W (6x2), then its products with H and the residual
        for p in range(6):
            hw0 = H[0, p] * w00 + H[1, p] * w01
            hw1 = H[0, p] * w01 + H[1, p] * w11
            b[p] += hw0 * e0 + hw1 * e1
            for q in range(6):
                A[p, q] += hw0 * H[0, q] + hw1 * H[1, q]
        used += 1
    return A, b, used


def compile_kernel() -> None:
    """Run :func:`normal_equations` once on one point, so that numba compiles it (about 2 s the
    first run after an install) or loads it from its cache before a run's first frame rather than
    in it."""
    eye = np.eye(3)
    normal_equations(eye, np.zeros(3), np.array([[0.0, 0.0, 5.0]]), np.zeros((1, 3, 3)), np.zeros((1, 2)), eye, np.zeros(3), np.array([500.0, 500.0, 0.0, 0.0, 0, 0, 0, 0, 0]), 1.0, 1.345)


__all__ = ["compile_kernel", "normal_equations"]
