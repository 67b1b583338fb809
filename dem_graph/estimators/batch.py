"""Full smoothing of a whole log (``--estimator isam2-batch``).

The online pass (:class:`~dem_graph.estimators.isam2.Isam2Slam` with ``batch: true``) does the data
association and records every measurement it used (:class:`MeasurementLog`). Here one graph holds
them all: a pose per frame, the motion between consecutive frames, a projection factor for every
inlier observation of every frame, each point's seed factors, and the links between the landmarks
of one track (a patch refresh starts a new one). Levenberg-Marquardt starts from the
online pass's smoothed estimates.

Pose variables: ``X(0)`` is the start pose (with the run's prior), ``X(f + 1)`` frame ``f``'s.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, replace

import gtsam
import numpy as np
from gtsam.symbol_shorthand import L, X

from dem_graph.errors import DemGraphError, one_line
from dem_graph.estimators.base import ONLINE_TRAJECTORY, EstimatorResult
from dem_graph.estimators.graph_factors import calibration, link_factor, odometry_factor, projection_factor, seed_factors
from dem_graph.estimators.measurement_log import MeasurementLog
from dem_graph.geometry.rig import SensorRig

log = logging.getLogger(__name__)


@dataclass
class BatchResult:
    poses: np.ndarray  # (n_frames, 4, 4) T_world_body of every frame
    points: dict[int, np.ndarray]  # landmark -> X_world
    iterations: int
    error_initial: float
    error_final: float
    build_s: float
    optimize_s: float
    n_factors: int

    def apply_to(self, res: EstimatorResult, landmark_of: dict[int, int]) -> EstimatorResult:
        """The online result with the smoothed poses and points (the online poses kept as :data:`ONLINE_TRAJECTORY`)."""
        online = np.array([f.T_world_body for f in res.frames])
        res.frames = [replace(f, T_world_body=self.poses[i]) for i, f in enumerate(res.frames)]
        res.extra_poses[ONLINE_TRAJECTORY] = online
        res.points.xyz = [self.points.get(landmark_of.get(pid, -1), xyz) for pid, xyz in zip(res.points.point_id, res.points.xyz)]
        res.counters["batch_iterations"] = self.iterations
        res.counters["batch_factors"] = self.n_factors
        res.counters["batch_build_ms"] = round(1000 * self.build_s)
        res.counters["batch_optimize_ms"] = round(1000 * self.optimize_s)
        return res


def build_graph(mlog: MeasurementLog, rig: SensorRig, T0: np.ndarray, P0: np.ndarray, sigma_px: float, sigma_seed_px: float, robust: bool) -> gtsam.NonlinearFactorGraph:
    K = calibration(rig.camera_model)
    T_body_cam = rig.T_body_cam
    graph = gtsam.NonlinearFactorGraph()
    graph.add(gtsam.PriorFactorPose3(X(0), gtsam.Pose3(np.asarray(T0, dtype=float)), gtsam.noiseModel.Gaussian.Covariance(np.asarray(P0, dtype=float))))
    for f in range(mlog.n_frames):
        graph.add(odometry_factor(X(f), X(f + 1), mlog.T_prev_curr[f], mlog.motion_covariance[f]))
    for before, after, sigma_m in mlog.links:
        graph.add(link_factor(L(before), L(after), sigma_m))
    for f, lm, seed in zip(mlog.seed_frame, mlog.seed_landmark, mlog.seeds):
        for factor in seed_factors(X(f + 1), L(lm), seed.kind, seed.p_body, seed.Sigma_body, rig.camera_model, K, T_body_cam, sigma_seed_px):
            graph.add(factor)
    frames, landmarks, uv = mlog.observations()
    for f, lm, z in zip(frames.tolist(), landmarks.tolist(), uv):
        graph.add(projection_factor(X(f + 1), L(lm), z, sigma_px, K, T_body_cam, robust=robust))
    return graph


def smooth_batch(
    mlog: MeasurementLog,
    rig: SensorRig,
    T0: np.ndarray,
    P0: np.ndarray,
    poses_init: np.ndarray,
    points_init: dict[int, np.ndarray],
    sigma_px: float,
    sigma_seed_px: float,
    robust: bool = True,
    max_iterations: int = 10,
    relative_error_tol: float = 1e-3,
) -> BatchResult:
    """Smooth the whole log from the initial estimates (``poses_init``: every frame's pose)."""
    t0 = time.perf_counter()
    graph = build_graph(mlog, rig, T0, P0, sigma_px, sigma_seed_px, robust)
    values = gtsam.Values()
    values.insert(X(0), gtsam.Pose3(np.asarray(T0, dtype=float)))
    for f in range(mlog.n_frames):
        values.insert(X(f + 1), gtsam.Pose3(poses_init[f]))
    landmarks = set(mlog.seed_landmark) | {after for _, after, _ in mlog.links}
    for lm in landmarks:
        values.insert(L(lm), gtsam.Point3(*points_init[lm]))
    t1 = time.perf_counter()
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(max_iterations)
    params.setRelativeErrorTol(relative_error_tol)
    optimizer = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
    error_initial = optimizer.error()  # the optimiser evaluates it on construction
    try:
        out = optimizer.optimize()
    except RuntimeError as exc:
        raise DemGraphError(f"the batch optimisation failed: {one_line(exc)}") from None
    t2 = time.perf_counter()
    result = BatchResult(
        poses=np.array([out.atPose3(X(f + 1)).matrix() for f in range(mlog.n_frames)]),
        points={lm: out.atPoint3(L(lm)) for lm in landmarks},
        iterations=optimizer.iterations(),
        error_initial=float(error_initial),
        error_final=float(optimizer.error()),
        build_s=t1 - t0,
        optimize_s=t2 - t1,
        n_factors=graph.size(),
    )
    log.info(
        "batch: %d factors, built in %.1f s; %d iterations in %.1f s, error %.1f -> %.1f",
        result.n_factors, result.build_s, result.iterations, result.optimize_s, result.error_initial, result.error_final,
    )
    return result


__all__ = ["BatchResult", "build_graph", "smooth_batch"]
