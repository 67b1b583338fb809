"""The EKF baselines with an IMU (issue 36): the gyroscope's bias in the state, the accelerometer's
gravity direction as a tilt update, against closed forms and the simulator's truth."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from dem_graph.estimators.ekf_filter import ACCEL_BIAS, GYRO_BIAS, POS, ROT, EkfState
from dem_graph.sim.scenarios import scenario
from dem_graph.sim.simulator import SimulatedSequence

G = 9.80665
R_BODY_IMU = Rotation.from_euler("z", 90, degrees=True).as_matrix()  # the default rig's mounting


def _state(sigma_rot_rad: float, sigma_gyro_bias: float, sigma_accel_bias: float) -> EkfState:
    P_pose = np.diag([sigma_rot_rad**2] * 3 + [1e-4] * 3)
    return EkfState(np.eye(4), P_pose, np.zeros(6), np.eye(6) * 0.01, (sigma_gyro_bias, sigma_accel_bias))


def test_the_gyroscope_bias_turns_the_body_by_its_integral():
    """With the body at rest and no other noise, ``n`` frames of ``T`` seconds with an uncertain bias
    (sigma ``s``) leave the rotation uncertain by ``s n T`` per axis and correlated with the bias by
    ``-n T s^2 R_body_imu`` (the rotation error is the bias error integrated): exact to 1e-12."""
    s, T, n = 1e-3, 0.04, 25
    st = _state(0.0, s, 0.01)
    for _ in range(n):
        st.propagate_imu_biases(R_BODY_IMU, T, 0.0, 0.0)
    np.testing.assert_allclose(st.P[ROT, ROT], np.eye(3) * (s * n * T) ** 2, atol=1e-12 * (s * n * T) ** 2)
    np.testing.assert_allclose(st.P[ROT, GYRO_BIAS], -n * T * s**2 * R_BODY_IMU, atol=1e-15)
    np.testing.assert_allclose(st.P[GYRO_BIAS, GYRO_BIAS], np.eye(3) * s**2, rtol=1e-12)


def test_gravity_sets_roll_and_pitch_and_leaves_the_heading():
    """A pose tilted 1.1 and 1.7 degrees (0.036 rad) from the estimate, its accelerometer without
    noise or bias (the bias known to 1e-6 m/s^2): one update brings the estimate's up direction onto
    the true one up to the linearisation's second-order error (below the square of the tilt,
    1.3e-3; measured 1.6e-6 after four updates), and the heading (yaw), which gravity does not
    see, stays where it was to 1e-6 rad."""
    st = _state(0.05, 1e-4, 1e-6)
    tilt = np.array([0.02, -0.03, 0.0])
    R_true = Rotation.from_rotvec(tilt).as_matrix()  # world-frame tilt of the true pose
    f_imu = R_BODY_IMU.T @ R_true.T @ np.array([0.0, 0.0, G])
    assert st.gravity_update(f_imu, np.zeros(3), R_BODY_IMU, 1e-10, G, gate_chi2=1e12)
    up_est = st.T_world_body[:3, :3].T @ np.array([0.0, 0.0, 1.0])
    assert np.linalg.norm(up_est - R_true.T @ np.array([0.0, 0.0, 1.0])) < np.linalg.norm(tilt) ** 2
    heading = lambda R: np.arctan2(R[1, 0], R[0, 0])  # noqa: E731
    assert heading(st.T_world_body[:3, :3]) == pytest.approx(heading(R_true), abs=1e-6)
    assert np.all(np.sqrt(np.diag(st.P[ROT, ROT]))[:2] < 1e-4)  # roll and pitch now known
    assert np.sqrt(st.P[2, 2]) == pytest.approx(0.05, rel=1e-3)  # yaw as uncertain as before


def test_an_accelerating_vehicle_is_not_a_tilt_measurement():
    """2 m/s^2 along the body's x axis, unmodelled, against 0.2 m/s^2 of allowed acceleration: the
    update fails the chi-square gate and leaves the state as it was."""
    st = _state(0.01, 1e-4, 0.02)
    P0, T0 = st.P.copy(), st.T_world_body.copy()
    f_imu = R_BODY_IMU.T @ np.array([2.0, 0.0, G])
    assert not st.gravity_update(f_imu, np.zeros(3), R_BODY_IMU, 0.2**2, G, gate_chi2=9.21)
    np.testing.assert_array_equal(st.P, P0)
    np.testing.assert_array_equal(st.T_world_body, T0)


def test_the_accelerometer_bias_and_the_tilt_share_the_measurement():
    """The same specific force fits a tilt or an accelerometer bias: with the bias as uncertain as
    its spread (0.02 m/s^2), updates leave roll and pitch uncertain to about 0.02 / g rad (to within
    15 %), not to the accelerometer's noise."""
    sigma_ba = 0.02
    st = _state(0.05, 1e-4, sigma_ba)
    f_imu = R_BODY_IMU.T @ np.array([0.0, 0.0, G])
    for _ in range(200):
        st.gravity_update(f_imu, np.zeros(3), R_BODY_IMU, 1e-6, G, gate_chi2=1e12)
    sigma_tilt = np.sqrt(np.diag(st.P[ROT, ROT]))[:2]
    np.testing.assert_allclose(sigma_tilt, sigma_ba / G, rtol=0.15)
    assert np.all(np.sqrt(np.diag(st.P[ACCEL_BIAS, ACCEL_BIAS]))[:2] > 0.5 * sigma_ba)
    assert np.all(np.isfinite(st.P[POS, POS]))


@pytest.fixture(scope="module")
def ptpm_with_imu():
    from dem_graph.pipeline import RunConfig
    from dem_graph.pipeline.live import make_estimator
    from dem_graph.pipeline.run import feed

    log = SimulatedSequence.from_config(scenario("smoke", seed=1, length_m=10.0))
    config = RunConfig.model_validate({"estimator": "ptpm"})
    estimator = make_estimator(log.rig, log.T_world_body_initial, log.t_start_s, log.has_odometry, config)
    for _ in feed(estimator, log, finish=False):
        pass
    return log, estimator


def test_ptpm_estimates_the_gyroscope_bias_within_its_covariance(ptpm_with_imu):
    """PTPM on 10 m of `smoke` with the simulated IMU: the filter's gyroscope bias at the end is
    within its own covariance of the simulator's (3-dimensional NEES under the chi-square 99.9 %
    point, 16.3), and every frame's rotation came from the gyroscope."""
    log, estimator = ptpm_with_imu
    truth = log.imu_track()
    st = estimator.state
    i = int(np.searchsorted(truth.t_s, estimator.last_frame.t_s, side="right")) - 1
    error = st.gyro_bias_rad_s - truth.gyro_bias_rad_s[i]
    assert float(error @ np.linalg.solve(st.P[GYRO_BIAS, GYRO_BIAS], error)) < 16.3
    assert estimator.frontend.counters["imu_frames_without_gyro"] == 0


def test_ptpm_takes_the_tilt_from_gravity_at_a_steady_speed(ptpm_with_imu):
    """At `smoke`'s steady 1.5 m/s, the accelerometer's horizontal components over a frame stay
    within the allowed 0.2 m/s^2 of gravity's: at least 95 % of the frames update the tilt; and the
    end pose's roll and pitch are within three of the filter's own sigmas of the truth."""
    log, estimator = ptpm_with_imu
    c = estimator.frontend.counters
    assert c["imu_tilt_updates"] >= 0.95 * (c["imu_tilt_updates"] + c["imu_tilt_gated"])
    t_end = estimator.last_frame.t_s
    R_true = log.ground_truth.trajectory.at(np.array([t_end]))[0][:3, :3]
    R_est = estimator.state.T_world_body[:3, :3]
    up_error = R_est.T @ np.array([0.0, 0.0, 1.0]) - R_true.T @ np.array([0.0, 0.0, 1.0])  # ~ tilt error, body frame
    sigma = np.sqrt(np.diag(estimator.state.pose_covariance()[:3, :3]))
    assert abs(up_error[0]) < 3 * sigma[1] and abs(up_error[1]) < 3 * sigma[0]
