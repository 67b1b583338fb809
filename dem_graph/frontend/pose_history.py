"""Recent estimated poses, interpolated at any time in between by a spline (the paper, III-D).

The laser is not synchronized with the camera: a scan's pose lies between two camera poses. As in
the paper, the pose at the scan's time comes from a spline through the recent pose history: one
cubic spline (scipy's ``CubicSpline``) through the last few estimated poses, of the position and of
the rotation as a vector in the tangent space of the newest pose (``R = R_newest Exp(r(t))``).

The window spans a fraction of a second and a few degrees of turn, where the tangent space costs
nothing in accuracy. It replaced scipy's ``RotationSpline``, which is five times dearer (a spline is
built for every scan) and, with its natural end conditions, about 40 times further from the truth in the
newest interval, where the scans fall (tests/test_pose_history.py).
"""

from __future__ import annotations

from collections import deque

import numpy as np
from scipy.interpolate import CubicSpline

from dem_graph.geometry.lie import so3_exp, so3_log
from dem_graph.geometry.se3 import make_pose

GAP_FACTOR = 4.0  # an interval this many times the median spacing of the history is a gap (PoseHistory.at)


class PoseHistory:
    def __init__(self, window: int = 6):
        self._t: deque[float] = deque(maxlen=window)
        self._T: deque[np.ndarray] = deque(maxlen=window)
        self._spline: CubicSpline | None = None  # [rotation vector, position] against time; built once per history state

    def append(self, t_s: float, T_world_body: np.ndarray) -> None:
        """Add the pose at ``t_s``; a pose at the latest time replaces it (a re-estimate)."""
        self._spline = None
        if self._t and t_s <= self._t[-1]:
            if t_s == self._t[-1]:
                self._T[-1] = np.array(T_world_body, dtype=float)
                return
            raise ValueError("pose history times must increase")
        self._t.append(float(t_s))
        self._T.append(np.array(T_world_body, dtype=float))

    def correct(self, T_correction: np.ndarray) -> None:
        """Left-multiply every stored pose by ``T_correction`` (a world-frame re-anchoring, as when
        a smoother moves the newest pose: the recent poses move with it and the spline stays smooth)."""
        C = np.asarray(T_correction, dtype=float)
        self._spline = None
        for i in range(len(self._T)):
            self._T[i] = C @ self._T[i]

    def __len__(self) -> int:
        return len(self._t)

    def _long_interval(self, t_s: float) -> int | None:
        """The index of the interval holding ``t_s`` when it is more than ``GAP_FACTOR`` times the
        history's median spacing (a camera gap): a cubic through such uneven knots swings far off the
        path inside it, so it is interpolated linearly (rotation slerp, linear translation)."""
        t = self._t
        if len(t) < 3 or not t[0] <= t_s <= t[-1]:
            return None
        i = min(int(np.searchsorted(t, t_s, side="right")) - 1, len(t) - 2)
        spacing = np.diff(np.asarray(t, dtype=float))
        return i if spacing[i] > GAP_FACTOR * float(np.median(spacing)) else None

    def at(self, t_s: float) -> np.ndarray:
        """``T_world_body`` at ``t_s``: spline inside the history's span, linear just beyond it."""
        t = self._t
        if len(t) == 1:
            return self._T[0].copy()
        i_gap = self._long_interval(t_s)
        if len(t) == 2 or t_s < t[0] or t_s > t[-1] or i_gap is not None:
            i = i_gap if i_gap is not None else 0 if t_s < t[0] else len(t) - 2
            T0, T1 = self._T[i], self._T[i + 1]
            a = (t_s - t[i]) / (t[i + 1] - t[i])
            R = T0[:3, :3] @ so3_exp(a * so3_log(T0[:3, :3].T @ T1[:3, :3]))
            p = T0[:3, 3] + a * (T1[:3, 3] - T0[:3, 3])
            return make_pose(R, p)
        R_base = self._T[-1][:3, :3]
        if self._spline is None:  # several scans may read the same history
            T = np.array(self._T)
            r = np.array([so3_log(R_base.T @ Ti[:3, :3]) for Ti in T])
            self._spline = CubicSpline(np.array(t), np.concatenate([r, T[:, :3, 3]], axis=1), axis=0)
        y = self._spline(t_s)
        return make_pose(R_base @ so3_exp(y[:3]), y[3:])
