"""Small SO(3)/SE(3) helpers for estimators, in gtsam's tangent order [rotation, translation].

Perturbations are on the right: ``T = T_hat * Exp(xi)``, ``xi = [omega, v]`` with ``v`` in the body
frame. :func:`retract` uses the decoupled form (``R Exp(omega)``, ``t + R v``), which agrees with
gtsam's ``Pose3.retract`` to first order.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation


def skew(w: np.ndarray) -> np.ndarray:
    """``skew(a) @ b == cross(a, b)``; (...,3) -> (...,3,3)."""
    w = np.asarray(w, dtype=float)
    S = np.zeros(w.shape[:-1] + (3, 3))
    S[..., 0, 1], S[..., 0, 2] = -w[..., 2], w[..., 1]
    S[..., 1, 0], S[..., 1, 2] = w[..., 2], -w[..., 0]
    S[..., 2, 0], S[..., 2, 1] = -w[..., 1], w[..., 0]
    return S


def so3_exp(w: np.ndarray) -> np.ndarray:
    return Rotation.from_rotvec(np.asarray(w, dtype=float)).as_matrix()


def so3_log(R: np.ndarray) -> np.ndarray:
    return Rotation.from_matrix(R).as_rotvec()


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
