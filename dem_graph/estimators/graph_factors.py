"""Factor builders for the iSAM2 estimator, all of them gtsam's own (C++) factors.

- :func:`point_in_frame_factors` ties a point to a pose by a measurement of the point in that
  pose's frame with a full 3x3 covariance: a projection and a range factor from a virtual sensor on
  the covariance's major axis, so no Python factor runs in the solver. It is the laser factor: the
  point in the body frame through Eq. 2, with the range noise along the beam.
- :func:`range_factor` measures a point's distance from a sensor on the body. A new camera point
  gets it with the flat-ground depth uncertainty, plus the projection factor of the pixel it was
  seeded at: together they are the EKF's seed covariance (about 0.5 m of height along the ray,
  one pixel across it). A point-in-frame factor from the body origin cannot carry that covariance:
  seen from the body origin, a few decimetres along the camera's ray bend the bearing by more than
  the millimetres the covariance allows across the ray.
- :func:`odometry_factor`: a ``BetweenFactorPose3`` with the increment's 6x6 covariance.
- :func:`projection_factor`: a ``GenericProjectionFactorCal3DS2`` with ``T_body_cam`` as the
  sensor offset and a robust (Huber) kernel; :class:`ProjectionFactors` makes the same factors in a
  hot loop, sharing the sensor offset and one noise model per pixel sigma.
- :func:`seed_factors`: the factors a new point enters the graph with (laser or flat-ground seed);
  :func:`seeds_factors` the same for many points at once.
- :func:`link_factor`: a landmark continued by another (a patch refresh), within a sigma.
- :func:`level_factor`: a landmark on the start pose's ground plane (the laser's ties of the start's
  ground level the world: :mod:`~dem_graph.estimators.laser_ties`).

Covariances are in gtsam's tangent order [rotation, translation] (the package convention).
"""

from __future__ import annotations

import gtsam
import numpy as np

from dem_graph.frontend.frontend import PointKind
from dem_graph.geometry.camera import PinholeCamera
from dem_graph.geometry.se3 import invert, transform_points

HUBER_K = 1.345  # 95 % efficiency on Gaussian residuals


VIRTUAL_RANGE_M = 1.0  # distance of the virtual sensor from a point-in-frame measurement, metres


def point_in_frame_factors(pose_key: int, point_key: int, p_frame: np.ndarray, Sigma_frame: np.ndarray) -> list[gtsam.NonlinearFactor]:
    """The point ``point_key`` measured at ``p_frame`` (metres) in the frame of pose ``pose_key``,
    with covariance ``Sigma_frame`` (3x3, m^2), as two of gtsam's C++ factors.

    A virtual sensor sits ``VIRTUAL_RANGE_M`` behind the point on the covariance's major axis,
    looking along it: a projection factor (unit focal length) carries the two minor axes' sigmas,
    and a range factor from the same sensor the major axis's. To first order their summed cost is
    ``d^T Sigma^-1 d / 2`` for a displacement ``d`` of the point, and it stays smooth however the
    point moves (a bearing factor's tangent basis switches axes, making its cost jump).
    """
    p = np.asarray(p_frame, dtype=float)
    Sigma = np.asarray(Sigma_frame, dtype=float)
    if p.size != 3 or Sigma.shape != (3, 3):
        raise ValueError(f"a point-in-frame measurement needs a 3D point and a 3x3 covariance, got {p_frame} and shape {Sigma.shape}")
    return _point_in_frame_factors([pose_key], [point_key], p.reshape(1, 3), Sigma[None])


def points_in_frame_factors(pose_keys, point_keys, p_frame: np.ndarray, Sigma_frame: np.ndarray) -> list[gtsam.NonlinearFactor]:
    """:func:`point_in_frame_factors` of many measurements: ``p_frame`` (m,3), ``Sigma_frame`` (m,3,3), in their order."""
    p, Sigma = np.asarray(p_frame, dtype=float).reshape(-1, 3), np.asarray(Sigma_frame, dtype=float).reshape(-1, 3, 3)
    if not (len(p) == len(Sigma) == len(pose_keys) == len(point_keys)):
        raise ValueError(f"{len(pose_keys)} pose keys, {len(point_keys)} point keys, {len(p)} points and {len(Sigma)} covariances: one of each per measurement")
    return _point_in_frame_factors(list(pose_keys), list(point_keys), p, Sigma)


def _virtual_sensors(p_frame: np.ndarray, Sigma_frame: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per point-in-frame measurement (m,3) with its covariance (m,3,3): the virtual sensor's pose in
    the frame (m,4,4) and the covariance's eigenvalues (m,3), ascending (see :func:`point_in_frame_factors`)."""
    bad = ~(np.all(np.isfinite(p_frame), axis=1) & np.all(np.isfinite(Sigma_frame), axis=(1, 2)))
    if np.any(bad):
        i = int(np.flatnonzero(bad)[0])
        raise ValueError(f"a point-in-frame measurement needs a finite 3D point and covariance, got {p_frame[i]} and {Sigma_frame[i].tolist()}")
    lam, V = np.linalg.eigh(0.5 * (Sigma_frame + np.swapaxes(Sigma_frame, 1, 2)))  # ascending
    if np.any(lam[:, 0] <= 0):
        i = int(np.flatnonzero(lam[:, 0] <= 0)[0])
        raise ValueError(f"Sigma_frame must be positive definite, got eigenvalues {lam[i]}")
    z, x = V[:, :, 2], V[:, :, 0]
    T_frame_sensor = np.zeros((len(p_frame), 4, 4))
    T_frame_sensor[:, :3, 0], T_frame_sensor[:, :3, 1], T_frame_sensor[:, :3, 2] = x, np.cross(z, x), z
    T_frame_sensor[:, :3, 3] = p_frame - VIRTUAL_RANGE_M * z
    T_frame_sensor[:, 3, 3] = 1.0
    return T_frame_sensor, lam


_UNIT_CAMERA = gtsam.Cal3_S2(1.0, 1.0, 0.0, 0.0, 0.0)


def _point_in_frame_factors(pose_keys, point_keys, p_frame: np.ndarray, Sigma_frame: np.ndarray) -> list[gtsam.NonlinearFactor]:
    """:func:`point_in_frame_factors` of many measurements (m,3), (m,3,3), in their order."""
    T_frame_sensor, lam = _virtual_sensors(p_frame, Sigma_frame)
    across = np.sqrt(lam[:, :2]) / VIRTUAL_RANGE_M
    along = np.sqrt(lam[:, 2])
    out = []
    for pose_key, point_key, T, s_across, s_along in zip(pose_keys, point_keys, T_frame_sensor, across, along):
        sensor = gtsam.Pose3(T)
        out.append(gtsam.GenericProjectionFactorCal3_S2(np.zeros(2), gtsam.noiseModel.Diagonal.Sigmas(s_across), pose_key, point_key, _UNIT_CAMERA, sensor))
        out.append(gtsam.RangeFactorWithTransform3D(pose_key, point_key, VIRTUAL_RANGE_M, gtsam.noiseModel.Isotropic.Sigma(1, float(s_along)), sensor))
    return out


def range_factor(pose_key: int, point_key: int, range_m: float, sigma_m: float, T_body_sensor: np.ndarray | gtsam.Pose3) -> gtsam.NonlinearFactor:
    """Distance ``range_m`` (sigma ``sigma_m``) from the sensor at ``T_body_sensor`` (4x4, or a
    ``gtsam.Pose3``) on body pose ``pose_key`` to point ``point_key``."""
    if not (np.isfinite(range_m) and range_m > 0 and np.isfinite(sigma_m) and sigma_m > 0):
        raise ValueError(f"a range factor needs a positive range and sigma, got {range_m}, {sigma_m}")
    noise = gtsam.noiseModel.Isotropic.Sigma(1, float(sigma_m))
    sensor = T_body_sensor if isinstance(T_body_sensor, gtsam.Pose3) else gtsam.Pose3(np.asarray(T_body_sensor, dtype=float))
    return gtsam.RangeFactorWithTransform3D(pose_key, point_key, float(range_m), noise, sensor)


def odometry_factor(key_a: int, key_b: int, T_a_b: np.ndarray, covariance: np.ndarray) -> gtsam.BetweenFactorPose3:
    """Relative motion ``T_a_b`` between two poses with its 6x6 covariance ([rot, trans], right perturbation)."""
    cov = np.asarray(covariance, dtype=float)
    return gtsam.BetweenFactorPose3(key_a, key_b, gtsam.Pose3(np.asarray(T_a_b, dtype=float)), gtsam.noiseModel.Gaussian.Covariance(0.5 * (cov + cov.T)))


def calibration(camera: PinholeCamera) -> gtsam.Cal3DS2:
    """gtsam's calibration of the camera (k3 is not representable: it must be 0)."""
    k1, k2, p1, p2, k3 = camera.distortion
    if k3 != 0.0:
        raise ValueError("gtsam's Cal3DS2 has no k3: undistort the measurements or recalibrate without k3")
    return gtsam.Cal3DS2(camera.fx_px, camera.fy_px, 0.0, camera.cx_px, camera.cy_px, k1, k2, p1, p2)


class ProjectionFactors:
    """Projection factors of one camera: the calibration, the sensor offset ``T_body_cam`` and each
    pixel sigma's noise model are made once and shared by the factors (gtsam's are immutable), so
    in a hot loop a factor costs its own construction only (a third of the time of making each
    anew)."""

    def __init__(self, K: gtsam.Cal3DS2, T_body_cam: np.ndarray, robust: bool = True):
        self._K = K
        self._sensor = gtsam.Pose3(np.asarray(T_body_cam, dtype=float))
        self._robust = robust
        self._noise: dict[float, gtsam.noiseModel.Base] = {}

    def noise(self, sigma_px: float) -> gtsam.noiseModel.Base:
        """The (robust) noise model of a pixel with ``sigma_px``, made at its first use."""
        model = self._noise.get(sigma_px)
        if model is None:
            model = gtsam.noiseModel.Isotropic.Sigma(2, sigma_px)
            if self._robust:
                model = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(HUBER_K), model)
            if len(self._noise) < 4096:  # (sigmas come from a few track lengths; a bound all the same)
                self._noise[sigma_px] = model
        return model

    def __call__(self, pose_key: int, point_key: int, uv_px: np.ndarray, sigma_px: float) -> gtsam.GenericProjectionFactorCal3DS2:
        """The pixel ``uv_px`` of point ``point_key`` seen from body pose ``pose_key``, within ``sigma_px``."""
        u, v = uv_px
        return gtsam.GenericProjectionFactorCal3DS2(gtsam.Point2(float(u), float(v)), self.noise(float(sigma_px)), pose_key, point_key, self._K, self._sensor)


def projection_factor(
    pose_key: int, point_key: int, uv_px: np.ndarray, sigma_px: float, K: gtsam.Cal3DS2, T_body_cam: np.ndarray, robust: bool = True
) -> gtsam.GenericProjectionFactorCal3DS2:
    """The pixel ``uv_px`` of point ``point_key`` seen from body pose ``pose_key`` through ``T_body_cam``
    (one factor; :class:`ProjectionFactors` for many)."""
    return ProjectionFactors(K, T_body_cam, robust=robust)(pose_key, point_key, uv_px, sigma_px)


def seed_factors(
    pose_key: int, point_key: int, kind: int, p_body: np.ndarray, Sigma_body: np.ndarray, camera: PinholeCamera, K: gtsam.Cal3DS2, T_body_cam: np.ndarray, sigma_seed_px: float
) -> list[gtsam.NonlinearFactor]:
    """The factors a new point enters the graph with, from the front end's seed ``p_body`` (m) and
    ``Sigma_body`` (m^2) in the frame of body pose ``pose_key``.

    - Laser point: the point in the body frame (the paper's Eq. 2), with its covariance.
    - Camera point (flat-ground guess): the range from the camera, with the covariance's variance
      along the camera's ray, and the pixel it was seeded at, with ``sigma_seed_px``.
    """
    return seeds_factors([pose_key], [point_key], [kind], np.reshape(p_body, (1, 3)), np.reshape(Sigma_body, (1, 3, 3)), camera, K, T_body_cam, sigma_seed_px)


def seeds_factors(
    pose_keys, point_keys, kinds, p_body: np.ndarray, Sigma_body: np.ndarray, camera: PinholeCamera, K: gtsam.Cal3DS2, T_body_cam: np.ndarray, sigma_seed_px: float
) -> list[gtsam.NonlinearFactor]:
    """:func:`seed_factors` of many seeds (``p_body`` (m,3), ``Sigma_body`` (m,3,3)), each seed's
    factors in the seeds' order; the laser seeds' eigen-decompositions in one call (they were most of
    the batch graph's seed factors' 1.9 s for 9800 seeds)."""
    p = np.asarray(p_body, dtype=float).reshape(-1, 3)
    Sigma = np.asarray(Sigma_body, dtype=float).reshape(-1, 3, 3)
    laser = np.array([kind == PointKind.LASER for kind in kinds], dtype=bool)
    by_seed: list[list[gtsam.NonlinearFactor]] = [[] for _ in range(len(p))]
    if np.any(laser):
        idx = np.flatnonzero(laser)
        factors = _point_in_frame_factors([pose_keys[i] for i in idx], [point_keys[i] for i in idx], p[idx], Sigma[idx])
        for n, i in enumerate(idx):
            by_seed[i] = factors[2 * n : 2 * n + 2]
    if not np.all(laser):
        idx = np.flatnonzero(~laser)
        T_body_cam = np.asarray(T_body_cam, dtype=float)
        T_cam_body = invert(T_body_cam)
        camera_pose = gtsam.Pose3(T_body_cam)
        projection = ProjectionFactors(K, T_body_cam, robust=False)
        for i in idx:  # (one seed at a time, as alone, to the bit: a stack's norms and products may round otherwise)
            ray = p[i] - T_body_cam[:3, 3]
            range_m = float(np.linalg.norm(ray))
            r = ray / range_m
            sigma_along = float(np.sqrt(r @ Sigma[i] @ r))
            uv, in_front = camera.project(transform_points(T_cam_body, p[i][None]))
            if not in_front[0]:
                raise ValueError(f"a camera seed must lie in front of the camera, got {p[i]} in the body frame")
            by_seed[i] = [range_factor(pose_keys[i], point_keys[i], range_m, sigma_along, camera_pose), projection(pose_keys[i], point_keys[i], uv[0], sigma_seed_px)]
    return [f for factors in by_seed for f in factors]


def level_factor(point_key: int, mean_world: np.ndarray, Sigma_world: np.ndarray) -> gtsam.PriorFactorPoint3:
    """The point ``point_key`` on the start pose's ground plane: a world-frame prior, tight across the
    plane (:func:`~dem_graph.estimators.laser_ties.level_prior`), for a laser tie of the start's ground."""
    return gtsam.PriorFactorPoint3(point_key, gtsam.Point3(*np.asarray(mean_world, dtype=float)), gtsam.noiseModel.Gaussian.Covariance(np.asarray(Sigma_world, dtype=float)))


def link_factor(key_before: int, key_after: int, sigma_m: float) -> gtsam.BetweenFactorPoint3:
    """Landmark ``key_after`` is landmark ``key_before`` to within ``sigma_m`` (metres, each axis)."""
    return gtsam.BetweenFactorPoint3(key_before, key_after, gtsam.Point3(0.0, 0.0, 0.0), gtsam.noiseModel.Isotropic.Sigma(3, float(sigma_m)))
