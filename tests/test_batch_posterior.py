"""isam2-batch's own posterior: each frame's pose marginal from the batch's final graph, and the
height and pitch sigmas it gives (:mod:`dem_graph.evaluation.posterior`), against closed forms."""

from __future__ import annotations

import logging

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from dem_graph.estimators import batch, batch_log
from dem_graph.estimators.base import EstimatorResult, FrameRecord
from dem_graph.estimators.measurement_log import MeasurementLog
from dem_graph.evaluation.posterior import height_sigma_m, pitch_sigma_rad, posterior_summary
from dem_graph.evaluation.trajectory_metrics import nees_summary, pose_nees
from dem_graph.geometry.lie import adjoint, so3_exp
from dem_graph.geometry.se3 import invert
from dem_graph.pipeline import RunConfig, run_estimator
from dem_graph.sim.scenarios import scenario


def _pose(yaw: float, pitch: float, roll: float, t=(1.0, 2.0, 3.0)) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("ZYX", [yaw, pitch, roll]).as_matrix()
    T[:3, 3] = t
    return T


def _spd(rng, scales) -> np.ndarray:
    """A random symmetric positive definite matrix with the sigmas ``scales`` and correlations."""
    A = rng.normal(size=(len(scales), len(scales)))
    C = A @ A.T + len(scales) * np.eye(len(scales))
    d = 1 / np.sqrt(np.diag(C))
    return np.outer(scales, scales) * (d[:, None] * C * d[None, :])


# --- the height and pitch sigmas -----------------------------------------------------------------


def test_height_and_pitch_sigma_match_their_closed_forms():
    """R = Rz(yaw) Ry(pitch) Rx(roll), a diagonal covariance (body frame): world z = third row of R
    times the body translation, so sigma_z^2 = sin^2(p) sx^2 + cos^2(p) sin^2(r) sy^2 + cos^2(p) cos^2(r) sz^2;
    the ZYX pitch moves by cos(r) w_y - sin(r) w_z, so sigma^2 = cos^2(r) by^2 + sin^2(r) bz^2
    (whatever the yaw and pitch). Exact to rounding (1e-12 relative)."""
    yaw, pitch, roll = 0.7, np.radians(12.0), np.radians(-25.0)
    sr, sx, sy, sz = (0.01, 0.02, 0.03), 0.1, 0.2, 0.3
    P = np.diag([*(np.square(sr)), sx**2, sy**2, sz**2])
    T = _pose(yaw, pitch, roll)
    sp, cp, s_r, c_r = np.sin(pitch), np.cos(pitch), np.sin(roll), np.cos(roll)
    h = height_sigma_m(T[None], P[None])
    assert h.shape == (1,)
    assert h[0] == pytest.approx(np.sqrt(sp**2 * sx**2 + cp**2 * s_r**2 * sy**2 + cp**2 * c_r**2 * sz**2), rel=1e-12)
    assert pitch_sigma_rad(T[None], P[None])[0] == pytest.approx(np.sqrt(c_r**2 * sr[1] ** 2 + s_r**2 * sr[2] ** 2), rel=1e-12)
    # level: the body's own z sigma and its rotation about y
    assert height_sigma_m(np.eye(4)[None], P[None])[0] == pytest.approx(sz, rel=1e-12)
    assert pitch_sigma_rad(np.eye(4)[None], P[None])[0] == pytest.approx(sr[1], rel=1e-12)


def test_height_and_pitch_sigma_are_the_linearised_sigmas_of_a_right_perturbation():
    """For a random pose and a full covariance (correlated rotation and translation): the sigma of
    the origin's world z and of the ZYX pitch of ``T @ Exp(xi)``, from their finite-difference
    gradients in ``xi``, are the functions' (1e-6 relative): the translation part alone counts for
    the height, the rotation part alone for the pitch."""
    rng = np.random.default_rng(4)
    T = _pose(2.1, np.radians(-20.0), np.radians(30.0), t=(5.0, -3.0, 1.0))
    P = _spd(rng, [0.02, 0.01, 0.03, 0.2, 0.1, 0.3])

    def exp_right(xi):
        E = np.eye(4)
        E[:3, :3] = so3_exp(xi[:3])
        E[:3, 3] = xi[3:]  # first order is all that counts at xi = 0
        return T @ E

    def z(xi):
        return exp_right(xi)[2, 3]

    def pitch(xi):
        return Rotation.from_matrix(exp_right(xi)[:3, :3]).as_euler("ZYX")[1]

    eps = 1e-6
    for f, sigma in ((z, height_sigma_m), (pitch, pitch_sigma_rad)):
        g = np.array([(f(eps * e) - f(-eps * e)) / (2 * eps) for e in np.eye(6)])
        assert sigma(T[None], P[None])[0] == pytest.approx(np.sqrt(g @ P @ g), rel=1e-6)


def test_posterior_summary_is_the_rms_over_frames_and_the_last_frame():
    sig = np.array([0.1, 0.2, 0.4])
    T = np.repeat(np.eye(4)[None], 3, axis=0)
    P = np.zeros((3, 6, 6))
    P[:, 5, 5] = sig**2  # the height
    P[:, 1, 1] = (sig / 10) ** 2  # the pitch
    s = posterior_summary(T, P)
    assert s.frames == 3
    assert s.height_sigma_rms_m == pytest.approx(np.sqrt(np.mean(sig**2)), rel=1e-12)
    assert s.height_sigma_end_m == pytest.approx(0.4, rel=1e-12)
    assert s.pitch_sigma_rms_rad == pytest.approx(np.sqrt(np.mean(sig**2)) / 10, rel=1e-12)
    assert s.pitch_sigma_end_deg == pytest.approx(np.degrees(0.04), rel=1e-12)
    with pytest.raises(ValueError, match="covariances"):
        height_sigma_m(T, P[:2])


# --- the batch's marginals -----------------------------------------------------------------------


def _odometry_chain(rng, motions):
    """A measurement log of odometry only (no landmark), its start pose and prior, and its poses."""
    mlog = MeasurementLog()
    T0 = _pose(0.3, 0.05, -0.02, t=(0.0, 0.0, 0.5))
    P0 = _spd(rng, [1e-3, 1e-3, 2e-3, 0.01, 0.01, 0.02])
    poses, T = [], T0
    for f, U in enumerate(motions):
        Q = _spd(rng, [2e-3, 3e-3, 1e-3, 0.02, 0.01, 0.01])
        mlog.add_frame(0.1 * (f + 1), U, Q, np.zeros(0, dtype=int), np.zeros((0, 2)))
        T = T @ U
        poses.append(T)
    return mlog, T0, P0, np.array(poses)


def _smooth(mlog, T0, P0, poses, **kwargs):
    return batch.smooth_batch(mlog, scenario("smoke", seed=3).rig, T0, P0, poses, {}, sigma_px=1.0, sigma_seed_px=1.0, **kwargs)


def test_batch_marginals_of_a_still_chain_are_the_prior_plus_each_motion():
    """Odometry only, the vehicle still (every motion the identity): frame k's pose is the start's
    composed with k + 1 motions, so its marginal is P0 + Q_0 + ... + Q_k (1e-6 relative)."""
    rng = np.random.default_rng(0)
    mlog, T0, P0, poses = _odometry_chain(rng, [np.eye(4)] * 6)
    res = _smooth(mlog, T0, P0, poses)
    assert res.pose_covariances.shape == (6, 6, 6) and not res.marginals_failed
    expected = P0 + np.cumsum(np.array(mlog.motion_covariance), axis=0)
    np.testing.assert_allclose(res.pose_covariances, expected, rtol=1e-6, atol=0)


def test_batch_marginals_of_a_moving_chain_follow_the_adjoint():
    """Odometry only, turning and climbing: ``X_k = X_(k-1) U_k`` with right perturbations gives
    ``P_k = Ad(U_k^-1) P_(k-1) Ad(U_k^-1)^T + Q_k`` exactly (the chain has no loop, the measurements
    agree, so the linearisation at the solution is this propagation): 1e-6 relative, per element
    against sqrt(P_ii P_jj). 60 frames: the marginals are taken in chunks of consecutive poses
    (``MARGINAL_CHUNK``), and the chain spans more than two."""
    rng = np.random.default_rng(1)
    motions = []
    assert 60 > 2 * batch.MARGINAL_CHUNK
    for _ in range(60):
        U = np.eye(4)
        U[:3, :3] = so3_exp(rng.normal(scale=0.1, size=3))
        U[:3, 3] = [1.0, 0.1, 0.05] + rng.normal(scale=0.05, size=3)
        motions.append(U)
    mlog, T0, P0, poses = _odometry_chain(rng, motions)
    res = _smooth(mlog, T0, P0, poses)
    np.testing.assert_allclose(res.poses, poses, atol=1e-9)
    P, expected = P0, []
    for U, Q in zip(motions, mlog.motion_covariance):
        A = adjoint(invert(U))
        P = A @ P @ A.T + Q
        expected.append(P)
    expected = np.array(expected)
    scale = np.sqrt(np.einsum("nii,njj->nij", expected, expected))
    assert np.max(np.abs(res.pose_covariances - expected) / scale) < 1e-6
    # the height sigma grows along the chain, as the propagation's does
    h = height_sigma_m(res.poses, res.pose_covariances)
    np.testing.assert_allclose(h, height_sigma_m(poses, expected), rtol=1e-6)


def _refuse(*args):
    raise RuntimeError("Indeterminant linear system detected while working near variable x1")


def test_batch_marginals_by_qr_where_cholesky_refuses(monkeypatch, caplog):
    """Cholesky's elimination refusing (the IMU's stiff bias walk can make its pivots fail on a
    well-posed system): QR's gives the still chain's marginals, P0 + Q_0 + ... + Q_k (1e-6
    relative), says so in the log, and the run counts it."""
    rng = np.random.default_rng(0)
    mlog, T0, P0, poses = _odometry_chain(rng, [np.eye(4)] * 6)
    monkeypatch.setattr(batch.gtsam, "Marginals", _refuse)
    with caplog.at_level(logging.INFO, logger="dem_graph.estimators.batch"):
        res = _smooth(mlog, T0, P0, poses)
    assert res.marginals_by_qr and not res.marginals_failed
    assert "the marginals by QR instead" in caplog.text and "no marginal covariances" not in caplog.text
    expected = P0 + np.cumsum(np.array(mlog.motion_covariance), axis=0)
    np.testing.assert_allclose(res.pose_covariances, expected, rtol=1e-6, atol=0)
    frames = [FrameRecord(0.1 * k, np.eye(4), np.eye(6), 0, 0, {}) for k in range(6)]
    counted = res.apply_to(EstimatorResult("isam2-batch", frames=frames), {})
    assert counted.counters["batch_marginals_by_qr"] == 1 and "batch_marginals_failed" not in counted.counters


def test_batch_without_marginals_or_when_gtsam_refuses_keeps_the_online_covariances(monkeypatch, caplog):
    """``marginals=False``: none computed. gtsam refusing (an indeterminate system) with Cholesky and
    with QR: a warning, no covariances, the smoothing's result kept; ``apply_to`` then leaves the
    online covariances and counts the failure."""
    rng = np.random.default_rng(2)
    mlog, T0, P0, poses = _odometry_chain(rng, [np.eye(4)] * 3)
    off = _smooth(mlog, T0, P0, poses, marginals=False)
    assert off.pose_covariances is None and not off.marginals_failed

    monkeypatch.setattr(batch.gtsam, "Marginals", _refuse)
    monkeypatch.setattr(batch, "_marginals_by_qr", _refuse)
    with caplog.at_level(logging.WARNING, logger="dem_graph.estimators.batch"):
        failed = _smooth(mlog, T0, P0, poses)
    assert failed.pose_covariances is None and failed.marginals_failed
    assert "no marginal covariances" in caplog.text
    np.testing.assert_allclose(failed.poses, poses, atol=1e-9)
    online = [np.eye(6) * (k + 1) for k in range(3)]
    res = EstimatorResult("isam2-batch", frames=[FrameRecord(0.1 * k, np.eye(4), online[k], 0, 0, {}) for k in range(3)])
    res = failed.apply_to(res, {})
    assert all(np.array_equal(f.pose_covariance, c) for f, c in zip(res.frames, online))
    assert res.counters["batch_marginals_failed"] == 1 and "batch_marginals_ms" not in res.counters


def test_batch_run_gives_its_frames_its_own_marginals(smoke_log, monkeypatch):
    """On `smoke`, the run's frames carry the batch's marginals, not the online pass's covariances,
    and the run's pose NEES is computed from them: the same summary as recomputed from the batch's
    poses and covariances against the truth (1e-12), finite and positive."""
    seen = {}
    real_apply = batch.BatchResult.apply_to

    def keep(self, res, landmark_of):
        seen["batch"] = self
        seen["online"] = np.array([f.pose_covariance for f in res.frames])
        return real_apply(self, res, landmark_of)

    monkeypatch.setattr(batch.BatchResult, "apply_to", keep)
    run = run_estimator(smoke_log, RunConfig.model_validate({"estimator": "isam2-batch"}), with_dem=False)
    assert run.error is None
    b, online = seen["batch"], seen["online"]
    P = run.estimator.pose_covariances()
    assert P.shape == (len(run.estimator.frames), 6, 6)
    np.testing.assert_array_equal(P, b.pose_covariances)
    # not the online pass's: the batch's posterior is much tighter (every frame's observations, all
    # at once; measured: the median ratio of the traces 0.02)
    assert np.median(np.trace(P, axis1=1, axis2=2) / np.trace(online, axis1=1, axis2=2)) < 0.2
    assert run.metrics.events["batch_marginals_ms"] >= 0 and "batch_marginals_failed" not in run.metrics.events
    t = np.array([f.t_s for f in run.estimator.frames])
    nees = pose_nees(b.poses, smoke_log.ground_truth.trajectory.at(t), b.pose_covariances)
    assert np.all(np.isfinite(nees)) and np.all(nees > 0)
    assert run.metrics.pose_nees.median == pytest.approx(nees_summary(nees).median, rel=1e-12)


def test_batch_log_passes_the_option(smoke_log, monkeypatch):
    """``isam2.batch_marginals: false`` reaches the smoothing (and the frames keep the online pass's covariances)."""
    seen = {}

    def keep(*args, **kwargs):
        seen.update(kwargs)
        return batch.smooth_batch(*args, **kwargs)

    monkeypatch.setattr(batch_log, "smooth_batch", keep)
    config = RunConfig.model_validate({"estimator": "isam2-batch", "isam2": {"batch_marginals": False}, "max_frames": 12})
    run = run_estimator(smoke_log, config, with_dem=False)
    assert seen["marginals"] is False
    assert "batch_marginals_ms" not in run.metrics.events
