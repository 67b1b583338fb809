"""The online graph: keyframe poses and map points in gtsam's incremental fixed-lag smoother (iSAM2).

Variables are ``X(k)``, the body pose ``T_world_body`` of keyframe k, and ``L(j)``, the world
position of landmark ``j`` (metres). Each variable carries a timestamp: a keyframe its time, a point
the time of the last keyframe that observed it. Whatever is older than ``lag_s`` behind the newest
keyframe is marginalised out (its information stays as a linear factor on what remains), so the
cost of an update follows the window, not the length of the run.

The latest estimate of every variable ever in the window is kept (:attr:`poses`, :attr:`points`):
a marginalised variable keeps the value it had when it left.
"""

from __future__ import annotations

import gtsam
import numpy as np
from gtsam.symbol_shorthand import L, X

from dem_graph.errors import DemGraphError, one_line


class GraphUpdateError(DemGraphError):
    """An iSAM2 update failed (an indeterminate system, say); the smoother's state is unusable."""


class KeyframeGraph:
    def __init__(self, T_world_body_0: np.ndarray, P0: np.ndarray, t0_s: float, lag_s: float, relinearize_threshold: float = 0.01, relinearize_skip: int = 1):
        self._params = gtsam.ISAM2Params()
        self._params.setRelinearizeThreshold(relinearize_threshold)
        self._params.relinearizeSkip = relinearize_skip
        self.lag_s = float(lag_s)
        self.smoother = gtsam.IncrementalFixedLagSmoother(self.lag_s, self._params)
        self.poses: dict[int, np.ndarray] = {}  # keyframe index -> T_world_body, latest estimate
        self.points: dict[int, np.ndarray] = {}  # landmark -> X_world, latest estimate
        self.keyframe_t_s: list[float] = []
        self._in_window: set[int] = set()  # landmarks whose variable is still in the smoother
        self._clear_pending()
        k = self.add_keyframe(t0_s, T_world_body_0)
        self._prior_on_pose(k, T_world_body_0, P0)
        self.update()

    # --- building the next update -----------------------------------------------------------
    @property
    def last_keyframe(self) -> int:
        return len(self.keyframe_t_s) - 1

    def add_keyframe(self, t_s: float, T_world_body_guess: np.ndarray) -> int:
        """A new keyframe pose variable at ``t_s``, starting from the guess; returns its index."""
        if self.keyframe_t_s and t_s <= self.keyframe_t_s[-1]:
            raise DemGraphError(f"keyframe times must increase: {t_s} after {self.keyframe_t_s[-1]}")
        k = len(self.keyframe_t_s)
        self.keyframe_t_s.append(float(t_s))
        self._new_values.insert(X(k), gtsam.Pose3(np.asarray(T_world_body_guess, dtype=float)))
        self._stamps.insert((X(k), float(t_s)))
        return k

    def add_point(self, landmark: int, X_world_guess: np.ndarray) -> None:
        """A new landmark variable, stamped with the newest keyframe's time."""
        self._new_values.insert(L(landmark), gtsam.Point3(*np.asarray(X_world_guess, dtype=float)))
        self._stamps.insert((L(landmark), self.keyframe_t_s[-1]))
        self.points[int(landmark)] = np.array(X_world_guess, dtype=float)
        self._in_window.add(int(landmark))

    def observed(self, landmark: int) -> None:
        """Stamp a landmark with the newest keyframe's time (it was measured there)."""
        self._stamps.insert((L(landmark), self.keyframe_t_s[-1]))

    def add_factor(self, factor: gtsam.NonlinearFactor) -> None:
        self._new_factors.add(factor)

    def in_window(self, landmark: int) -> bool:
        return int(landmark) in self._in_window

    def _clear_pending(self) -> None:
        self._new_factors = gtsam.NonlinearFactorGraph()
        self._new_values = gtsam.Values()
        self._stamps = gtsam.FixedLagSmootherKeyTimestampMap()

    def _prior_on_pose(self, k: int, T_world_body: np.ndarray, P: np.ndarray) -> None:
        T = gtsam.Pose3(np.asarray(T_world_body, dtype=float))
        self.add_factor(gtsam.PriorFactorPose3(X(k), T, gtsam.noiseModel.Gaussian.Covariance(np.asarray(P, dtype=float))))

    # --- solving ----------------------------------------------------------------------------
    def update(self) -> None:
        """One iSAM2 update with what was added since the last one; refreshes the estimates."""
        try:
            self.smoother.update(self._new_factors, self._new_values, self._stamps)
        except RuntimeError as exc:  # gtsam reports an indeterminate system or a missing key this way
            text = one_line(exc)  # with the variable gtsam names
            raise GraphUpdateError(f"the graph update at keyframe {self.last_keyframe} (t = {self.keyframe_t_s[-1]:.3f} s) failed: {text}") from None
        finally:
            self._clear_pending()
        values = self.smoother.calculateEstimate()
        in_window = set()
        for key in values.keys():
            sym = gtsam.Symbol(key)
            if sym.chr() == ord("x"):
                self.poses[sym.index()] = values.atPose3(key).matrix()
            else:
                self.points[sym.index()] = values.atPoint3(key)
                in_window.add(sym.index())
        self._in_window = in_window

    def restart(self, T_world_body: np.ndarray, P: np.ndarray, point_priors: dict[int, tuple[np.ndarray, np.ndarray]]) -> None:
        """Start a new smoother from the newest keyframe after a failed update: its pose and the
        given points (landmark -> (X_world, 3x3 covariance)) enter with priors at their estimates;
        what the failed update held is dropped. Keyframe numbering and kept estimates continue."""
        self.smoother = gtsam.IncrementalFixedLagSmoother(self.lag_s, self._params)
        self._clear_pending()
        k = self.last_keyframe
        self._new_values.insert(X(k), gtsam.Pose3(np.asarray(T_world_body, dtype=float)))
        self._stamps.insert((X(k), self.keyframe_t_s[-1]))
        self._prior_on_pose(k, T_world_body, P)
        for lm, (X_world, Sigma) in point_priors.items():
            self.add_point(lm, X_world)
            self.add_factor(gtsam.PriorFactorPoint3(L(lm), gtsam.Point3(*X_world), gtsam.noiseModel.Gaussian.Covariance(np.asarray(Sigma, dtype=float))))
        self.update()

    def pose_covariance(self, k: int) -> np.ndarray:
        """Marginal covariance of keyframe ``k``'s pose (6x6, [rotation, translation], right perturbation)."""
        return np.asarray(self.smoother.marginalCovariance(X(k)))


__all__ = ["GraphUpdateError", "KeyframeGraph"]
