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


@pytest.mark.parametrize("robust", [True, False])
def test_the_compiled_normal_equations_are_the_projections_ones(robust):
    """The pose update's compiled per-point loop (projection_kernel.normal_equations) gives the normal
    equations of the numpy formulation (project_with_jacobians, R_i = sigma^2 I + H_x Sigma H_x^T,
    Huber weights, sum H^T W H and H^T W r) to 1e-9 relative, with lens distortion, points behind
    the camera and pixels that are NaN left out, and outliers in the Huber kernel's linear part."""
    from dem_graph.estimators.pose_update import HUBER_K, project_with_jacobians
    from dem_graph.estimators.projection_kernel import normal_equations
    from dem_graph.geometry.camera import PinholeCamera

    rng = np.random.default_rng(11)
    rig, T_true, X = _scene(rng, n=80)
    cam = PinholeCamera(width_px=800, height_px=600, fx_px=560.0, fy_px=555.0, cx_px=399.5, cy_px=301.0, distortion=(-0.05, 0.01, 0.001, -0.0005, 0.002))
    X[:3] = transform_points(T_true, np.array([[-2.0, 0.1, 0.0], [-1.0, -0.3, 0.2], [-5.0, 1.0, -0.1]]))  # behind the camera
    T = retract(T_true, np.array([0.004, -0.003, 0.006, 0.02, -0.01, 0.005]))
    A_ = rng.normal(size=(len(X), 3, 3)) * 0.01
    Sigma = A_ @ np.swapaxes(A_, 1, 2) + 1e-6 * np.eye(3)
    uv_true, _, _, _ = project_with_jacobians(T_true, X, cam, rig.T_body_cam)
    z = uv_true + rng.normal(scale=0.5, size=uv_true.shape)
    z[5:15] += 8.0  # outliers
    z[20] = np.nan
    sigma_px = 0.7
    # the numpy formulation
    uv, Hp, Hx, in_front = project_with_jacobians(T, X, cam, rig.T_body_cam)
    ok = in_front & np.isfinite(z).all(axis=1)
    W = np.linalg.inv(sigma_px**2 * np.eye(2) + Hx[ok] @ Sigma[ok] @ np.swapaxes(Hx[ok], 1, 2))
    r = z[ok] - uv[ok]
    if robust:
        d = np.sqrt(np.einsum("ni,nij,nj->n", r, W, r))
        W = W * np.where(d <= HUBER_K, 1.0, HUBER_K / d)[:, None, None]
        assert np.sum(d > HUBER_K) >= 10
    HtW = np.swapaxes(Hp[ok], 1, 2) @ W
    A_ref, b_ref = np.einsum("nij,njk->ik", HtW, Hp[ok]), np.einsum("nij,nj->i", HtW, r)
    T_cam_body = invert(rig.T_body_cam)
    A, b, used = normal_equations(T[:3, :3].copy(), T[:3, 3].copy(), X, Sigma, z, T_cam_body[:3, :3].copy(), T_cam_body[:3, 3].copy(), cam.intrinsics_array, sigma_px, HUBER_K if robust else 0.0)
    assert used == ok.sum() == len(X) - 4
    np.testing.assert_allclose(A, A_ref, rtol=1e-9, atol=1e-9 * np.abs(A_ref).max())
    np.testing.assert_allclose(b, b_ref, rtol=1e-9, atol=1e-9 * np.abs(b_ref).max())


def test_the_pose_kernel_a_frame_runs_is_compiled_before_it(monkeypatch):
    """After ``compile_kernel`` (run when an :class:`OnlineFilter` is made) a frame's pose update,
    robust or not, runs the compiled loop with the signature it already has: nothing is compiled in
    the first frame. A fresh dispatcher of the same loop, so that no other test's call counts."""
    import numba

    from dem_graph.estimators import pose_update, projection_kernel

    fresh = numba.njit(nogil=True)(projection_kernel.normal_equations.py_func)
    monkeypatch.setattr(projection_kernel, "normal_equations", fresh)
    monkeypatch.setattr(pose_update, "normal_equations", fresh)
    projection_kernel.compile_kernel()
    assert len(fresh.signatures) == 1
    rig, T_true, X = _scene(np.random.default_rng(3))
    for robust in (True, False):
        T, _ = update_pose(T_true, 1e-4 * np.eye(6), X, np.zeros((len(X), 3, 3)), _pixels(rig, T_true, X), rig.camera_model, rig.T_body_cam, 1.0, robust=robust)
    assert len(fresh.signatures) == 1
    assert np.abs(local(T_true, T)).max() < 1e-9
