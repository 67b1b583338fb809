"""The simulated IMU: what a strapdown gyroscope and accelerometer on the body read while it drives.

The truth is the IMU frame's own trajectory, ``T_world_imu(t) = T_world_body(t) T_body_imu``,
sampled at the IMU's rate; the vibration the terrain gives the body (the wheels following the
ground's bumps) is in it. Sample ``k`` at ``t_k`` holds the rate and the specific force that carry
the IMU from ``t_k`` to ``t_k+1`` (held constant over the interval, as preintegration reads them):

- angular rate: ``Log(R_k^T R_k+1) / dt``, in the IMU frame;
- specific force: ``R_k^T (a_k - g)`` with ``a_k = (v_k+1 - v_k) / dt``, the velocities central
  differences of the positions, and ``g = (0, 0, -gravity)`` in the world (z up). At rest it reads
  +gravity along the IMU's up axis.

Integrated from the true velocity, these reproduce the sampled poses to the discretisation's
second order (a fraction of a millimetre over seconds). The noise is the continuous-time model of
the rig's :class:`~dem_graph.geometry.rig.ImuSpec`: white noise of the given density (sigma
``density / sqrt(dt)`` per sample) and biases that start at a random offset and random-walk.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from dem_graph.geometry.rig import ImuSpec


@dataclass(frozen=True)
class ImuTrack:
    """Every IMU sample of a run, with the truth behind it."""

    t_s: np.ndarray  # (N,)
    gyro_rad_s: np.ndarray  # (N,3) measured, IMU frame
    accel_mps2: np.ndarray  # (N,3) measured specific force, IMU frame
    gyro_bias_rad_s: np.ndarray  # (N,3) the true bias in each sample
    accel_bias_mps2: np.ndarray  # (N,3)
    T_world_imu: np.ndarray  # (N,4,4) true pose of the IMU at each sample time
    velocity_world_mps: np.ndarray  # (N,3) true velocity of the IMU at each sample time (world frame)


def imu_sample_times(t_end_s: float, rate_hz: float) -> np.ndarray:
    """The sample times from 0 to ``t_end_s`` (inclusive within a nanosecond)."""
    return np.arange(0.0, t_end_s + 1e-9, 1.0 / rate_hz)


def true_imu_signals(T_world_imu: np.ndarray, dt_s: float, gravity_mps2: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The noiseless rate (N,3), specific force (N,3) and velocity (N,3) of a pose sequence (N,4,4)
    sampled every ``dt_s`` (module docstring); the last sample repeats the one before."""
    R = T_world_imu[:, :3, :3]
    p = T_world_imu[:, :3, 3]
    n = len(T_world_imu)
    if n < 3:
        raise ValueError(f"an IMU track needs 3 samples at least, got {n}")
    v = np.gradient(p, dt_s, axis=0, edge_order=2)
    gyro = np.empty((n, 3))
    gyro[:-1] = Rotation.from_matrix(np.einsum("nji,njk->nik", R[:-1], R[1:])).as_rotvec() / dt_s
    gyro[-1] = gyro[-2]
    a_world = np.empty((n, 3))
    a_world[:-1] = np.diff(v, axis=0) / dt_s
    a_world[-1] = a_world[-2]
    g_world = np.array([0.0, 0.0, -gravity_mps2])
    accel = np.einsum("nji,nj->ni", R, a_world - g_world)
    return gyro, accel, v


def simulate_imu(T_world_body_at, T_body_imu: np.ndarray, spec: ImuSpec, t_end_s: float, rng: np.random.Generator | None) -> ImuTrack:
    """The IMU's samples from 0 to ``t_end_s`` for a body moving as ``T_world_body_at(t) -> (N,4,4)``;
    ``rng`` None: without noise and bias."""
    t = imu_sample_times(t_end_s, spec.rate_hz)
    dt = 1.0 / spec.rate_hz
    T_world_imu = T_world_body_at(t) @ np.asarray(T_body_imu, dtype=float)
    gyro, accel, v = true_imu_signals(T_world_imu, dt, spec.gravity_mps2)
    n = len(t)
    if rng is None:
        zeros = np.zeros((n, 3))
        return ImuTrack(t, gyro, accel, zeros, zeros.copy(), T_world_imu, v)
    bg0 = spec.gyro_bias_sigma * rng.standard_normal(3)
    ba0 = spec.accel_bias_sigma * rng.standard_normal(3)
    steps = rng.standard_normal((n, 4, 3))
    bg = bg0 + np.cumsum(np.vstack([np.zeros((1, 3)), steps[:-1, 0] * spec.gyro_bias_random_walk * np.sqrt(dt)]), axis=0)
    ba = ba0 + np.cumsum(np.vstack([np.zeros((1, 3)), steps[:-1, 1] * spec.accel_bias_random_walk * np.sqrt(dt)]), axis=0)
    gyro_meas = gyro + bg + steps[:, 2] * spec.gyro_noise_density / np.sqrt(dt)
    accel_meas = accel + ba + steps[:, 3] * spec.accel_noise_density / np.sqrt(dt)
    return ImuTrack(t, gyro_meas, accel_meas, bg, ba, T_world_imu, v)


__all__ = ["ImuTrack", "imu_sample_times", "simulate_imu", "true_imu_signals"]
