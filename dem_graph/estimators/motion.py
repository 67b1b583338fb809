"""The prediction between frames, as far as the estimators share it.

Both take the odometry increment since the previous frame when the run uses odometry
(:meth:`~dem_graph.estimators.settings.MotionConfig.uses_odometry`), and otherwise a
constant-velocity model. They keep the velocity differently: the EKF in its filter state (it
estimates it), the graph estimator outside (from its last two poses, :func:`constant_velocity_increment`).
"""

from __future__ import annotations

import numpy as np

from dem_graph.datasets.events import Odometry
from dem_graph.estimators.odometry import OdometryIntegrator
from dem_graph.estimators.settings import MotionConfig
from dem_graph.geometry.lie import retract


class FrameMotion:
    """Where a frame's motion comes from, and the time the estimate is at: the odometry increments
    since the previous frame when the run uses odometry, else none (the estimator's constant-velocity
    model then predicts, with the white acceleration noise ``sigma_acc``)."""

    def __init__(self, config: MotionConfig, has_odometry: bool, t_start_s: float):
        self.uses_odometry = config.uses_odometry(has_odometry)
        self.wait_for_odometry = config.wait_for_odometry
        self.t_s = float(t_start_s)
        self._odometry = OdometryIntegrator(self.t_s)
        # [angular rad/s^2 x3, linear m/s^2 x3] per sqrt(Hz)
        self.sigma_acc = np.array([config.sigma_angular_acc_radps2] * 3 + [config.sigma_linear_acc_mps2] * 3)

    def add_odometry(self, event: Odometry) -> None:
        self._odometry.add(event)

    def holds(self, t_s: float) -> bool:
        """A frame at ``t_s`` waits for the odometry covering it (instead of extrapolating)."""
        return self.uses_odometry and self.wait_for_odometry and not self._odometry.covers(t_s)

    def advance(self, t_s: float) -> tuple[float, tuple[np.ndarray, np.ndarray] | None]:
        """Move the estimate's time to ``t_s``: the time since the previous frame, seconds, and the
        odometry increment over it, ``(T_prev_curr, 6x6 covariance)``, or None under constant velocity."""
        dt = t_s - self.t_s
        increment = self._odometry.increment(t_s) if self.uses_odometry else None
        self.t_s = t_s
        return dt, increment


def constant_velocity_increment(v_body: np.ndarray, dt_s: float, sigma_acc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The motion ``T_prev_curr`` over ``dt_s`` at the body twist ``v_body`` ([angular, linear] per
    second) and its 6x6 covariance from white acceleration ``sigma_acc`` (right perturbation)."""
    U = retract(np.eye(4), v_body * dt_s)
    q = sigma_acc**2
    Q = np.diag(q * max(dt_s, 1e-3) ** 3) + np.eye(6) * 1e-10
    return U, Q


__all__ = ["FrameMotion", "constant_velocity_increment"]
