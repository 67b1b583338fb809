"""What ``isam2-batch`` adds to the graph estimator's online pass: every measurement it used,
recorded frame by frame (a :class:`~dem_graph.estimators.measurement_log.MeasurementLog`), and the
whole log smoothed at the end (:func:`~dem_graph.estimators.batch.smooth_batch`) from the online
pass's smoothed estimates."""

from __future__ import annotations

import numpy as np

from dem_graph.estimators.batch import BatchResult, smooth_batch
from dem_graph.estimators.isam2_config import Isam2Config
from dem_graph.estimators.laser_ties import LaserTies
from dem_graph.estimators.measurement_log import MeasurementLog
from dem_graph.frontend.frontend import NewPoint
from dem_graph.geometry.rig import SensorRig


class BatchLog:
    """The measurement log of the online pass (``log``) and, after :meth:`smooth`, its smoothing (``result``)."""

    def __init__(self, config: Isam2Config, rig: SensorRig, T_world_body_0: np.ndarray, P0: np.ndarray):
        self.config = config
        self.rig = rig
        self._T0, self._P0 = T_world_body_0, P0  # the start pose and its prior
        self.log = MeasurementLog()
        self.result: BatchResult | None = None

    def add_frame(
        self, t_s: float, U: np.ndarray, Q: np.ndarray, landmarks: np.ndarray, uv_px: np.ndarray, split_old: np.ndarray,
        imu: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
    ) -> None:
        """A frame: the motion ``U`` from the previous frame (covariance ``Q``) and its inlier
        observations of ``landmarks`` (m,) at ``uv_px`` (m,2). ``split_old``: per observation, the
        landmark before a patch refresh in this frame, or -1. ``imu``: the IMU samples since the
        previous frame (times, rates, forces), when the run uses an IMU."""
        # a refreshed point's match is an observation of the landmark before (matched with the
        # old patch) and defines the one after
        both = split_old >= 0
        self.log.add_frame(t_s, U, Q, np.concatenate([landmarks, split_old[both]]), np.concatenate([uv_px, uv_px[both]]), imu)

    def add_seeds(self, frame: int, new: list[NewPoint], landmarks: np.ndarray) -> None:
        """The new points seeded at frame ``frame``, starting ``landmarks``."""
        self.log.add_seeds(frame, new, landmarks)

    def add_ties(self, ties: LaserTies) -> None:
        """Landmarks tied to the scans of their ground (:mod:`~dem_graph.estimators.laser_ties`), each in its frame."""
        self.log.add_ties(ties)

    def add_link(self, before: int, after: int) -> None:
        """A patch refresh: landmark ``after`` continues ``before``."""
        self.log.add_link(before, after, self.config.split_link_sigma_m)

    def smooth(self, poses: np.ndarray, points: dict[int, np.ndarray]) -> None:
        """Smooth the whole log from every frame's pose ``poses`` and the landmarks' ``points``."""
        c = self.config
        self.result = smooth_batch(
            # every frame's observation, with AR(1) errors: each carries (1 - rho) / (1 + rho) of an independent one's information
            self.log, self.rig, self._T0, self._P0, poses, points,
            c.frontend.sigma_px * np.sqrt((1 + c.track_correlation) / (1 - c.track_correlation)), c.frontend.camera_point_sigma_px,
            robust=c.robust, max_iterations=c.batch_max_iterations, relative_error_tol=c.batch_relative_error_tol,
            imu=self.rig.imu if c.motion.use_imu else None, sigma_v0_mps=c.motion.initial_sigma_speed_mps, marginals=c.batch_marginals,
        )  # fmt: skip


__all__ = ["BatchLog"]
