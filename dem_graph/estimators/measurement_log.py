"""Every measurement an online pass used, kept for smoothing the whole log afterwards (isam2-batch).

Per frame: its time, the motion from the previous frame (odometry or the motion model) with its
covariance, and the inlier observations (landmark and pixel). Per new point: the frame it was seeded
at, its landmark and its seed (kind, body-frame position and covariance). Per patch refresh: the
link from the landmark before to the one after. The laser's ties (a laser the camera does not see):
the frame each is measured in, its landmark, and the landmark's position and covariance there.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from dem_graph.estimators.laser_ties import LaserTies
from dem_graph.frontend.frontend import NewPoint


@dataclass
class MeasurementLog:
    t_s: list[float] = field(default_factory=list)
    T_prev_curr: list[np.ndarray] = field(default_factory=list)
    motion_covariance: list[np.ndarray] = field(default_factory=list)
    _obs_frame: list[np.ndarray] = field(default_factory=list)
    _obs_point: list[np.ndarray] = field(default_factory=list)
    _obs_uv: list[np.ndarray] = field(default_factory=list)
    seed_frame: list[int] = field(default_factory=list)
    seeds: list[NewPoint] = field(default_factory=list)
    seed_landmark: list[int] = field(default_factory=list)
    links: list[tuple[int, int, float]] = field(default_factory=list)  # (landmark before, after, sigma m)
    imu: list[tuple[np.ndarray, np.ndarray, np.ndarray] | None] = field(default_factory=list)  # per frame: the IMU samples since the frame before
    ties: list[LaserTies] = field(default_factory=list)  # the laser's ties to landmarks, each measured in a frame (LaserTies.frames)

    @property
    def n_frames(self) -> int:
        return len(self.t_s)

    def add_frame(
        self, t_s: float, T_prev_curr: np.ndarray, covariance: np.ndarray, landmarks: np.ndarray, uv_px: np.ndarray,
        imu: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
    ) -> None:
        """Frame ``n_frames``: the motion from the previous frame (from the start pose for the first),
        the pixels of the landmarks it observed, and the IMU samples since the previous frame (times,
        rates, forces) when there are."""
        f = self.n_frames
        self.t_s.append(float(t_s))
        self.T_prev_curr.append(np.array(T_prev_curr, dtype=float))
        self.motion_covariance.append(np.array(covariance, dtype=float))
        ids = np.asarray(landmarks, dtype=np.int64).reshape(-1)
        self._obs_frame.append(np.full(len(ids), f, dtype=np.int64))
        self._obs_point.append(ids)
        self._obs_uv.append(np.asarray(uv_px, dtype=float).reshape(-1, 2))
        self.imu.append(imu)

    def add_seeds(self, frame: int, new: list[NewPoint], landmarks) -> None:
        self.seed_frame.extend([int(frame)] * len(new))
        self.seeds.extend(new)
        self.seed_landmark.extend(int(x) for x in landmarks)

    def add_link(self, before: int, after: int, sigma_m: float) -> None:
        """Landmark ``after`` continues ``before`` (a patch refresh), within ``sigma_m`` of it."""
        self.links.append((int(before), int(after), float(sigma_m)))

    def add_ties(self, ties: LaserTies) -> None:
        self.ties.append(ties)

    def seed_arrays(self) -> tuple[np.ndarray, np.ndarray]:
        """Every seed's body-frame position (m,3) and covariance (m,3,3), in the seeds' order."""
        return np.array([s.p_body for s in self.seeds], dtype=float).reshape(-1, 3), np.array([s.Sigma_body for s in self.seeds], dtype=float).reshape(-1, 3, 3)

    def observations(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Frame index (N,), landmark (N,) and pixel (N,2) of every observation."""
        if not self._obs_frame:
            return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64), np.zeros((0, 2))
        return np.concatenate(self._obs_frame), np.concatenate(self._obs_point), np.concatenate(self._obs_uv)


__all__ = ["MeasurementLog"]
