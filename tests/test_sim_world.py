"""The simulated vehicle, odometry, terrain and determinism against their truth and noise models."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest
from scipy.stats import chi2

from dem_graph.datasets import CameraFrame, ImuSample, LaserScan, Odometry
from dem_graph.geometry.se3 import invert
from dem_graph.sim.scenarios import scenario
from dem_graph.sim.simulator import SimulatedSequence


@pytest.fixture(scope="module")
def smoke():
    return SimulatedSequence.from_config(scenario("smoke", seed=1))


def _log(T):
    return gtsam.Pose3.Logmap(gtsam.Pose3(T))


def test_terrain_relief_is_realistic(smoke):
    world = smoke.world
    z = np.asarray(world.terrain.elevation.z_m, dtype=float)
    res = world.terrain.geometry.resolution_m
    assert 0.02 <= res <= 0.05
    assert 0.1 < z.std() < 0.6  # gentle undulation of decimetres
    # stones and mounds of 5-30 cm stand out above a 1 m median of the surface
    from scipy.ndimage import median_filter

    bumps = z - median_filter(z, size=int(1.0 / res))
    assert 0.05 < np.percentile(bumps, 99.9) < 0.45


def test_trajectory_stays_on_terrain(smoke):
    gt = smoke.ground_truth.trajectory
    contact_z, ground_z = smoke.world.motion.contact_heights(gt.poses_se3)
    residual = contact_z - ground_z
    # the mean of the four contacts lies on the terrain (to 2 mm); one wheel may be off the contact
    # plane by the terrain's twist, a few centimetres at most
    assert np.abs(residual.mean(axis=1)).max() < 0.002
    assert np.abs(residual).max() < 0.05
    # it drives at the scenario's speed
    speed = np.linalg.norm(np.diff(gt.positions_xyz, axis=0), axis=1) / np.diff(gt.t_s)
    assert np.median(speed) == pytest.approx(smoke.config.path.speed_mps, rel=0.12)
    assert gt.path_length_m == pytest.approx(smoke.config.length_m, rel=0.02)


@pytest.fixture(scope="module")
def smoke_events(smoke):
    return list(smoke.events())


def test_event_streams_and_rates(smoke, smoke_events):
    times = np.array([e.t_s for e in smoke_events])
    assert np.all(np.diff(times) >= 0)
    cam = np.array([e.t_s for e in smoke_events if isinstance(e, CameraFrame)])
    laser = np.array([e.t_s for e in smoke_events if isinstance(e, LaserScan)])
    odo = [e for e in smoke_events if isinstance(e, Odometry)]
    np.testing.assert_allclose(np.diff(cam), 1 / 25.0, atol=1e-9)
    np.testing.assert_allclose(np.diff(laser), 1 / 12.5, atol=1e-9)
    np.testing.assert_allclose(np.diff([e.t_s for e in odo]), 1 / 50.0, atol=1e-9)
    # odometry increments chain: each starts where the previous one ended
    np.testing.assert_array_equal([e.t_prev_s for e in odo[1:]], [e.t_s for e in odo[:-1]])
    # the laser is not synchronized with the camera
    assert np.min(np.abs(laser[:, None] - cam[None, :])) > 0.005
    first = next(e for e in smoke_events if isinstance(e, CameraFrame))
    assert first.image.shape == (240, 320) and first.image.dtype == np.uint8
    # realistic images: neither flat nor saturated
    assert 20 < first.image.std() < 90 and np.mean(first.image == 255) < 0.01


def _odometry(seq):
    rngs_stream = seq._odometry_events(np.random.default_rng(11))
    return [e for _, _, e in rngs_stream]


def test_odometry_increments_match_their_covariance(smoke):
    gt = smoke.ground_truth.trajectory
    odo = _odometry(smoke)
    nees = []
    for e in odo:
        T_true = invert(gt.at(e.t_prev_s)) @ gt.at(e.t_s)
        xi = _log(invert(T_true) @ e.T_prev_curr)
        nees.append(xi @ np.linalg.solve(e.covariance, xi))
    nees = np.array(nees)
    # chi-square with 6 degrees of freedom: mean 6 (the one slip draw shifts it a little)
    assert 3.5 < nees.mean() < 9.0
    assert np.mean(nees < chi2.ppf(0.99, 6)) > 0.95


def test_odometry_integrates_to_truth_within_noise_model():
    # white noise only (no slip), so the propagated covariance is the whole noise model
    config = scenario("smoke", seed=4)
    rig = config.rig.model_copy(update={"odometry": config.rig.odometry.model_copy(update={"sigma_scale": 0.0})})
    seq = SimulatedSequence.from_config(config.model_copy(update={"rig": rig}))
    gt = seq.ground_truth.trajectory
    nees = []
    for seed in range(20):
        T = gt.at(seq.t_start_s)
        cov = np.zeros((6, 6))
        for e in seq._odometry_events(np.random.default_rng(100 + seed)):
            e = e[2]
            T = T @ e.T_prev_curr
            Ad = gtsam.Pose3(invert(e.T_prev_curr)).AdjointMap()
            cov = Ad @ cov @ Ad.T + e.covariance
        xi = _log(invert(gt.at(e.t_s)) @ T)
        nees.append(xi @ np.linalg.solve(cov, xi))
    # 20 runs of a chi-square(6): the mean lies within [3.5, 9] with probability > 99.9 %
    assert 3.5 < np.mean(nees) < 9.0


def test_same_seed_same_data_and_different_seed_differs():
    a = SimulatedSequence.from_config(scenario("smoke", seed=7, length_m=1.0))
    b = SimulatedSequence.from_config(scenario("smoke", seed=7, length_m=1.0))
    c = SimulatedSequence.from_config(scenario("smoke", seed=8, length_m=1.0))
    ea, eb = list(a.events()), list(b.events())
    # of the other seed's log only its start is compared (its first image, its first 100 IMU samples)
    ec, n_frames, n_imu = [], 0, 0
    for e in c.events():
        ec.append(e)
        n_frames += isinstance(e, CameraFrame)
        n_imu += isinstance(e, ImuSample)
        if n_frames and n_imu >= 100:
            break
    assert len(ea) == len(eb)
    for x, y in zip(ea, eb):
        assert type(x) is type(y) and x.t_s == y.t_s
        if isinstance(x, CameraFrame):
            assert np.array_equal(x.image, y.image)
        elif isinstance(x, LaserScan):
            assert np.array_equal(x.ranges_m, y.ranges_m, equal_nan=True)
        elif isinstance(x, ImuSample):
            assert np.array_equal(x.gyro_rad_s, y.gyro_rad_s) and np.array_equal(x.accel_mps2, y.accel_mps2)
        else:
            assert np.array_equal(x.T_prev_curr, y.T_prev_curr)
    assert np.array_equal(a.world.terrain.elevation.z_m, b.world.terrain.elevation.z_m)
    imu_a = np.array([e.gyro_rad_s for e in ea if isinstance(e, ImuSample)])
    imu_c = np.array([e.gyro_rad_s for e in ec if isinstance(e, ImuSample)])
    assert len(imu_a) > 100 and not np.array_equal(imu_a[:100], imu_c[:100])
    assert not np.array_equal(a.world.terrain.elevation.z_m, c.world.terrain.elevation.z_m)
    first_a = next(e for e in ea if isinstance(e, CameraFrame)).image
    first_c = next(e for e in ec if isinstance(e, CameraFrame)).image
    assert np.abs(first_a.astype(int) - first_c.astype(int)).mean() > 5


def test_odometry_switch_leaves_world_unchanged():
    on = SimulatedSequence.from_config(scenario("smoke", seed=2, length_m=1.0))
    off = SimulatedSequence.from_config(scenario("smoke", seed=2, length_m=1.0, with_odometry=False))
    assert on.has_odometry and not off.has_odometry
    assert not any(isinstance(e, Odometry) for e in off.events())
    np.testing.assert_array_equal(on.ground_truth.trajectory.positions_xyz, off.ground_truth.trajectory.positions_xyz)
