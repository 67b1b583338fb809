"""The per-frame pose update against known poses and points."""

from __future__ import annotations

import numpy as np
import pytest

from dem_graph.estimators.pose_update import update_pose
from dem_graph.geometry.lie import local, retract
from dem_graph.geometry.rig import default_rig
from dem_graph.geometry.se3 import invert, make_pose, rotation_from_rpy, transform_points


def _scene(rng, n=60):
    rig = default_rig()
    T_true = make_pose(rotation_from_rpy(0.02, -0.01, 0.4), [12.0, -3.0, 0.2])
    p_body = np.column_stack([rng.uniform(2.5, 6.0, n), rng.uniform(-1.5, 1.5, n), rng.uniform(-0.2, 0.2, n)])
    X = transform_points(T_true, p_body)
    return rig, T_true, X


def _pixels(rig, T, X):
    uv, in_front = rig.camera_model.project(transform_points(invert(T @ rig.T_body_cam), X))
    assert in_front.all()
    return uv


def test_noiseless_pixels_give_the_true_pose():
    rng = np.random.default_rng(0)
    rig, T_true, X = _scene(rng)
    # a weak prior 0.03 rad and 0.03 m off: the MAP is pulled towards it by about P_post P0^-1,
    # below 1e-8 here, so the pixels alone decide
    P0 = np.eye(6) * 100.0
    T_prior = retract(T_true, np.array([0.01, -0.008, 0.012, 0.03, -0.02, 0.01]))
    T, P = update_pose(T_prior, P0, X, np.zeros((len(X), 3, 3)), _pixels(rig, T_true, X), rig.camera_model, rig.T_body_cam, 1.0)
    np.testing.assert_allclose(local(T_true, T), 0.0, atol=1e-8)
    assert np.all(np.linalg.eigvalsh(P) > 0)


def test_pose_error_is_consistent_with_its_covariance():
    """Prior and pixels drawn from the assumed distributions (points with uncertainty too): the NEES
    over 300 trials averages 6 (chi-square, 6 dof), within 3 standard errors (sd 2*sqrt(3) / sqrt(300))."""
    rng = np.random.default_rng(1)
    rig, T_true, X_true = _scene(rng, n=40)
    P0 = np.diag([2e-5] * 3 + [1e-4] * 3)
    Sigma = np.tile(np.diag([1e-4, 1e-4, 4e-4]), (len(X_true), 1, 1))
    nees = []
    for _ in range(300):
        T_prior = retract(T_true, rng.multivariate_normal(np.zeros(6), P0))
        X = X_true + rng.multivariate_normal(np.zeros(3), Sigma[0], size=len(X_true))
        z = _pixels(rig, T_true, X_true) + rng.normal(0, 1.0, (len(X_true), 2))
        T, P = update_pose(T_prior, P0, X, Sigma, z, rig.camera_model, rig.T_body_cam, 1.0, robust=False)
        xi = local(T, T_true)
        nees.append(xi @ np.linalg.solve(P, xi))
    assert abs(np.mean(nees) - 6.0) < 3 * np.sqrt(12.0 / 300)


def test_a_wrong_match_is_down_weighted():
    rng = np.random.default_rng(2)
    rig, T_true, X = _scene(rng)
    z = _pixels(rig, T_true, X) + rng.normal(0, 0.5, (len(X), 2))
    z[:3] += 40.0  # three wrong matches, 40 px off
    P0 = np.diag([1e-4] * 3 + [1e-3] * 3)
    Sigma = np.zeros((len(X), 3, 3))
    T_rob, _ = update_pose(T_true, P0, X, Sigma, z, rig.camera_model, rig.T_body_cam, 0.5, robust=True)
    T_ls, _ = update_pose(T_true, P0, X, Sigma, z, rig.camera_model, rig.T_body_cam, 0.5, robust=False)
    err_rob = np.linalg.norm(local(T_true, T_rob)[3:])
    err_ls = np.linalg.norm(local(T_true, T_ls)[3:])
    assert err_rob < 0.5 * err_ls


def test_mismatched_lengths_are_refused():
    rig = default_rig()
    with pytest.raises(ValueError):
        update_pose(np.eye(4), np.eye(6), np.zeros((3, 3)), np.zeros((2, 3, 3)), np.zeros((3, 2)), rig.camera_model, rig.T_body_cam, 1.0)
