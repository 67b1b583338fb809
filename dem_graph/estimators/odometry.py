"""Wheel odometry between two arbitrary times, for every estimator's prediction.

Odometry arrives as increments ``T_prev_curr`` over ``[t_prev_s, t_s]`` with a 6x6 covariance
([rot, trans], right perturbation). :class:`OdometryIntegrator` composes the part of them that
falls between the last time asked and a new one; an increment cut by that time contributes its
share (rotation angle and translation scaled, covariance scaled), and the rest is kept for the
next call. A time past the last increment is extrapolated at the last increment's rate.
"""

from __future__ import annotations

import numpy as np

from dem_graph.datasets.events import Odometry
from dem_graph.geometry.lie import adjoint, scale_increment
from dem_graph.geometry.se3 import invert


class OdometryIntegrator:
    def __init__(self, t_start_s: float):
        self._events: list[Odometry] = []
        self._cursor_s = float(t_start_s)
        self._last: tuple[np.ndarray, np.ndarray, float] | None = None  # last increment, its covariance, its span

    def add(self, event: Odometry) -> None:
        self._events.append(event)

    def covers(self, t_s: float) -> bool:
        """Whether an increment ending at or after ``t_s`` has arrived."""
        return any(e.t_s >= t_s for e in self._events)

    def increment(self, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        """``(T_prev_curr, covariance)`` of the motion from the previous call's time to ``t_s``."""
        a, b = self._cursor_s, float(t_s)
        U, Q = np.eye(4), np.zeros((6, 6))
        covered = a
        keep = []
        for e in self._events:
            lo, hi = max(e.t_prev_s, covered), min(e.t_s, b)
            span = e.t_s - e.t_prev_s
            if hi > lo and span > 0:
                f = (hi - lo) / span
                part = scale_increment(e.T_prev_curr, f) if f < 1.0 - 1e-9 else e.T_prev_curr
                A = adjoint(invert(part))
                Q = A @ Q @ A.T + e.covariance * f
                U = U @ part
                covered = hi
                self._last = (e.T_prev_curr, e.covariance, span)
            if e.t_s > b:
                keep.append(e)
        if covered < b and self._last is not None:
            T_rate, cov_rate, span = self._last
            f = (b - covered) / span
            part = scale_increment(T_rate, f)
            A = adjoint(invert(part))
            Q = A @ Q @ A.T + cov_rate * max(f, 1.0)
            U = U @ part
        self._events = keep
        self._cursor_s = b
        if not np.any(Q):
            Q = np.eye(6) * 1e-6
        return U, Q
