"""Trajectory metrics: known answers, alignment, NEES, and a cross-check against evo."""

from __future__ import annotations

import copy

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from scipy.stats import chi2

from dem_graph.errors import DemGraphError
from dem_graph.evaluation.trajectory_metrics import (
    TrajectoryMetrics,
    ate_aligned_rmse_m,
    nees_bounds,
    pose_nees,
    trajectory_errors,
    trajectory_metrics,
    umeyama_alignment,
)
from dem_graph.geometry.se3 import make_pose
from dem_graph.geometry.trajectory import Trajectory


def curved_truth(n: int = 200, seed: int = 0) -> Trajectory:
    """A vehicle-like path: an arc with some height change, yaw along the path, small roll and pitch."""
    rng = np.random.default_rng(seed)
    t = np.linspace(10.0, 30.0, n)
    heading = 0.05 * (t - 10.0)
    positions = np.stack([10.0 * np.sin(heading), 10.0 * (1.0 - np.cos(heading)), 0.2 * np.sin(0.3 * t)], axis=1)
    rpy = np.stack([rng.normal(0, 0.02, n), rng.normal(0, 0.02, n), heading], axis=1)
    quats = Rotation.from_euler("xyz", rpy).as_quat()
    return Trajectory(t, positions, quats)


def noisy_estimate(truth: Trajectory, seed: int = 1, every: int = 3) -> Trajectory:
    """The truth at every ``every``-th sample, with random position drift and rotation errors."""
    rng = np.random.default_rng(seed)
    t = truth.t_s[::every]
    T = truth.at(t)
    drift = np.cumsum(rng.normal(0.0, 0.05, (len(t), 3)), axis=0)
    R = Rotation.from_rotvec(rng.normal(0.0, 0.01, (len(t), 3))).as_matrix()
    return Trajectory.from_poses(t, make_pose(T[:, :3, :3] @ R, T[:, :3, 3] + drift))


# ------------------------------------------------------------------------------- known answers


def test_constant_offset_gives_its_norm_and_zero_after_alignment():
    truth = curved_truth()
    estimate = Trajectory(truth.t_s, truth.positions_xyz + [0.3, -0.4, 0.0], truth.orientations_quat_xyzw)
    errors = trajectory_errors(estimate, truth)
    np.testing.assert_allclose(errors.position_error_m, np.tile([0.3, -0.4, 0.0], (len(truth), 1)), atol=1e-12)
    np.testing.assert_allclose(errors.rotation_error_rad, 0.0, atol=1e-7)
    m = trajectory_metrics(estimate, truth)
    assert m.ate_rmse_m == pytest.approx(0.5, abs=1e-12)
    assert m.ate_max_m == pytest.approx(0.5, abs=1e-12)
    assert m.final_error_m == pytest.approx(0.5, abs=1e-12)
    assert m.n_poses == len(truth)
    assert m.distance_m == pytest.approx(truth.path_length_m, rel=1e-12)
    assert ate_aligned_rmse_m(estimate, truth) == pytest.approx(0.0, abs=1e-9)


def test_linear_drift_of_one_metre_over_100_m_is_one_percent():
    t = np.linspace(0.0, 100.0, 101)
    positions = np.stack([t, np.zeros_like(t), np.zeros_like(t)], axis=1)  # 1 m/s along x
    q = np.tile([0.0, 0.0, 0.0, 1.0], (len(t), 1))
    truth = Trajectory(t, positions, q)
    estimate = Trajectory(t, positions + np.stack([np.zeros_like(t), t / 100.0, np.zeros_like(t)], axis=1), q)
    errors = trajectory_errors(estimate, truth)
    np.testing.assert_allclose(errors.distance_travelled_m, t, atol=1e-12)
    m = trajectory_metrics(estimate, truth)
    assert m.distance_m == pytest.approx(100.0)
    assert m.final_error_m == pytest.approx(1.0)
    assert m.drift_percent == pytest.approx(1.0)
    assert m.ate_rmse_m == pytest.approx(np.sqrt(np.mean((t / 100.0) ** 2)))


def test_distance_follows_the_truth_between_estimate_samples():
    # truth goes out 1 m along x and back along y: estimate sampled only at the ends
    truth = Trajectory([0.0, 1.0, 2.0], [[0, 0, 0], [1, 0, 0], [1, 1, 0]], np.tile([0, 0, 0, 1.0], (3, 1)))
    estimate = Trajectory([0.5, 2.0], [[0.5, 0, 0], [1, 1, 0]], np.tile([0, 0, 0, 1.0], (2, 1)))
    np.testing.assert_allclose(trajectory_errors(estimate, truth).distance_travelled_m, [0.0, 1.5])


def test_known_yaw_offset_gives_its_angle():
    truth = curved_truth()
    yaw = np.radians(7.0)
    R_off = Rotation.from_euler("z", yaw).as_matrix()
    T = truth.poses_se3
    estimate = Trajectory.from_poses(truth.t_s, make_pose(T[:, :3, :3] @ R_off, T[:, :3, 3]))
    errors = trajectory_errors(estimate, truth)
    np.testing.assert_allclose(errors.rotation_error_rad, yaw, atol=1e-9)
    m = trajectory_metrics(estimate, truth)
    assert m.rotation_rmse_deg == pytest.approx(7.0, abs=1e-7)
    assert m.ate_rmse_m == pytest.approx(0.0, abs=1e-12)


def test_truth_is_interpolated_at_the_estimate_times():
    truth = curved_truth()
    t = (truth.t_s[:-1] + truth.t_s[1:]) / 2.0
    estimate = Trajectory.from_poses(t, truth.at(t))
    m = trajectory_metrics(estimate, truth)
    assert m.ate_rmse_m == pytest.approx(0.0, abs=1e-12)
    assert m.rotation_rmse_deg == pytest.approx(0.0, abs=1e-5)


def test_estimate_outside_the_truth_span_is_an_error():
    truth = curved_truth()
    estimate = Trajectory(truth.t_s + 1.0, truth.positions_xyz, truth.orientations_quat_xyzw)
    with pytest.raises(DemGraphError, match="outside the ground truth"):
        trajectory_errors(estimate, truth)


def test_no_travel_gives_nan_drift_and_plain_floats():
    q = np.tile([0, 0, 0, 1.0], (3, 1))
    truth = Trajectory([0.0, 1.0, 2.0], np.zeros((3, 3)), q)
    estimate = Trajectory([0.0, 1.0, 2.0], np.full((3, 3), 0.1), q)
    m = trajectory_metrics(estimate, truth)
    assert np.isnan(m.drift_percent)
    d = m.as_dict()
    assert set(d) == set(TrajectoryMetrics.__dataclass_fields__)
    assert all(type(v) is float for k, v in d.items() if k != "n_poses") and type(d["n_poses"]) is int


# ------------------------------------------------------------------------------------- alignment


@pytest.mark.parametrize("with_scale", [False, True])
def test_umeyama_recovers_a_known_transform(with_scale):
    rng = np.random.default_rng(3)
    source = rng.normal(size=(50, 3))
    R = Rotation.random(random_state=4).as_matrix()
    t = np.array([1.0, -2.0, 0.5])
    s = 1.7 if with_scale else 1.0
    target = s * source @ R.T + t
    R_est, t_est, s_est = umeyama_alignment(source, target, with_scale=with_scale)
    np.testing.assert_allclose(R_est, R, atol=1e-12)
    np.testing.assert_allclose(t_est, t, atol=1e-12)
    assert s_est == pytest.approx(s, abs=1e-12)
    assert np.linalg.det(R_est) == pytest.approx(1.0)


def test_umeyama_never_returns_a_reflection():
    rng = np.random.default_rng(5)
    source = rng.normal(size=(20, 3))
    target = source * [1.0, 1.0, -1.0]  # a mirror image: the best rotation is not a reflection
    R, _, _ = umeyama_alignment(source, target)
    assert np.linalg.det(R) == pytest.approx(1.0)


def test_umeyama_rejects_bad_shapes():
    with pytest.raises(DemGraphError):
        umeyama_alignment(np.zeros((4, 3)), np.zeros((5, 3)))
    with pytest.raises(DemGraphError):
        umeyama_alignment(np.zeros((0, 3)), np.zeros((0, 3)))


# ------------------------------------------------------------------------------------------ NEES


def test_nees_of_errors_drawn_from_the_covariance_averages_the_dof():
    gtsam = pytest.importorskip("gtsam")
    rng = np.random.default_rng(42)
    n = 2000
    truth = curved_truth(n)
    T_est = truth.poses_se3
    # a different, well-conditioned covariance per pose, with correlations
    A = rng.normal(size=(n, 6, 6)) * np.array([0.02, 0.02, 0.02, 0.1, 0.1, 0.1])
    P = A @ np.swapaxes(A, 1, 2) + np.diag([1e-4] * 3 + [1e-3] * 3)
    L = np.linalg.cholesky(P)
    xi = (L @ rng.normal(size=(n, 6, 1)))[..., 0]
    T_true = np.stack([T_est[i] @ gtsam.Pose3.Expmap(xi[i]).matrix() for i in range(n)])
    nees = pose_nees(T_est, T_true, P)
    expected = np.einsum("ni,nij,nj->n", xi, np.linalg.inv(P), xi)
    np.testing.assert_allclose(nees, expected, rtol=1e-6)
    assert nees.mean() == pytest.approx(6.0, rel=0.05)
    lo, hi = nees_bounds()
    assert np.mean((nees >= lo) & (nees <= hi)) == pytest.approx(0.95, abs=0.02)


def test_nees_convention_is_the_right_perturbation_rotation_first():
    gtsam = pytest.importorskip("gtsam")
    T_est = make_pose(Rotation.from_euler("z", 90, degrees=True).as_matrix(), [1.0, 2.0, 3.0])
    # 0.1 m along the estimate's own x axis (the world's y): translation part, second block
    T_true = T_est @ gtsam.Pose3.Expmap(np.array([0, 0, 0, 0.1, 0, 0])).matrix()
    np.testing.assert_allclose(T_true[:3, 3], [1.0, 2.1, 3.0], atol=1e-12)
    P = np.diag([1e-6, 1e-6, 1e-6, 0.01, 1e-6, 1e-6])
    assert pose_nees(T_est[None], T_true[None], P[None])[0] == pytest.approx(1.0, rel=1e-9)


def test_nees_rejects_bad_covariances():
    T = np.eye(4)[None]
    with pytest.raises(DemGraphError, match="positive definite"):
        pose_nees(T, T, -np.eye(6)[None])
    with pytest.raises(DemGraphError, match="shape|needs"):
        pose_nees(T, T, np.eye(3)[None])


@pytest.mark.parametrize("dof,probability", [(6, 0.95), (3, 0.99), (1, 0.5)])
def test_nees_bounds_match_scipy(dof, probability):
    lo, hi = nees_bounds(dof, probability)
    assert lo == pytest.approx(chi2.ppf((1 - probability) / 2, dof), rel=1e-12)
    assert hi == pytest.approx(chi2.ppf((1 + probability) / 2, dof), rel=1e-12)
    assert chi2.cdf(hi, dof) - chi2.cdf(lo, dof) == pytest.approx(probability)


# ----------------------------------------------------------------------------------- evo check


def test_ate_matches_evo_ape_unaligned_and_aligned():
    metrics = pytest.importorskip("evo.core.metrics")
    evo_trajectory = pytest.importorskip("evo.core.trajectory")
    truth = curved_truth()
    estimate = noisy_estimate(truth)
    truth_at_est = truth.at(estimate.t_s)

    def evo_traj(t, T):
        return evo_trajectory.PoseTrajectory3D(timestamps=np.asarray(t), poses_se3=list(T))

    ref = evo_traj(estimate.t_s, truth_at_est)
    est = evo_traj(estimate.t_s, estimate.poses_se3)

    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref, est))
    evo_rmse = ape.get_statistic(metrics.StatisticsType.rmse)
    evo_max = ape.get_statistic(metrics.StatisticsType.max)
    m = trajectory_metrics(estimate, truth)
    assert m.ate_rmse_m > 0.05  # the test means something
    assert m.ate_rmse_m == pytest.approx(evo_rmse, abs=1e-9)
    assert m.ate_max_m == pytest.approx(evo_max, abs=1e-9)

    est_aligned = copy.deepcopy(est)
    est_aligned.align(ref, correct_scale=False)
    ape_aligned = metrics.APE(metrics.PoseRelation.translation_part)
    ape_aligned.process_data((ref, est_aligned))
    evo_aligned = ape_aligned.get_statistic(metrics.StatisticsType.rmse)
    ours = ate_aligned_rmse_m(estimate, truth)
    assert ours < m.ate_rmse_m
    assert ours == pytest.approx(evo_aligned, abs=1e-9)
