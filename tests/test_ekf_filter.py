"""The EKF's algebra: Jacobians against numerical derivatives, sequential = batch, Lie helpers."""

from __future__ import annotations

import copy

import gtsam
import numpy as np
import pytest

from dem_graph.estimators.ekf_filter import EkfState, point_cols
from dem_graph.geometry.lie import adjoint, local, retract, scale_increment
from dem_graph.geometry.rig import default_rig
from dem_graph.geometry.se3 import make_pose, rotation_from_rpy


def _random_pose(rng):
    return make_pose(rotation_from_rpy(*rng.uniform(-0.3, 0.3, 3)), rng.uniform(-2, 2, 3))


def _state_with_points(rng, n=5):
    rig = default_rig()
    T = make_pose(rotation_from_rpy(0.02, -0.03, 0.3), [1.0, 2.0, 0.1])
    st = EkfState(T, np.eye(6) * 1e-3, np.zeros(6), np.eye(6) * 0.01)
    # points on the ground 3-6 m ahead of the body, seen by the camera
    p_body = np.column_stack([rng.uniform(3, 6, n), rng.uniform(-1, 1, n), rng.uniform(-0.1, 0.1, n)])
    st.add_points(np.arange(n), p_body, np.array([np.eye(3) * 0.01] * n))
    # make the covariance a generic SPD matrix
    A = rng.normal(size=(st.dim, st.dim)) * 0.01
    st.P = st.P + A @ A.T
    return st, rig


def test_lie_helpers_match_gtsam():
    rng = np.random.default_rng(0)
    for _ in range(10):
        T = _random_pose(rng)
        xi = rng.normal(size=6) * 0.1
        np.testing.assert_allclose(adjoint(T), gtsam.Pose3(T).AdjointMap(), atol=1e-12)
        np.testing.assert_allclose(local(T, retract(T, xi)), xi, atol=1e-12)
        # the decoupled retraction agrees with gtsam's to first order
        np.testing.assert_allclose(retract(T, 1e-4 * xi), gtsam.Pose3(T).retract(1e-4 * xi).matrix(), atol=1e-8)
    U = _random_pose(rng)
    np.testing.assert_allclose(scale_increment(U, 1.0), U, atol=1e-12)
    half = scale_increment(U, 0.5)
    np.testing.assert_allclose(half[:3, :3] @ half[:3, :3], U[:3, :3], atol=1e-12)


def test_observation_jacobians_match_numerical_derivatives():
    rng = np.random.default_rng(1)
    st, rig = _state_with_points(rng)
    cam = rig.camera_model
    idx = np.arange(st.n_points)
    uv, Hp, Hx, in_front, _ = st.observe(idx, cam, rig.T_body_cam)
    assert in_front.all()
    eps = 1e-6
    for k in range(6):
        d = np.zeros(6)
        d[k] = eps
        plus, minus = copy.deepcopy(st), copy.deepcopy(st)
        plus.T_world_body = retract(st.T_world_body, d)
        minus.T_world_body = retract(st.T_world_body, -d)
        num = (plus.observe(idx, cam, rig.T_body_cam)[0] - minus.observe(idx, cam, rig.T_body_cam)[0]) / (2 * eps)
        np.testing.assert_allclose(Hp[:, :, k], num, atol=1e-4, rtol=1e-6)
    for k in range(3):
        plus, minus = copy.deepcopy(st), copy.deepcopy(st)
        plus.points_xyz = st.points_xyz.copy()
        minus.points_xyz = st.points_xyz.copy()
        plus.points_xyz[:, k] += eps
        minus.points_xyz[:, k] -= eps
        num = (plus.observe(idx, cam, rig.T_body_cam)[0] - minus.observe(idx, cam, rig.T_body_cam)[0]) / (2 * eps)
        np.testing.assert_allclose(Hx[:, :, k], num, atol=1e-4, rtol=1e-6)


def test_sequential_updates_equal_one_batch_update():
    """PTPM's lazily accumulated sequential updates give exactly the batch (GM) posterior for the same
    linearisation: the Kalman filter processes independent measurements in any grouping."""
    rng = np.random.default_rng(2)
    st, rig = _state_with_points(rng, n=6)
    uv, Hp, Hx, _, _ = st.observe(np.arange(st.n_points), rig.camera_model, rig.T_body_cam)
    z = uv + rng.normal(size=uv.shape) * 2.0
    R = 1.3
    batch, seq = copy.deepcopy(st), copy.deepcopy(st)
    batch.batch_update(np.arange(st.n_points), z - uv, Hp, Hx, R)
    seq.begin_sequential(st.n_points)
    for i in [3, 0, 5, 1, 4, 2]:
        d_pose, d_point = seq.correction(i)
        y = z[i] - (uv[i] + Hp[i] @ d_pose + Hx[i] @ d_point)
        S = seq.sequential_innovation_covariance(i, Hp[i], Hx[i], R)
        seq.sequential_update(i, y, Hp[i], Hx[i], S)
    seq.end_sequential()
    np.testing.assert_allclose(seq.P, batch.P, atol=1e-12)
    np.testing.assert_allclose(seq.T_world_body, batch.T_world_body, atol=1e-12)
    np.testing.assert_allclose(seq.points_xyz, batch.points_xyz, atol=1e-12)


def test_innovation_covariances_vectorised_equal_per_point():
    rng = np.random.default_rng(3)
    st, rig = _state_with_points(rng)
    _, Hp, Hx, _, _ = st.observe(np.arange(st.n_points), rig.camera_model, rig.T_body_cam)
    S_all = st.innovation_covariances(Hp, Hx, 0.7)
    st.begin_sequential(st.n_points)
    for i in range(st.n_points):
        np.testing.assert_allclose(S_all[i], st.sequential_innovation_covariance(i, Hp[i], Hx[i], 0.7), atol=1e-12)
    st.end_sequential()


def test_added_point_covariance_follows_pose_uncertainty():
    """A point added at p_body gets X = T p_body: its covariance is J P_pose J^T + R Sigma R^T, and
    its cross-covariance with the pose is J P_pose (checked by Monte Carlo over the pose)."""
    rng = np.random.default_rng(4)
    T = make_pose(rotation_from_rpy(0.0, 0.05, 0.7), [3.0, -1.0, 0.2])
    P_pose = np.diag([1e-4, 2e-4, 3e-4, 1e-2, 2e-2, 5e-3])
    st = EkfState(T, P_pose, np.zeros(6), np.eye(6) * 0.01)
    p_body = np.array([[4.0, 0.5, -0.2]])
    Sigma = np.eye(3)[None] * 1e-4
    st.add_points(np.array([7]), p_body, Sigma)
    samples = []
    for _ in range(20000):
        xi = rng.multivariate_normal(np.zeros(6), P_pose)
        Ts = retract(T, xi)
        samples.append(Ts[:3, :3] @ (p_body[0] + rng.multivariate_normal(np.zeros(3), Sigma[0])) + Ts[:3, 3])
    mc = np.cov(np.array(samples).T)
    C = st.point_covariance(0)
    # standard error of a sample covariance element: sqrt((C_ii C_jj + C_ij^2) / N); allow 4 of them
    se = np.sqrt((np.outer(np.diag(C), np.diag(C)) + C**2) / len(samples))
    assert np.all(np.abs(C - mc) < 4 * se)
    assert st.point_ids.tolist() == [7] and point_cols(0) == slice(12, 15)


def test_remove_points_keeps_the_rest_consistent():
    rng = np.random.default_rng(5)
    st, _ = _state_with_points(rng, n=4)
    P_before, X_before = st.P.copy(), st.points_xyz.copy()
    st.remove_points(np.array([False, True, False, True]))
    assert st.point_ids.tolist() == [0, 2]
    keep = np.r_[0:12, 12:15, 18:21]
    np.testing.assert_array_equal(st.P, P_before[np.ix_(keep, keep)])
    np.testing.assert_array_equal(st.points_xyz, X_before[[0, 2]])


def test_sequential_mode_guards_structure_changes():
    st, _ = _state_with_points(np.random.default_rng(6), n=2)
    st.begin_sequential(2)
    with pytest.raises(RuntimeError):
        st.remove_points(np.array([True, False]))
    st.end_sequential()
