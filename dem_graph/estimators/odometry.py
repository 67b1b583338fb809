"""Wheel odometry between two arbitrary times, for every estimator's prediction.

Odometry arrives as increments ``T_prev_curr`` over ``[t_prev_s, t_s]`` with a 6x6 covariance
([rot, trans], right perturbation). :class:`OdometryIntegrator` composes the part of them that
falls between the last time asked and a new one; an increment cut by that time contributes its
share (rotation angle and translation scaled, covariance scaled), and the rest is kept for the
next call. A time past the last increment is extrapolated at the last increment's rate.

A time no increment covers between two increments (a dropped message, or an increment the dataset
reader skipped as beyond the vehicle's motion) is bridged the same way: at the last increment's
rate (constant velocity), with at least that increment's whole covariance. So a missing increment
leaves no hole in the motion.
"""

from __future__ import annotations

import numpy as np

from dem_graph.datasets.events import Odometry
from dem_graph.geometry.lie import compose_increments, scale_increment

_GAP_S = 1e-9  # an uncovered time shorter than this is rounding, not a gap


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
                if lo - covered > _GAP_S:
                    U, Q = self._at_last_rate(U, Q, lo - covered)
                f = (hi - lo) / span
                part = scale_increment(e.T_prev_curr, f) if f < 1.0 - 1e-9 else e.T_prev_curr
                U, Q = compose_increments(U, Q, part, e.covariance * f)
                covered = hi
                self._last = (e.T_prev_curr, e.covariance, span)
            if e.t_s > b:
                keep.append(e)
        if covered < b:
            U, Q = self._at_last_rate(U, Q, b - covered)
        self._events = keep
        self._cursor_s = b
        if not np.any(Q):
            Q = np.eye(6) * 1e-6
        return U, Q

    def _at_last_rate(self, U: np.ndarray, Q: np.ndarray, duration_s: float) -> tuple[np.ndarray, np.ndarray]:
        """``(U, Q)`` followed by ``duration_s`` at the last increment's rate, with at least its whole
        covariance; unchanged before the first increment."""
        if self._last is None:
            return U, Q
        T_rate, cov_rate, span = self._last
        f = duration_s / span
        return compose_increments(U, Q, scale_increment(T_rate, f), cov_rate * max(f, 1.0))

