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
    accuracy_summary,
    ate_aligned_rmse_m,
    nees_bounds,
    pose_nees,
    relative_pose_errors,
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
    assert m.final_height_error_m == pytest.approx(0.0, abs=1e-12)  # the drift is sideways


@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_the_height_error_at_the_end_keeps_its_sign(sign):
    t = np.linspace(0.0, 10.0, 11)
    positions = np.stack([t, np.zeros_like(t), np.zeros_like(t)], axis=1)
    q = np.tile([0.0, 0.0, 0.0, 1.0], (len(t), 1))
    truth = Trajectory(t, positions, q)
    estimate = Trajectory(t, positions + np.stack([np.zeros_like(t), np.zeros_like(t), sign * 0.02 * t], axis=1), q)
    m = trajectory_metrics(estimate, truth)
    assert m.final_height_error_m == pytest.approx(sign * 0.2, abs=1e-12)  # 2 cm per metre over 10 m, estimate above the truth when positive
    assert m.final_error_m == pytest.approx(0.2, abs=1e-12)


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


# ------------------------------------------------------------------------------------------- RPE


def straight_truth(length_m: float = 40.0, step_m: float = 0.5) -> Trajectory:
    """1 m/s along x, facing +x, one pose every ``step_m``."""
    t = np.arange(0.0, length_m + 1e-9, step_m)
    positions = np.stack([t, np.zeros_like(t), np.zeros_like(t)], axis=1)
    return Trajectory(t, positions, np.tile([0.0, 0.0, 0.0, 1.0], (len(t), 1)))


def test_rpe_of_a_constant_scale_error_is_known():
    """An estimate that goes 2 % too far along x: every 10 m pair is 0.2 m too long, with no rotation error."""
    truth = straight_truth()
    estimate = Trajectory(truth.t_s, truth.positions_xyz * [1.02, 1.0, 1.0], truth.orientations_quat_xyzw)
    rpe = relative_pose_errors(estimate, truth, delta_m=10.0)
    # every pose at least 10 m before the end starts a pair, ending exactly 20 samples later
    assert len(rpe.pairs) == 61
    np.testing.assert_array_equal(rpe.pairs[:, 1] - rpe.pairs[:, 0], 20)
    np.testing.assert_allclose(rpe.translation_error_m, 0.2, atol=1e-12)
    np.testing.assert_allclose(rpe.rotation_error_deg, 0.0, atol=1e-9)
    d = rpe.summary().to_json_dict()
    assert d["translation_rmse_m"] == pytest.approx(0.2, abs=1e-12)
    assert d["translation_rmse_percent"] == pytest.approx(2.0, abs=1e-10)
    assert d["reason"] is None
    # with evo's default tolerance (10 %: 1 m), the poses less than 1 m past the last full pair pair with the end
    loose = relative_pose_errors(estimate, truth, delta_m=10.0, relative_tolerance=0.1)
    np.testing.assert_array_equal(loose.pairs[61:], [[61, 80], [62, 80]])
    np.testing.assert_allclose(loose.translation_error_m[61:], [0.02 * 9.5, 0.02 * 9.0], atol=1e-12)


def test_rpe_of_a_constant_yaw_rate_error_is_known():
    """A heading that turns 0.1 deg per metre too much: the rotation error of every 10 m pair is 1 deg."""
    truth = straight_truth()
    yaw = np.radians(0.1) * truth.positions_xyz[:, 0]
    estimate = Trajectory(truth.t_s, truth.positions_xyz, Rotation.from_euler("z", yaw[:, None]).as_quat())
    rpe = relative_pose_errors(estimate, truth, delta_m=10.0)
    np.testing.assert_allclose(rpe.rotation_error_deg, 1.0, atol=1e-9)
    # positions agree, but seen from the estimate's turned body frame at i, the 10 m step is off by 2 sin(theta/2) * 10 m
    np.testing.assert_allclose(rpe.translation_error_m, 10.0 * 2.0 * np.sin(np.radians(0.1) * truth.positions_xyz[rpe.pairs[:, 0], 0] / 2.0), atol=1e-9)


def test_rpe_ignores_an_error_made_before_the_pair():
    """A 1 m jump at t = 5 s only affects the pairs that straddle it; anchored ATE sees it everywhere after."""
    truth = straight_truth()
    p = truth.positions_xyz.copy()
    p[truth.t_s > 5.0, 1] += 1.0
    estimate = Trajectory(truth.t_s, p, truth.orientations_quat_xyzw)
    rpe = relative_pose_errors(estimate, truth, delta_m=10.0)
    straddle = (truth.t_s[rpe.pairs[:, 0]] <= 5.0) & (truth.t_s[rpe.pairs[:, 1]] > 5.0)
    np.testing.assert_allclose(rpe.translation_error_m[straddle], 1.0, atol=1e-12)
    np.testing.assert_allclose(rpe.translation_error_m[~straddle], 0.0, atol=1e-12)


@pytest.mark.parametrize("length_m", [6.0, 9.5])
def test_rpe_of_a_run_shorter_than_the_distance_is_nan_with_a_reason(length_m):
    truth = straight_truth(length_m=length_m)
    rpe = relative_pose_errors(truth, truth, delta_m=10.0)
    d = rpe.summary().to_json_dict()
    assert d["pairs"] == 0
    assert np.isnan(d["translation_rmse_m"]) and np.isnan(d["rotation_rmse_deg"])
    assert f"{length_m:.2f} m" in d["reason"] and "less than the RPE's 10 m" in d["reason"]
    with pytest.raises(DemGraphError, match="positive"):
        relative_pose_errors(truth, truth, delta_m=0.0)


def test_aligned_ate_of_the_truth_moved_by_a_rigid_transform_is_zero():
    truth = curved_truth()
    T_off = make_pose(Rotation.from_euler("xyz", [0.1, -0.2, 1.3]).as_matrix(), [5.0, -3.0, 2.0])
    moved = Trajectory.from_poses(truth.t_s, T_off @ truth.poses_se3)
    assert ate_aligned_rmse_m(moved, truth) == pytest.approx(0.0, abs=1e-9)
    assert trajectory_metrics(moved, truth).ate_rmse_m > 1.0
    # the relative motion is unchanged by a rigid transform of the whole trajectory
    rpe = relative_pose_errors(moved, truth, delta_m=5.0)
    assert len(rpe.pairs) > 0
    np.testing.assert_allclose(rpe.translation_error_m, 0.0, atol=1e-9)


def test_accuracy_summary_gathers_every_number():
    truth = straight_truth()
    estimate = Trajectory(truth.t_s, truth.positions_xyz * [1.02, 1.0, 1.0], truth.orientations_quat_xyzw)
    d = accuracy_summary(estimate, truth).to_json_dict()
    assert d["drift_percent"] == pytest.approx(2.0, abs=1e-10)
    assert d["ate_rmse_m"] == trajectory_metrics(estimate, truth).ate_rmse_m
    assert d["ate_aligned_rmse_m"] == ate_aligned_rmse_m(estimate, truth)
    assert d["rpe"] == relative_pose_errors(estimate, truth, 10.0).summary().to_json_dict()
    assert d["rpe"]["delta_m"] == 10.0


def long_truth(n: int = 1500) -> Trajectory:
    """60 m of a winding path with height change, roll and pitch: long enough for many 10 m pairs."""
    t = np.linspace(0.0, 60.0, n)
    heading = 0.6 * np.sin(0.08 * t)
    speed = 1.0 + 0.3 * np.sin(0.21 * t)
    dt = np.diff(t, prepend=t[0])
    x = np.cumsum(speed * np.cos(heading) * dt)
    y = np.cumsum(speed * np.sin(heading) * dt)
    z = 0.4 * np.sin(0.15 * t)
    rpy = np.stack([0.03 * np.sin(0.7 * t), 0.05 * np.cos(0.4 * t), heading], axis=1)
    return Trajectory(t, np.stack([x, y, z], axis=1), Rotation.from_euler("xyz", rpy).as_quat())


def test_ate_and_rpe_match_evo_on_the_same_tum_files(tmp_path):
    """Our anchored and aligned ATE and our RPE over 10 m, against evo's APE (``--align`` off and on) and
    RPE (10 m, all pairs, pairs from the reference, our 1 % tolerance), read from the TUM files the
    library writes. Agreement to 1e-6 m (and 1e-6 deg)."""
    evo_metrics = pytest.importorskip("evo.core.metrics", reason="evo is not installed (pip install evo)")
    evo_sync = pytest.importorskip("evo.core.sync")
    file_interface = pytest.importorskip("evo.tools.file_interface")
    from dem_graph.io.tum import read_tum, write_tum

    truth = long_truth()
    # the estimate: every other truth time, with a random-walk drift in position and heading, and white noise
    rng = np.random.default_rng(11)
    t = truth.t_s[::2]
    T = truth.at(t)
    drift = np.cumsum(rng.normal(0.0, 0.01, (len(t), 3)), axis=0) + rng.normal(0.0, 0.02, (len(t), 3))
    R_err = Rotation.from_rotvec(np.cumsum(rng.normal(0.0, 0.002, (len(t), 3)), axis=0)).as_matrix()
    estimate = Trajectory.from_poses(t, make_pose(T[:, :3, :3] @ R_err, T[:, :3, 3] + drift))
    write_tum(tmp_path / "truth.tum", truth)
    write_tum(tmp_path / "estimate.tum", estimate)

    ref = file_interface.read_tum_trajectory_file(str(tmp_path / "truth.tum"))
    est = file_interface.read_tum_trajectory_file(str(tmp_path / "estimate.tum"))
    ref, est = evo_sync.associate_trajectories(ref, est)
    assert est.num_poses == len(t)

    def ape(aligned: bool) -> float:
        e = copy.deepcopy(est)
        if aligned:
            e.align(ref, correct_scale=False)
        metric = evo_metrics.APE(evo_metrics.PoseRelation.translation_part)
        metric.process_data((ref, e))
        return metric.get_statistic(evo_metrics.StatisticsType.rmse)

    def rpe(relation) -> tuple[float, int]:
        metric = evo_metrics.RPE(relation, delta=10.0, delta_unit=evo_metrics.Unit.meters, rel_delta_tol=0.01, all_pairs=True, pairs_from_reference=True)
        metric.process_data((ref, est))
        return metric.get_statistic(evo_metrics.StatisticsType.rmse), len(metric.error)

    truth_back, estimate_back = read_tum(tmp_path / "truth.tum"), read_tum(tmp_path / "estimate.tum")
    ours = accuracy_summary(estimate_back, truth_back)
    assert ours.ate_rmse_m == pytest.approx(ape(aligned=False), abs=1e-6)
    assert ours.ate_aligned_rmse_m == pytest.approx(ape(aligned=True), abs=1e-6)
    evo_translation, evo_pairs = rpe(evo_metrics.PoseRelation.translation_part)
    evo_rotation, _ = rpe(evo_metrics.PoseRelation.rotation_angle_deg)
    assert ours.rpe.pairs == evo_pairs > 500
    assert ours.rpe.translation_rmse_m == pytest.approx(evo_translation, abs=1e-6)
    assert ours.rpe.rotation_rmse_deg == pytest.approx(evo_rotation, abs=1e-6)
    # the noise is big enough that the numbers mean something
    assert ours.ate_rmse_m > 0.05 and ours.rpe.translation_rmse_m > 0.02
