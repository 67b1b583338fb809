"""A time-stamped trajectory, queryable at any time inside its span."""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from dem_graph.errors import DemGraphError
from dem_graph.geometry.se3 import make_pose, matrix_from_quat_xyzw, quat_xyzw_from_matrix


@dataclass(frozen=True)
class Trajectory:
    """Poses ``T_world_body`` at increasing times.

    Stored as positions and quaternions ``[qx, qy, qz, qw]`` so that a TUM file round-trips exactly.
    Between samples, :meth:`at` interpolates the rotation by slerp and the translation linearly.
    """

    t_s: np.ndarray  # (N,)
    positions_xyz: np.ndarray  # (N, 3) metres
    orientations_quat_xyzw: np.ndarray  # (N, 4)

    def __post_init__(self):
        t = np.asarray(self.t_s, dtype=float)
        p = np.asarray(self.positions_xyz, dtype=float)
        q = np.asarray(self.orientations_quat_xyzw, dtype=float)
        if t.ndim != 1 or p.shape != (len(t), 3) or q.shape != (len(t), 4):
            raise DemGraphError(
                f"trajectory arrays have inconsistent shapes: t {t.shape}, positions {p.shape}, quaternions {q.shape}"
            )
        if len(t) == 0:
            raise DemGraphError("trajectory is empty")
        if not (np.all(np.isfinite(t)) and np.all(np.isfinite(p)) and np.all(np.isfinite(q))):
            raise DemGraphError("trajectory contains NaN or infinite values")
        if len(t) > 1 and np.any(np.diff(t) <= 0):
            i = int(np.argmax(np.diff(t) <= 0))
            raise DemGraphError(f"trajectory times are not strictly increasing at index {i + 1} (t={t[i + 1]!r})")
        norms = np.linalg.norm(q, axis=1)
        if np.any(np.abs(norms - 1.0) > 1e-3):
            raise DemGraphError("trajectory quaternions are not unit length")
        object.__setattr__(self, "t_s", t)
        object.__setattr__(self, "positions_xyz", p)
        object.__setattr__(self, "orientations_quat_xyzw", q)

    @classmethod
    def from_poses(cls, t_s: np.ndarray, T_world_body: np.ndarray) -> Trajectory:
        T = np.asarray(T_world_body, dtype=float)
        return cls(np.asarray(t_s, dtype=float), T[:, :3, 3].copy(), quat_xyzw_from_matrix(T[:, :3, :3]))

    def __len__(self) -> int:
        return len(self.t_s)

    @property
    def poses_se3(self) -> np.ndarray:
        """(N, 4, 4) ``T_world_body`` at the sample times."""
        return make_pose(matrix_from_quat_xyzw(self.orientations_quat_xyzw), self.positions_xyz)

    @property
    def duration_s(self) -> float:
        return float(self.t_s[-1] - self.t_s[0])

    @property
    def path_length_m(self) -> float:
        return float(np.sum(np.linalg.norm(np.diff(self.positions_xyz, axis=0), axis=1)))

    def at(self, t_s) -> np.ndarray:
        """``T_world_body`` at time(s) ``t_s``: (4,4) for a scalar, (M,4,4) for an array.

        Raises :class:`DemGraphError` for a time outside the trajectory's span.
        """
        tq = np.atleast_1d(np.asarray(t_s, dtype=float))
        lo, hi = self.t_s[0], self.t_s[-1]
        eps = 1e-9 * max(1.0, abs(hi))
        if np.any(tq < lo - eps) or np.any(tq > hi + eps):
            raise DemGraphError(f"time outside the trajectory span [{lo:.6f}, {hi:.6f}] s")
        tq = np.clip(tq, lo, hi)
        if len(self.t_s) == 1:
            T = np.repeat(self.poses_se3, len(tq), axis=0)
        else:
            rot = self._slerp(tq)
            pos = np.stack([np.interp(tq, self.t_s, self.positions_xyz[:, k]) for k in range(3)], axis=1)
            T = make_pose(rot.as_matrix(), pos)
        return T[0] if np.ndim(t_s) == 0 else T

    @cached_property
    def _slerp(self) -> Slerp:
        """The rotation interpolator, built once (it costs a few milliseconds per thousand poses)."""
        return Slerp(self.t_s, Rotation.from_quat(self.orientations_quat_xyzw))

    def slice(self, t_start_s: float, t_end_s: float) -> Trajectory:
        """The samples with ``t_start_s <= t <= t_end_s``."""
        keep = (self.t_s >= t_start_s) & (self.t_s <= t_end_s)
        return Trajectory(self.t_s[keep], self.positions_xyz[keep], self.orientations_quat_xyzw[keep])
