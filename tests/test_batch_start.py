"""The batch's start (:func:`~dem_graph.estimators.batch_start.fit_landmarks`): the landmarks fitted
to held poses, against the truth of exact measurements and against gtsam's optimum of the same cost."""

from __future__ import annotations

import gtsam
import numpy as np
from gtsam.symbol_shorthand import L, X

from dem_graph.estimators.batch_start import fit_landmarks
from dem_graph.estimators.graph_factors import ProjectionFactors, calibration
from dem_graph.geometry.camera import PinholeCamera
from dem_graph.geometry.se3 import invert, make_pose, rotation_from_rpy, transform_points

CAMERA = PinholeCamera(800, 600, 600.0, 610.0, 400.0, 300.0, (-0.12, 0.03, 0.001, -0.0005, 0.0))
# the camera 1.5 m up, looking ahead and 30 degrees down (body: x ahead, z up; camera: z along the view)
T_BODY_CAM = make_pose(rotation_from_rpy(-np.pi / 2 - np.radians(30), 0.0, -np.pi / 2), np.array([0.2, 0.0, 1.5]))


def _scene(rng, n_points=60, n_poses=12):
    """Poses 0.1 m apart along x with some turn and pitch, ground points 3-6 m ahead of the first;
    each point seen from every pose that has it in the image, seeded at one of them."""
    poses = np.array([make_pose(rotation_from_rpy(0.01 * np.sin(k), 0.02 * np.cos(k), 0.03 * k), np.array([0.1 * k, 0.02 * k, 0.01 * k])) for k in range(n_poses)])
    X_true = np.column_stack([rng.uniform(3.0, 6.0, n_points), rng.uniform(-1.5, 1.5, n_points), rng.normal(0.0, 0.05, n_points)])
    obs_pose, obs_landmark, uv = [], [], []
    for k, T in enumerate(poses):
        p_cam = transform_points(invert(T @ T_BODY_CAM), X_true)
        px, front = CAMERA.project(p_cam)
        seen = front & CAMERA.in_image(px)
        obs_pose += [k] * int(seen.sum())
        obs_landmark += np.flatnonzero(seen).tolist()
        uv.append(px[seen])
    seed_pose = rng.integers(0, n_poses, n_points)
    seed_p_body = np.array([transform_points(invert(poses[k]), X_true[j][None])[0] for j, k in enumerate(seed_pose)])
    seed_Sigma = np.array([np.diag(rng.uniform(0.01, 0.2, 3) ** 2) for _ in range(n_points)])
    return poses, X_true, np.array(obs_pose), np.array(obs_landmark), np.concatenate(uv), seed_pose, seed_p_body, seed_Sigma


def _refreshed(X_true, obs_pose, obs_lm, linked):
    """Each point of ``linked`` refreshed at pose 6: landmark ``n + i`` continues point ``linked[i]``
    (the same ground point), observed from there on; returns the landmarks' true positions, the
    observations' landmarks and the links."""
    n = len(X_true)
    late = np.isin(obs_lm, linked) & (obs_pose >= 6)
    obs_lm = np.where(late, n + np.searchsorted(linked, obs_lm), obs_lm)
    return np.concatenate([X_true, X_true[linked]]), obs_lm, np.column_stack([linked, n + np.arange(len(linked))])


def test_exact_measurements_give_the_true_landmarks_from_far_off():
    """Pixels, seeds and links all exact: from 0.3 m away, every landmark returns to its true
    position to 1e-6 m, the linked ones too (a refreshed patch: two landmarks, one point)."""
    rng = np.random.default_rng(3)
    poses, X_true, obs_pose, obs_lm, uv, seed_pose, seed_p, seed_S = _scene(rng)
    n = len(X_true)
    X_all, obs_lm, links = _refreshed(X_true, obs_pose, obs_lm, np.arange(10))
    start = X_all + rng.normal(0.0, 0.3 / np.sqrt(3), X_all.shape)
    got, iterations = fit_landmarks(start, poses, obs_pose, obs_lm, uv, 0.3, CAMERA, T_BODY_CAM, seed_pose, np.arange(n), seed_p, seed_S, links, np.full(len(links), 0.005))
    np.testing.assert_allclose(got, X_all, atol=1e-6)
    assert 1 < iterations < 10


def _gtsam_optimum(start, poses, obs_pose, obs_lm, uv, sigma_px, seed_pose, seed_lm, seed_p, seed_S, links, link_sigma):
    """The same cost in gtsam, the poses pinned: robust projection factors, each seed as a world prior
    with the covariance carried into the world frame, each link a BetweenFactorPoint3."""
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    pin = gtsam.noiseModel.Isotropic.Sigma(6, 1e-9)  # (a hard constraint is refused by the Cholesky elimination)
    for k, T in enumerate(poses):
        values.insert(X(k), gtsam.Pose3(T))
        graph.add(gtsam.PriorFactorPose3(X(k), gtsam.Pose3(T), pin))
    for j, p in enumerate(start):
        values.insert(L(j), gtsam.Point3(*p))
    projection = ProjectionFactors(calibration(CAMERA), T_BODY_CAM, robust=True)
    for k, j, z in zip(obs_pose, obs_lm, uv):
        graph.add(projection(X(int(k)), L(int(j)), z, sigma_px))
    for k, j, p, S in zip(seed_pose, seed_lm, seed_p, seed_S):
        R = poses[k][:3, :3]
        graph.add(gtsam.PriorFactorPoint3(L(int(j)), transform_points(poses[k], p[None])[0], gtsam.noiseModel.Gaussian.Covariance(R @ S @ R.T)))
    for (a, b), s in zip(links, link_sigma):
        graph.add(gtsam.BetweenFactorPoint3(L(int(a)), L(int(b)), gtsam.Point3(0.0, 0.0, 0.0), gtsam.noiseModel.Isotropic.Sigma(3, float(s))))
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(100)
    params.setRelativeErrorTol(1e-15)
    params.setAbsoluteErrorTol(1e-15)
    out = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
    return np.array([out.atPoint3(L(j)) for j in range(len(start))])


def test_noisy_measurements_give_gtsams_optimum_of_the_same_cost():
    """Pixels with 0.3 px noise and a tenth of them 5-20 px off (the Huber kernel at work), seeds
    off by their sigmas, ten refreshed points: the fit is gtsam's Levenberg-Marquardt optimum of the
    same cost, poses held, to 1e-6 m."""
    rng = np.random.default_rng(11)
    poses, X_true, obs_pose, obs_lm, uv, seed_pose, seed_p, seed_S = _scene(rng)
    n = len(X_true)
    uv = uv + rng.normal(0.0, 0.3, uv.shape)
    bad = rng.random(len(uv)) < 0.1
    uv[bad] += rng.uniform(5.0, 20.0, (int(bad.sum()), 2)) * rng.choice([-1, 1], (int(bad.sum()), 2))
    seed_p = seed_p + np.array([rng.multivariate_normal(np.zeros(3), S) for S in seed_S])
    X_all, obs_lm, links = _refreshed(X_true, obs_pose, obs_lm, np.arange(10))
    link_sigma = np.full(len(links), 0.005)
    start = X_all + rng.normal(0.0, 0.1, X_all.shape)
    args = (poses, obs_pose, obs_lm, uv, 0.3)
    got, _ = fit_landmarks(start, *args, CAMERA, T_BODY_CAM, seed_pose, np.arange(n), seed_p, seed_S, links, link_sigma, max_iterations=50, tol_m=1e-10)
    want = _gtsam_optimum(start, *args, seed_pose, np.arange(n), seed_p, seed_S, links, link_sigma)
    np.testing.assert_allclose(got, want, atol=1e-6)
    assert np.max(np.linalg.norm(got - X_all, axis=1)) > 1e-3  # (the noise moved them: not the truth again)


def test_a_landmark_without_information_stays_where_it_is():
    rng = np.random.default_rng(5)
    poses, X_true, obs_pose, obs_lm, uv, seed_pose, seed_p, seed_S = _scene(rng, n_points=5)
    start = np.concatenate([X_true, [[10.0, 20.0, 30.0]]])  # landmark 5: no observation, seed or link
    got, _ = fit_landmarks(start, poses, obs_pose, obs_lm, uv, 0.3, CAMERA, T_BODY_CAM, seed_pose, np.arange(5), seed_p, seed_S, np.zeros((0, 2)), np.zeros(0))
    np.testing.assert_array_equal(got[5], [10.0, 20.0, 30.0])
    np.testing.assert_allclose(got[:5], X_true, atol=1e-6)


def test_an_observation_behind_the_camera_is_left_out():
    """A landmark that starts behind the cameras (a wrong start) has its pixels left out until its
    seed brings it in front: the fit ends on the truth, with no NaN."""
    rng = np.random.default_rng(7)
    poses, X_true, obs_pose, obs_lm, uv, seed_pose, seed_p, seed_S = _scene(rng, n_points=8)
    start = X_true.copy()
    start[0] = transform_points(poses[0] @ T_BODY_CAM, np.array([[0.0, 0.0, -2.0]]))[0]  # 2 m behind the first camera
    got, _ = fit_landmarks(start, poses, obs_pose, obs_lm, uv, 0.3, CAMERA, T_BODY_CAM, seed_pose, np.arange(8), seed_p, seed_S, np.zeros((0, 2)), np.zeros(0))
    assert np.all(np.isfinite(got))
    np.testing.assert_allclose(got, X_true, atol=1e-6)
