"""The odometry-only baseline: every frame's pose is the wheel odometry integrated from the start,
with its growing covariance; no camera, no point. Run beside the estimators (``dem-graph compare``
adds it when the log has odometry), it shows what the camera and the laser add to the trajectory
and, through the DEM fused from its poses, to the map."""

from __future__ import annotations

import time

import numpy as np

from dem_graph.datasets.events import CameraFrame
from dem_graph.errors import DemGraphError
from dem_graph.estimators.base import EstimatorResult, FrameDrivenEstimator, FrameRecord
from dem_graph.estimators.settings import MotionConfig
from dem_graph.geometry.lie import compose_increments
from dem_graph.geometry.rig import SensorRig

ODOMETRY_BASELINE = "odometry"


class OdometryOnly(FrameDrivenEstimator):
    """Dead reckoning on the odometry; feed it events in time order."""

    name = ODOMETRY_BASELINE

    def __init__(self, rig: SensorRig, T_world_body_initial: np.ndarray, t_start_s: float, has_odometry: bool, motion: MotionConfig | None = None):
        motion = motion or MotionConfig()
        if not motion.uses_odometry(has_odometry):
            raise DemGraphError("the odometry baseline needs a log with odometry (and motion.model auto or odometry): this run has none")
        super().__init__(motion, has_odometry, t_start_s)
        self.rig = rig
        self._T = np.array(T_world_body_initial, dtype=float)
        self._P = np.eye(6) * motion.initial_sigma_pose**2

    def _process(self, event: CameraFrame) -> FrameRecord:
        self._pending_frame = None
        t0 = time.perf_counter()
        _, increment = self._motion.advance(event.t_s)
        U, Q = increment
        self._T, self._P = compose_increments(self._T, self._P, U, Q)
        elapsed = time.perf_counter() - t0
        record = FrameRecord(event.t_s, self._T.copy(), self._P.copy(), 0, 0, {"prediction": elapsed, "total": elapsed})
        self._frames.append(record)
        return record

    def result(self) -> EstimatorResult:
        return EstimatorResult(self.name, list(self._frames))


__all__ = ["ODOMETRY_BASELINE", "OdometryOnly"]
