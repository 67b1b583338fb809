"""Rigid transforms as 4x4 numpy matrices.

``T_a_b`` maps coordinates in frame b to frame a: ``p_a = T_a_b @ p_b``. Quaternions are
stored in scipy's (and TUM's) order ``[qx, qy, qz, qw]``.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from dem_graph.errors import ConfigError


def make_pose(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Build ``T`` (4x4, or (N,4,4) for stacked inputs) from rotation ``R`` and translation ``t``."""
    R = np.asarray(R, dtype=float)
    t = np.asarray(t, dtype=float)
    T = np.zeros(R.shape[:-2] + (4, 4))
    T[..., :3, :3] = R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    return T


def invert(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid transform (or a stack of them)."""
    T = np.asarray(T, dtype=float)
    R_inv = np.swapaxes(T[..., :3, :3], -1, -2)
    t_inv = -np.einsum("...ij,...j->...i", R_inv, T[..., :3, 3])
    return make_pose(R_inv, t_inv)


def nearest_pose(T: np.ndarray) -> np.ndarray:
    """``T`` with its rotation replaced by the nearest rotation matrix (SVD): a product of many
    transforms drifts off SO(3) by rounding, and :func:`invert` assumes it is on it."""
    T = np.array(T, dtype=float)
    U, _, Vt = np.linalg.svd(T[..., :3, :3])
    D = np.ones(T.shape[:-2] + (3,))
    D[..., 2] = np.sign(np.linalg.det(U @ Vt))
    T[..., :3, :3] = (U * D[..., None, :]) @ Vt
    return T


def transform_points(T_a_b: np.ndarray, points_b: np.ndarray) -> np.ndarray:
    """Map (N,3) points from frame b to frame a."""
    points_b = np.asarray(points_b, dtype=float)
    return points_b @ T_a_b[:3, :3].T + T_a_b[:3, 3]


def rotation_from_rpy(roll_rad, pitch_rad, yaw_rad) -> np.ndarray:
    """``Rz(yaw) @ Ry(pitch) @ Rx(roll)``; broadcasts over array inputs to (...,3,3)."""
    angles = np.stack(np.broadcast_arrays(yaw_rad, pitch_rad, roll_rad), axis=-1)
    return Rotation.from_euler("ZYX", angles.reshape(-1, 3)).as_matrix().reshape(angles.shape[:-1] + (3, 3))


def quat_xyzw_from_matrix(R: np.ndarray) -> np.ndarray:
    """Unit quaternion(s) ``[qx, qy, qz, qw]`` with ``qw >= 0`` from rotation matrices."""
    R = np.asarray(R, dtype=float)
    q = Rotation.from_matrix(R.reshape(-1, 3, 3)).as_quat()
    q[q[:, 3] < 0] *= -1.0
    return q.reshape(R.shape[:-2] + (4,))


def matrix_from_quat_xyzw(q: np.ndarray) -> np.ndarray:
    """Rotation matrix (or matrices) from quaternion(s) ``[qx, qy, qz, qw]``."""
    q = np.asarray(q, dtype=float)
    return Rotation.from_quat(q.reshape(-1, 4)).as_matrix().reshape(q.shape[:-1] + (3, 3))


def check_pose(T, name: str, source: str | None = None, tol: float = 1e-6) -> np.ndarray:
    """Validate a 4x4 rigid transform given as nested lists or an array; return it as float array.

    Raises :class:`ConfigError` that names ``name`` (and ``source``) and the problem.
    """
    try:
        T = np.asarray(T, dtype=float)
    except (TypeError, ValueError):
        raise ConfigError(f"{name} must be a 4x4 matrix of numbers", source) from None
    if T.shape != (4, 4):
        raise ConfigError(f"{name} must be a 4x4 matrix, got shape {T.shape}", source)
    if not np.all(np.isfinite(T)):
        raise ConfigError(f"{name} contains NaN or infinite values", source)
    if not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0], atol=tol):
        raise ConfigError(f"{name} last row must be [0, 0, 0, 1], got {T[3].tolist()}", source)
    R = T[:3, :3]
    if not np.allclose(R.T @ R, np.eye(3), atol=tol) or np.linalg.det(R) < 0:
        raise ConfigError(f"{name} rotation block is not a proper rotation (orthonormal, det +1)", source)
    return T
