"""Full smoothing of a whole log (``--estimator isam2-batch``).

The online pass (:class:`~dem_graph.estimators.isam2.Isam2Slam` with ``batch: true``) does the data
association and records every measurement it used (:class:`MeasurementLog`). Here one graph holds
them all: a pose per frame, the motion between consecutive frames, a projection factor for every
inlier observation of every frame, each point's seed factors, and the links between the landmarks
of one track (a patch refresh starts a new one). Levenberg-Marquardt starts from the
online pass's smoothed poses, after a first pass that fits the landmarks to them with every pose held.

That first pass is there because the two halves of the online estimate do not agree: the
landmarks are the graph's estimates from when each was last updated, the poses its latest
keyframe estimates, and a landmark seen long ago no longer projects where it was measured from
the poses as they ended up. On ``paper`` seed 6 the start's error was 4.3e6 over 244 000 factors
(2.4e6 of it in the seed factors, 0.4e6 in the links between a refreshed track's landmarks), and
Levenberg-Marquardt stopped after one iteration, the trajectory 3 m low at the end.

Pose variables: ``X(0)`` is the start pose (with the run's prior), ``X(f + 1)`` frame ``f``'s.
With an IMU, each frame whose samples were logged also has ``V(f + 1)`` (world velocity) and
``B(f + 1)`` (biases), tied to the frame before by a ``CombinedImuFactor``; where such a chain
starts, a prior holds the velocity (the online poses' own, within ``sigma_v0_mps``) and the biases
(zero, within the rig's spread at the start).

The batch's posterior: with ``marginals`` (``batch_marginals``), each frame's pose covariance is its
marginal in the final graph at the solution (:func:`pose_marginals`, ``gtsam.Marginals``), in gtsam's
tangent order [rotation, translation] of the right perturbation in the body frame, the package's
convention; :meth:`BatchResult.apply_to` puts it in the run's frames in place of the online pass's,
so the run's pose NEES is the batch's own. Where Cholesky's elimination finds the system
indeterminate, QR's gives them (counted as ``batch_marginals_by_qr``); where that fails too, a
warning says so and the frames keep the online pass's covariances (``batch_marginals_failed``).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, replace

import gtsam
import numpy as np
from gtsam.symbol_shorthand import B, L, V, X

from dem_graph.errors import DemGraphError, one_line
from dem_graph.estimators.base import ONLINE_TRAJECTORY, EstimatorResult
from dem_graph.estimators.batch_start import fit_landmarks
from dem_graph.estimators.graph_factors import (
    ProjectionFactors,
    calibration,
    level_factor,
    link_factor,
    odometry_factor,
    points_in_frame_factors,
    seeds_factors,
)
from dem_graph.estimators.imu_preintegration import bias_sigmas, preintegrate, preintegration_params
from dem_graph.estimators.measurement_log import MeasurementLog
from dem_graph.geometry.rig import ImuSpec, SensorRig

log = logging.getLogger(__name__)


@dataclass
class BatchResult:
    poses: np.ndarray  # (n_frames, 4, 4) T_world_body of every frame
    points: dict[int, np.ndarray]  # landmark -> X_world
    iterations: int
    refit_iterations: int  # of the first pass, the landmarks fitted to the start's poses
    error_initial: float
    error_refit: float  # after the first pass
    error_final: float
    build_s: float
    optimize_s: float
    n_factors: int
    # (n_frames, 6, 6) every frame's marginal pose covariance ([rot, trans], right perturbation);
    # None: not asked for, or gtsam could not (marginals_failed)
    pose_covariances: np.ndarray | None = None
    marginals_s: float = 0.0
    marginals_failed: bool = False
    marginals_by_qr: bool = False  # Cholesky found the system indeterminate and QR's elimination was tried (pose_marginals); with marginals_failed it refused too

    def apply_to(self, res: EstimatorResult, landmark_of: dict[int, int]) -> EstimatorResult:
        """The online result with the smoothed poses and points (the online poses kept as
        :data:`ONLINE_TRAJECTORY`), and the batch's pose covariances when it has them (else the
        online pass's stay)."""
        online = np.array([f.T_world_body for f in res.frames])
        P = self.pose_covariances
        res.frames = [replace(f, T_world_body=self.poses[i], pose_covariance=f.pose_covariance if P is None else P[i]) for i, f in enumerate(res.frames)]
        res.extra_poses[ONLINE_TRAJECTORY] = online
        res.points.xyz = [self.points.get(landmark_of.get(pid, -1), xyz) for pid, xyz in zip(res.points.point_id, res.points.xyz)]
        res.counters["batch_iterations"] = self.iterations
        res.counters["batch_landmark_iterations"] = self.refit_iterations
        res.counters["batch_factors"] = self.n_factors
        res.counters["batch_build_ms"] = round(1000 * self.build_s)
        res.counters["batch_optimize_ms"] = round(1000 * self.optimize_s)
        if P is not None:
            res.counters["batch_marginals_ms"] = round(1000 * self.marginals_s)
        if self.marginals_failed:
            res.counters["batch_marginals_failed"] = 1
        if self.marginals_by_qr:
            res.counters["batch_marginals_by_qr"] = 1
        return res


def imu_chain(mlog: MeasurementLog) -> list[int]:
    """The frames ``f`` whose IMU factor from frame ``f - 1`` goes into the graph (every frame with
    logged samples but the first)."""
    return [f for f in range(1, mlog.n_frames) if mlog.imu and mlog.imu[f] is not None and mlog.t_s[f] > mlog.t_s[f - 1]]


def add_imu_factors(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, mlog: MeasurementLog, spec: ImuSpec, poses: np.ndarray, sigma_v0_mps: float) -> int:
    """The IMU's factors between consecutive frames, their velocity and bias variables started at
    the poses' finite-difference velocities and zero biases, and the priors where a chain starts;
    returns how many factors."""
    params = preintegration_params(spec)
    zero = gtsam.imuBias.ConstantBias()
    t = np.asarray(mlog.t_s)
    v_world = np.gradient(poses[:, :3, 3], t, axis=0) if len(t) > 1 else np.zeros((len(t), 3))
    sigma_bias = bias_sigmas(spec)
    n = 0
    for f in imu_chain(mlog):
        for g in (f - 1, f):
            if not values.exists(V(g + 1)):
                values.insert(V(g + 1), v_world[g])
                values.insert(B(g + 1), zero)
                if g == f - 1:  # a chain starts here
                    graph.add(gtsam.PriorFactorVector(V(g + 1), v_world[g], gtsam.noiseModel.Isotropic.Sigma(3, float(sigma_v0_mps))))
                    graph.add(gtsam.PriorFactorConstantBias(B(g + 1), zero, gtsam.noiseModel.Diagonal.Sigmas(sigma_bias)))
        ts, gyro, accel = mlog.imu[f]
        pim = preintegrate(params, ts, gyro, accel, float(t[f - 1]), float(t[f]), zero)
        graph.add(gtsam.CombinedImuFactor(X(f), V(f), X(f + 1), V(f + 1), B(f), B(f + 1), pim))
        n += 1
    return n


def build_graph(mlog: MeasurementLog, rig: SensorRig, T0: np.ndarray, P0: np.ndarray, sigma_px: float, sigma_seed_px: float, robust: bool) -> gtsam.NonlinearFactorGraph:
    K = calibration(rig.camera_model)
    T_body_cam = rig.T_body_cam
    graph = gtsam.NonlinearFactorGraph()
    graph.add(gtsam.PriorFactorPose3(X(0), gtsam.Pose3(np.asarray(T0, dtype=float)), gtsam.noiseModel.Gaussian.Covariance(np.asarray(P0, dtype=float))))
    for f in range(mlog.n_frames):
        graph.add(odometry_factor(X(f), X(f + 1), mlog.T_prev_curr[f], mlog.motion_covariance[f]))
    for before, after, sigma_m in mlog.links:
        graph.add(link_factor(L(before), L(after), sigma_m))
    if mlog.seeds:
        p_body, Sigma_body = mlog.seed_arrays()
        keys = ([X(f + 1) for f in mlog.seed_frame], [L(lm) for lm in mlog.seed_landmark], [seed.kind for seed in mlog.seeds])
        for factor in seeds_factors(*keys, p_body, Sigma_body, rig.camera_model, K, T_body_cam, sigma_seed_px):
            graph.add(factor)
    for ties in mlog.ties:  # the laser's ties (a laser the camera does not see), each in the frame of its scans
        if ties.pin_start is not None:  # the rig's mount agrees with the laser's ground: the start pose's own prior back
            graph.add(gtsam.PriorFactorPose3(X(0), gtsam.Pose3(np.asarray(T0, dtype=float)), gtsam.noiseModel.Gaussian.Covariance(ties.pin_start)))
        pose_keys, point_keys = [X(int(f) + 1) for f in ties.frames], [L(int(lm)) for lm in ties.landmarks]
        for factor in points_in_frame_factors(pose_keys, point_keys, ties.p_frame, ties.Sigma_frame):
            graph.add(factor)
        for lm, mean, Sigma in zip(ties.level_landmarks.tolist(), ties.level_mean, ties.level_Sigma):
            graph.add(level_factor(L(lm), mean, Sigma))
    frames, landmarks, uv = mlog.observations()
    projection = ProjectionFactors(K, T_body_cam, robust=robust)
    for f, lm, z in zip(frames.tolist(), landmarks.tolist(), uv):
        graph.add(projection(X(f + 1), L(lm), z, sigma_px))
    return graph


def _fit_landmarks_to_poses(
    mlog: MeasurementLog, rig: SensorRig, T0: np.ndarray, poses: np.ndarray, points: dict[int, np.ndarray], landmarks: list[int], sigma_px: float, robust: bool
) -> tuple[dict[int, np.ndarray], int]:
    """Each landmark moved to its best fit to the start's poses, held (:func:`~dem_graph.estimators.batch_start.fit_landmarks`),
    and the iterations it took."""
    row = {lm: i for i, lm in enumerate(landmarks)}
    T_world_body = np.concatenate([np.asarray(T0, dtype=float)[None], np.asarray(poses, dtype=float)])  # X(0), then X(f + 1)
    frames, obs_landmarks, uv = mlog.observations()
    links = np.array([(row[a], row[b]) for a, b, _ in mlog.links], dtype=np.int64).reshape(-1, 2)
    p_body, Sigma_body = mlog.seed_arrays()
    prior_pose, prior_landmark = np.asarray(mlog.seed_frame, dtype=np.int64) + 1, np.array([row[lm] for lm in mlog.seed_landmark], dtype=np.int64)
    if mlog.ties:  # the laser's ties are priors of the same form (a landmark in a pose's frame); the level ones in the start's (X(0))
        prior_pose, prior_landmark, p_body, Sigma_body = _with_ties(mlog, T0, row, prior_pose, prior_landmark, p_body, Sigma_body)
    X, iterations = fit_landmarks(
        np.array([points[lm] for lm in landmarks], dtype=float).reshape(-1, 3), T_world_body,
        frames + 1, np.array([row[lm] for lm in obs_landmarks.tolist()], dtype=np.int64), uv, sigma_px, rig.camera_model, rig.T_body_cam,
        prior_pose, prior_landmark, p_body, Sigma_body,
        links, np.array([sigma for _, _, sigma in mlog.links], dtype=float), robust=robust,
    )  # fmt: skip
    return dict(zip(landmarks, X)), iterations


def _with_ties(mlog: MeasurementLog, T0: np.ndarray, row: dict[int, int], pose, landmark, p_body, Sigma_body) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The seeds' priors (pose index, landmark row, body-frame position and covariance) with the laser's
    ties after them: each in its frame's pose, and each level tie's world-frame prior in the start pose's frame."""
    R0, t0 = np.asarray(T0, dtype=float)[:3, :3], np.asarray(T0, dtype=float)[:3, 3]
    poses, rows, ps, Sigmas = [pose], [landmark], [p_body], [Sigma_body]
    for ties in mlog.ties:
        poses.append(ties.frames + 1)
        rows.append(np.array([row[int(lm)] for lm in ties.landmarks], dtype=np.int64))
        ps.append(ties.p_frame)
        Sigmas.append(ties.Sigma_frame)
        poses.append(np.zeros(len(ties.level_landmarks), dtype=np.int64))
        rows.append(np.array([row[int(lm)] for lm in ties.level_landmarks], dtype=np.int64))
        ps.append((ties.level_mean.reshape(-1, 3) - t0) @ R0)
        Sigmas.append(R0.T @ ties.level_Sigma.reshape(-1, 3, 3) @ R0)
    return np.concatenate(poses), np.concatenate(rows), np.concatenate(ps).reshape(-1, 3), np.concatenate(Sigmas).reshape(-1, 3, 3)


def _fit_to_held_poses(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, params) -> gtsam.Values:
    """The variables of ``graph`` other than its poses (the IMU's velocities and biases), moved to
    their best fit with every pose held where ``values`` has it."""
    held = gtsam.NonlinearFactorGraph(graph)
    # a prior of 1 um and 1 urad, not a hard constraint: Levenberg-Marquardt's damping would move a
    # NonlinearEquality's pose and make its error infinite
    pin = gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)
    keys = list(graph.keyVector())
    poses = {key for key in keys if gtsam.Symbol(key).chr() == ord("x")}
    start = gtsam.Values()
    for key in keys:
        if key in poses:
            held.add(gtsam.PriorFactorPose3(key, values.atPose3(key), pin))
            start.insert(key, values.atPose3(key))
        elif gtsam.Symbol(key).chr() == ord("v"):
            start.insert(key, values.atVector(key))
        else:
            start.insert(key, values.atConstantBias(key))
    fitted = gtsam.LevenbergMarquardtOptimizer(held, start, params).optimize()
    for key in poses:
        fitted.erase(key)
    return fitted


def _marginals_by_qr(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, keys: list[int]) -> np.ndarray:
    """What ``gtsam.Marginals`` gives, from a QR elimination (the same COLAMD ordering) instead of
    Cholesky's: about twice as slow, and it takes systems Cholesky's pivots call indeterminate."""
    linear = graph.linearize(values)
    tree = linear.eliminateMultifrontal(gtsam.Ordering.ColamdGaussianFactorGraph(linear), gtsam.EliminateQR)
    return np.array([tree.marginalCovariance(k) for k in keys])


# poses whose marginals are asked for together: one joint marginal of some 25 consecutive poses costs
# about what two single ones do (each walks the Bayes tree to its root), so the 1669 frames of `paper`
# took 1.2 s (chunks of 20 or 30) instead of 7.5 s; the covariances agree to 1e-6 of their sigmas
# (docs/isam2_design.md, "The batch's time")
MARGINAL_CHUNK = 25


def _pose_covariances(marginals: gtsam.Marginals, keys: list[int]) -> np.ndarray:
    """Each pose's marginal covariance, taken ``MARGINAL_CHUNK`` poses at a time."""
    out = []
    for i in range(0, len(keys), MARGINAL_CHUNK):
        chunk = keys[i : i + MARGINAL_CHUNK]
        joint = marginals.jointMarginalCovariance(gtsam.KeyVector(chunk))
        out += [joint.at(k, k) for k in chunk]
    return np.array(out)


def pose_marginals(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, keys: list[int]) -> tuple[np.ndarray | None, bool]:
    """The marginal covariance (k, 6, 6) of each pose of ``keys`` in ``graph`` linearised at
    ``values`` (gtsam's tangent order [rotation, translation], right perturbation), symmetrised, and
    whether it took the QR elimination. That is the second try, when Cholesky's finds the system
    indeterminate: with the IMU, the biases' random walk between frames 40 ms apart (information
    up to about 1e11, docs/imu.md) can fail its pivots on a well-posed system. None, with a warning,
    when neither can factor the system or a covariance is not finite and positive definite."""
    by_qr = False
    try:
        marginals = gtsam.Marginals(graph, values)
        P = _pose_covariances(marginals, keys)
    except RuntimeError as exc:
        log.info("batch: Cholesky found the system indeterminate (%s): the marginals by QR instead", one_line(exc))
        by_qr = True
        try:
            P = _marginals_by_qr(graph, values, keys)
        except RuntimeError as exc_qr:
            log.warning("batch: no marginal covariances (%s): the frames keep the online pass's", one_line(exc_qr))
            return None, by_qr
    P = P.reshape(len(keys), 6, 6)
    P = 0.5 * (P + np.swapaxes(P, 1, 2))
    if not (np.all(np.isfinite(P)) and np.all(np.linalg.eigvalsh(P)[:, 0] > 0)):
        log.warning("batch: a marginal covariance is not finite and positive definite: the frames keep the online pass's")
        return None, by_qr
    return P, by_qr


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
    imu: ImuSpec | None = None,
    sigma_v0_mps: float = 1.0,
    marginals: bool = True,
) -> BatchResult:
    """Smooth the whole log from the initial estimates (``poses_init``: every frame's pose);
    ``marginals``: and each frame's pose covariance from the final graph (:func:`pose_marginals`)."""
    t0 = time.perf_counter()
    graph = build_graph(mlog, rig, T0, P0, sigma_px, sigma_seed_px, robust)
    values = gtsam.Values()
    values.insert(X(0), gtsam.Pose3(np.asarray(T0, dtype=float)))
    for f in range(mlog.n_frames):
        values.insert(X(f + 1), gtsam.Pose3(poses_init[f]))
    landmarks = set(mlog.seed_landmark) | {after for _, after, _ in mlog.links}
    for lm in landmarks:
        values.insert(L(lm), gtsam.Point3(*points_init[lm]))
    imu_graph = gtsam.NonlinearFactorGraph()
    n_imu = add_imu_factors(imu_graph, values, mlog, imu, np.asarray(poses_init), sigma_v0_mps) if imu is not None else 0
    graph.push_back(imu_graph)
    t1 = time.perf_counter()
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(max_iterations)
    params.setRelativeErrorTol(relative_error_tol)
    error_initial = graph.error(values)
    # the start: the landmarks, and the IMU's velocities and biases, fitted to the online poses, held
    X_fitted, refit_iterations = _fit_landmarks_to_poses(mlog, rig, T0, poses_init, points_init, sorted(landmarks), sigma_px, robust)
    for lm, X_lm in X_fitted.items():
        values.update(L(lm), gtsam.Point3(*X_lm))
    if n_imu:
        values.update(_fit_to_held_poses(imu_graph, values, params))
    error_refit = graph.error(values)
    try:
        optimizer = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
        out = optimizer.optimize()
    except RuntimeError as exc:
        raise DemGraphError(f"the batch optimisation failed: {one_line(exc)}") from None
    t2 = time.perf_counter()
    pose_covariances, marginals_by_qr = pose_marginals(graph, out, [X(f + 1) for f in range(mlog.n_frames)]) if marginals else (None, False)
    t3 = time.perf_counter()
    result = BatchResult(
        poses=np.array([out.atPose3(X(f + 1)).matrix() for f in range(mlog.n_frames)]),
        points={lm: out.atPoint3(L(lm)) for lm in landmarks},
        iterations=optimizer.iterations(),
        refit_iterations=refit_iterations,
        error_initial=float(error_initial),
        error_refit=float(error_refit),
        error_final=float(optimizer.error()),
        build_s=t1 - t0,
        optimize_s=t2 - t1,
        n_factors=graph.size(),
        pose_covariances=pose_covariances,
        marginals_s=t3 - t2 if marginals else 0.0,
        marginals_failed=marginals and pose_covariances is None,
        marginals_by_qr=marginals_by_qr,
    )
    if n_imu:
        log.info("batch: %d IMU factors between frames", n_imu)
    log.info(
        "batch: %d factors, built in %.1f s; %d + %d iterations in %.1f s, error %.1f -> %.1f (landmarks fitted) -> %.1f",
        result.n_factors, result.build_s, result.refit_iterations, result.iterations, result.optimize_s,
        result.error_initial, result.error_refit, result.error_final,
    )
    if result.pose_covariances is not None:
        log.info("batch: the poses' marginal covariances in %.1f s", result.marginals_s)
    return result


__all__ = ["BatchResult", "build_graph", "pose_marginals", "smooth_batch"]
