"""Small SO(3)/SE(3) helpers for estimators, in gtsam's tangent order [rotation, translation].

Perturbations are on the right: ``T = T_hat * Exp(xi)``, ``xi = [omega, v]`` with ``v`` in the body
frame. :func:`retract` uses the decoupled form (``R Exp(omega)``, ``t + R v``), which agrees with
gtsam's ``Pose3.retract`` to first order.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial.transform import Rotation

from dem_graph.geometry.se3 import invert


def skew(w: np.ndarray) -> np.ndarray:
    """``skew(a) @ b == cross(a, b)``; (...,3) -> (...,3,3)."""
    w = np.asarray(w, dtype=float)
    S = np.zeros(w.shape[:-1] + (3, 3))
    S[..., 0, 1], S[..., 0, 2] = -w[..., 2], w[..., 1]
    S[..., 1, 0], S[..., 1, 2] = w[..., 2], -w[..., 0]
    S[..., 2, 0], S[..., 2, 1] = -w[..., 1], w[..., 0]
    return S


def so3_exp(w: np.ndarray) -> np.ndarray:
    """The rotation (3,3) of a rotation vector (3,) (Rodrigues). Plain numpy: it runs several
    times a frame, where scipy's ``Rotation`` costs tens of microseconds a call."""
    x, y, z = (float(a) for a in np.asarray(w, dtype=float).reshape(3))
    angle2 = x * x + y * y + z * z
    if angle2 < 1e-16:
        a, b = 1.0 - angle2 / 6.0, 0.5 - angle2 / 24.0
    else:
        angle = math.sqrt(angle2)
        a, b = math.sin(angle) / angle, (1.0 - math.cos(angle)) / angle2
    # I + a K + b K^2 with K = skew(w), K^2 = w w^T - |w|^2 I
    return np.array(
        [
            [1.0 - b * (y * y + z * z), b * x * y - a * z, b * x * z + a * y],
            [b * x * y + a * z, 1.0 - b * (x * x + z * z), b * y * z - a * x],
            [b * x * z - a * y, b * y * z + a * x, 1.0 - b * (x * x + y * y)],
        ]
    )


def so3_log(R: np.ndarray) -> np.ndarray:
    """The rotation vector (3,) of a rotation (3,3); plain numpy below 170 degrees (see
    :func:`so3_exp`), scipy's quaternion route near pi, where the closed form loses precision."""
    R = np.asarray(R, dtype=float)
    c = 0.5 * (R[0, 0] + R[1, 1] + R[2, 2] - 1.0)
    if c < _COS_170_DEG:
        return Rotation.from_matrix(R).as_rotvec()
    v = 0.5 * np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    s = math.sqrt(float(v @ v))  # sin(angle)
    if s < 1e-8:
        return v * (1.0 + s * s / 6.0)
    return v * (math.atan2(s, min(c, 1.0)) / s)


_COS_170_DEG = math.cos(math.radians(170.0))


def so3_log_many(R: np.ndarray) -> np.ndarray:
    """Rotation vectors (n,3) of rotations (n,3,3), in plain numpy (much cheaper than scipy per call
    for a few dozen); for rotations well below pi, as between two poses a frame apart."""
    R = np.asarray(R, dtype=float)
    angle = np.arccos(np.clip((np.einsum("nii->n", R) - 1.0) / 2.0, -1.0, 1.0))
    v = 0.5 * np.stack([R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]], axis=1)
    s = np.sin(angle)
    small = s < 1e-8
    factor = np.where(small, 1.0 + angle * angle / 6.0, angle / np.where(small, 1.0, s))
    return v * factor[:, None]


def so3_exp_many(w: np.ndarray) -> np.ndarray:
    """Rotations (n,3,3) of rotation vectors (n,3) (Rodrigues), in plain numpy."""
    w = np.asarray(w, dtype=float)
    angle = np.linalg.norm(w, axis=1)
    small = angle < 1e-8
    safe = np.where(small, 1.0, angle)
    a = np.where(small, 1.0 - angle**2 / 6.0, np.sin(angle) / safe)
    b = np.where(small, 0.5 - angle**2 / 24.0, (1.0 - np.cos(angle)) / (safe * safe))
    K = skew(w)
    return np.eye(3) + a[:, None, None] * K + b[:, None, None] * (K @ K)


def retract(T: np.ndarray, xi: np.ndarray) -> np.ndarray:
    """``T * Exp(xi)`` (decoupled): rotation ``R Exp(omega)``, translation ``t + R v``."""
    out = np.array(T, dtype=float)
    out[:3, :3] = T[:3, :3] @ so3_exp(xi[:3])
    out[:3, 3] = T[:3, 3] + T[:3, :3] @ xi[3:6]
    return out


def local(T_hat: np.ndarray, T: np.ndarray) -> np.ndarray:
    """Inverse of :func:`retract`: the ``xi`` with ``retract(T_hat, xi) == T``."""
    R_hat = T_hat[:3, :3]
    return np.concatenate([so3_log(R_hat.T @ T[:3, :3]), R_hat.T @ (T[:3, 3] - T_hat[:3, 3])])


def adjoint(T: np.ndarray) -> np.ndarray:
    """6x6 adjoint of ``T`` for [rotation, translation] twists (as gtsam's ``Pose3.AdjointMap``)."""
    R, t = T[:3, :3], T[:3, 3]
    A = np.zeros((6, 6))
    A[:3, :3] = R
    A[3:, 3:] = R
    A[3:, :3] = skew(t) @ R
    return A


def scale_increment(T: np.ndarray, fraction: float) -> np.ndarray:
    """The part ``fraction`` (0..1) of a relative motion: rotation by the scaled angle, translation scaled."""
    out = np.eye(4)
    out[:3, :3] = so3_exp(fraction * so3_log(T[:3, :3]))
    out[:3, 3] = fraction * T[:3, 3]
    return out


def compose_increments(U: np.ndarray, Q: np.ndarray, part: np.ndarray, Q_part: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The motion ``U`` then ``part``, and its 6x6 covariance (right perturbation, [rot, trans]):
    ``Q`` carried through ``part`` plus ``Q_part``."""
    A = adjoint(invert(part))
    return U @ part, A @ Q @ A.T + Q_part
