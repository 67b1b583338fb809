"""The pixels' part of the batch start's landmark fit (:func:`~dem_graph.estimators.batch_start.fit_landmarks`)
in one compiled loop.

For each observation: the landmark through its pose's camera (OpenCV's radial-tangential
distortion), the residual, its Huber weight and loss, and its terms of the landmark's Gauss-Newton
normal equations ``sum J^T W J`` (3x3) and ``sum J^T W r``, ``J`` the pixel's Jacobian with respect
to the world point. The numpy version (``PinholeCamera.project_with_jacobian`` and the batched
products) took 0.14 s a pass over `paper`'s 217 000 observations, in some thirty temporaries;
this loop 12 ms (cProfile, 19 passes, this machine).
"""

from __future__ import annotations

import math

import numba
import numpy as np


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
    fx, fy, cx, cy = intrinsics[0], intrinsics[1], intrinsics[2], intrinsics[3]
    k1, k2, p1, p2, k3 = intrinsics[4], intrinsics[5], intrinsics[6], intrinsics[7], intrinsics[8]
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
        # d uv / d p_cam = (distortion Jacobian) @ [[1/z, 0, -x/z], [0, 1/z, -y/z]], then d p_cam / d X_world = R
        c00, c01, c02 = a00 * inv_z, a01 * inv_z, -(a00 * x + a01 * y) * inv_z
        c10, c11, c12 = a10 * inv_z, a11 * inv_z, -(a10 * x + a11 * y) * inv_z
        for c in range(3):
            J[0, c] = c00 * R[0, c] + c01 * R[1, c] + c02 * R[2, c]
            J[1, c] = c10 * R[0, c] + c11 * R[1, c] + c12 * R[2, c]
        e0 = fx * xd + cx - u_obs
        e1 = fy * yd + cy - v_obs
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


__all__ = ["pixel_normal_equations"]
