"""The per-point arithmetic of the camera's factors in compiled loops: the frame's pose update's
(:func:`normal_equations`, for :func:`~dem_graph.estimators.pose_update.update_pose`) and the batch
start's landmark fit's (:func:`pixel_normal_equations`, for
:func:`~dem_graph.estimators.batch_start.fit_landmarks`), sharing one projection (:func:`_project`).

Pose update: for each tracked point, its pixel through the camera (OpenCV's radial-tangential
distortion) with the Jacobians with respect to the body pose's right perturbation ``[rot, trans]``
and to the point, the innovation covariance ``sigma_px^2 I + H_x Sigma H_x^T``, its Huber weight,
and the point's terms of the Gauss-Newton normal equations ``sum H^T W H`` and ``sum H^T W r``. The
numpy version (:func:`~dem_graph.estimators.pose_update.project_with_jacobians` and the batched
products) made some twenty array temporaries per iteration, four iterations a frame; the arithmetic
is the same, in another order of summation (the two agree to 1e-9, tested).

Landmark fit: for each observation, the residual, its Huber weight and loss, and its terms of its
landmark's normal equations ``sum J^T W J`` (3x3) and ``sum J^T W r``, ``J`` the pixel's Jacobian
with respect to the world point. In numpy (``PinholeCamera.project_with_jacobian`` and the batched
products) a pass over `paper`'s 217 000 observations took 0.14 s, in some thirty temporaries; this
loop 12 ms (cProfile, 19 passes, an Intel Xeon).

The two loops share :func:`_project` in this module, so that an edit to it reaches numba's cache of
both (the cache follows the file of the function compiled, not the files of those it calls).
"""

from __future__ import annotations

import math

import numba
import numpy as np


@numba.njit(cache=True, nogil=True)
def _project(pc0: float, pc1: float, pc2: float, intrinsics: np.ndarray) -> tuple[float, float, float, float, float, float, float, float]:
    """The pixel ``(u, v)`` of the camera-frame point ``(pc0, pc1, pc2)`` (``pc2`` > 0) and its Jacobian
    ``d (u, v) / d p_cam`` row by row: ``(u, v, j00, j01, j02, j10, j11, j12)``. ``intrinsics``: fx, fy,
    cx, cy, k1, k2, p1, p2, k3 (pixels; the distortion OpenCV's)."""
    fx, fy, cx, cy = intrinsics[0], intrinsics[1], intrinsics[2], intrinsics[3]
    k1, k2, p1, p2, k3 = intrinsics[4], intrinsics[5], intrinsics[6], intrinsics[7], intrinsics[8]
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
    return (
        fx * xd + cx, fy * yd + cy,
        a00 * inv_z, a01 * inv_z, -(a00 * x + a01 * y) * inv_z,
        a10 * inv_z, a11 * inv_z, -(a10 * x + a11 * y) * inv_z,
    )  # fmt: skip


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
        u, v, J[0, 0], J[0, 1], J[0, 2], J[1, 0], J[1, 1], J[1, 2] = _project(pc0, pc1, pc2, intrinsics)
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
        e0 = u_obs - u
        e1 = v_obs - v
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


@numba.njit(cache=True, nogil=True)
def pixel_normal_equations(
    X_world: np.ndarray,
    obs_landmark: np.ndarray,
    R_cam_world: np.ndarray,
    t_cam_world: np.ndarray,
    obs_pose: np.ndarray,
    uv_px: np.ndarray,
    intrinsics: np.ndarray,
    sigma_px: float,
    huber_k: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per landmark (rows of ``X_world``): the pixels' loss (Huber's, or half the squared whitened
    residual when ``huber_k`` <= 0), ``sum J^T W J`` (n,3,3) and ``sum J^T W r`` (n,3), ``r`` the
    predicted minus the measured pixel. Observation ``i`` sees landmark ``obs_landmark[i]`` from
    camera ``obs_pose[i]`` (``R_cam_world``, ``t_cam_world``); one behind its camera, or with a
    non-finite pixel, is left out. ``intrinsics``: fx, fy, cx, cy, k1, k2, p1, p2, k3."""
    n = X_world.shape[0]
    loss = np.zeros(n)
    H = np.zeros((n, 3, 3))
    g = np.zeros((n, 3))
    inv_var = 1.0 / (sigma_px * sigma_px)
    J = np.zeros((2, 3))
    for i in range(obs_landmark.shape[0]):
        j, k = obs_landmark[i], obs_pose[i]
        u_obs, v_obs = uv_px[i, 0], uv_px[i, 1]
        if not (math.isfinite(u_obs) and math.isfinite(v_obs)):
            continue
        R = R_cam_world[k]
        pc0 = R[0, 0] * X_world[j, 0] + R[0, 1] * X_world[j, 1] + R[0, 2] * X_world[j, 2] + t_cam_world[k, 0]
        pc1 = R[1, 0] * X_world[j, 0] + R[1, 1] * X_world[j, 1] + R[1, 2] * X_world[j, 2] + t_cam_world[k, 1]
        pc2 = R[2, 0] * X_world[j, 0] + R[2, 1] * X_world[j, 1] + R[2, 2] * X_world[j, 2] + t_cam_world[k, 2]
        if not pc2 > 1e-9:
            continue
        u, v, c00, c01, c02, c10, c11, c12 = _project(pc0, pc1, pc2, intrinsics)
        for c in range(3):  # d uv / d X_world = (d uv / d p_cam) R
            J[0, c] = c00 * R[0, c] + c01 * R[1, c] + c02 * R[2, c]
            J[1, c] = c10 * R[0, c] + c11 * R[1, c] + c12 * R[2, c]
        e0 = u - u_obs
        e1 = v - v_obs
        e2 = (e0 * e0 + e1 * e1) * inv_var
        w = inv_var
        if huber_k > 0.0 and e2 > huber_k * huber_k:
            e = math.sqrt(e2)
            w = inv_var * huber_k / e
            loss[j] += huber_k * e - 0.5 * huber_k * huber_k
        else:
            loss[j] += 0.5 * e2
        for p in range(3):
            g[j, p] += w * (J[0, p] * e0 + J[1, p] * e1)
            for q in range(3):
                H[j, p, q] += w * (J[0, p] * J[0, q] + J[1, p] * J[1, q])
    return loss, H, g


def compile_kernel() -> None:
    """Run :func:`normal_equations` once on one point, so that numba compiles it (about 2 s the
    first run after an install) or loads it from its cache before a run's first frame rather than
    in it."""
    eye = np.eye(3)
    normal_equations(eye, np.zeros(3), np.array([[0.0, 0.0, 5.0]]), np.zeros((1, 3, 3)), np.zeros((1, 2)), eye, np.zeros(3), np.array([500.0, 500.0, 0.0, 0.0, 0, 0, 0, 0, 0]), 1.0, 1.345)


__all__ = ["compile_kernel", "normal_equations", "pixel_normal_equations"]
