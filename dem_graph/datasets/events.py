"""The time-ordered events every estimator reads."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class CameraFrame:
    """One image: (H,W) uint8 grey or (H,W,3) uint8 BGR, taken at ``t_s``.

    ``textureless``: the reader found no texture in it (:class:`~dem_graph.datasets.checks.InputChecks`'
    ``min_image_std_dn``): an estimator predicts its pose and neither tracks nor adds points in it.
    """

    t_s: float
    image: np.ndarray = field(repr=False)
    index: int = 0
    textureless: bool = False


@dataclass(frozen=True)
class LaserScan:
    """One scan: a range per beam of the rig's laser, metres; NaN means no return."""

    t_s: float
    ranges_m: np.ndarray = field(repr=False)
    index: int = 0


@dataclass(frozen=True)
class Odometry:
    """Body motion measured between ``t_prev_s`` and ``t_s``.

    ``T_prev_curr`` is the pose of the body at ``t_s`` in the body frame at ``t_prev_s``;
    ``covariance`` is its 6x6 uncertainty in gtsam's tangent order [rotation, translation]
    (radians^2, metres^2), as a right perturbation ``T_prev_curr * Exp(xi)``.
    """

    t_s: float
    t_prev_s: float
    T_prev_curr: np.ndarray = field(repr=False)
    covariance: np.ndarray = field(repr=False)
    index: int = 0


@dataclass(frozen=True)
class ImuSample:
    """One inertial measurement at ``t_s``, in the IMU's own frame (the rig's ``imu.T_body_imu``):
    the angular rate ``gyro_rad_s`` (3,) and the specific force ``accel_mps2`` (3,), which reads
    +9.81 m/s^2 up when the IMU is at rest (gravity's reaction, as every MEMS part reports it)."""

    t_s: float
    gyro_rad_s: np.ndarray = field(repr=False)
    accel_mps2: np.ndarray = field(repr=False)
    index: int = 0


Event = CameraFrame | LaserScan | Odometry | ImuSample
