"""The iSAM2 estimator's factors: their errors and noise against known geometry."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from dem_graph.estimators.graph_factors import ProjectionFactors, calibration, odometry_factor, point_in_frame_factors, projection_factor
from dem_graph.geometry.camera import PinholeCamera
from dem_graph.geometry.lie import retract
from dem_graph.geometry.rig import default_rig
from dem_graph.geometry.se3 import invert, make_pose, rotation_from_rpy, transform_points


def _values(pose_key, T, point_key=None, X=None):
    v = gtsam.Values()
    v.insert(pose_key, gtsam.Pose3(T))
    if point_key is not None:
        v.insert(point_key, gtsam.Point3(*X))
    return v


def _cost(factors, values) -> float:
    return sum(f.error(values) for f in factors)


@pytest.mark.parametrize("p_frame", [[3.0, 0.4, -1.2], [0.5, -2.0, 0.3], [-4.0, 1.0, 2.0], [2.5, 0.7, -0.7]])
def test_point_in_frame_factors_are_the_mahalanobis_distance_of_the_point(p_frame):
    """For a small displacement d of the point in the pose's frame, the factors' summed cost is
    d^T Sigma^-1 d / 2: the pair carries exactly the given 3x3 covariance."""
    rng = np.random.default_rng(0)
    T = make_pose(rotation_from_rpy(0.1, -0.2, 0.7), [10.0, -3.0, 1.0])
    p = np.array(p_frame)
    A = rng.normal(size=(3, 3))
    Sigma = A @ A.T * 1e-4 + np.diag([1e-4, 4e-4, 0.25])  # elongated, like a ray's depth
    fs = point_in_frame_factors(0, 1, p, Sigma)
    Sigma_inv = np.linalg.inv(Sigma)
    for _ in range(5):
        d = rng.multivariate_normal(np.zeros(3), Sigma) * 1e-5  # the linear range: the claim is first order
        X = transform_points(T, (p + d)[None])[0]
        assert _cost(fs, _values(0, T, 1, X)) == pytest.approx(0.5 * d @ Sigma_inv @ d, rel=1e-3, abs=1e-16)
    # and zero at the measurement
    assert _cost(fs, _values(0, T, 1, transform_points(T, p[None])[0])) == pytest.approx(0.0, abs=1e-18)


def test_laser_point_factors_stay_smooth_over_the_covariance():
    """A laser return's covariance (2 cm along the beam, 2 mm across), displacements drawn from it
    at full size, at points on both sides of where a bearing factor's tangent basis switches axes
    (|y| = |z|): the cost stays within 5 % of d^T Sigma^-1 d / 2 (the bearing-range factor this
    replaces was off by a median factor 12 there, measured on the `paper` log)."""
    rng = np.random.default_rng(2)
    T = make_pose(rotation_from_rpy(0.0, 0.05, 0.3), [1.0, 2.0, 0.0])
    ratios = []
    for y in np.linspace(-0.9, -0.5, 9):
        p = np.array([2.8, y, -0.7])
        beam = p / np.linalg.norm(p)
        Sigma = 0.02**2 * np.outer(beam, beam) + 0.002**2 * np.eye(3)
        fs = point_in_frame_factors(0, 1, p, Sigma)
        for d in rng.multivariate_normal(np.zeros(3), Sigma, size=20):
            expected = 0.5 * d @ np.linalg.solve(Sigma, d)
            ratios.append(_cost(fs, _values(0, T, 1, transform_points(T, (p + d)[None])[0])) / expected)
    assert np.min(ratios) > 0.95 and np.max(ratios) < 1.05


def test_point_in_frame_factors_reject_bad_input():
    with pytest.raises(ValueError):
        point_in_frame_factors(0, 1, [1.0, np.nan, 0.0], np.eye(3))
    with pytest.raises(ValueError):
        point_in_frame_factors(0, 1, [1.0, 0.0, 0.0], np.eye(2))
    with pytest.raises(ValueError):
        point_in_frame_factors(0, 1, [1.0, 0.0, 0.0], np.diag([1.0, 1.0, 0.0]))


def test_odometry_factor_uses_the_right_perturbation_covariance():
    """Cost of a relative pose off by a right perturbation xi is xi^T Q^-1 xi / 2 (small xi)."""
    rng = np.random.default_rng(1)
    Ta = make_pose(rotation_from_rpy(0.05, 0.1, -0.4), [2.0, 1.0, 0.3])
    U = make_pose(rotation_from_rpy(0.01, -0.02, 0.05), [0.06, 0.001, -0.002])
    Q = np.diag([1e-5, 2e-5, 5e-6, 4e-6, 1e-6, 9e-6])
    f = odometry_factor(0, 1, U, Q)
    for _ in range(5):
        xi = rng.multivariate_normal(np.zeros(6), Q) * 1e-3
        v = gtsam.Values()
        v.insert(0, gtsam.Pose3(Ta))
        v.insert(1, gtsam.Pose3(retract(Ta @ U, xi)))
        assert f.error(v) == pytest.approx(0.5 * xi @ np.linalg.solve(Q, xi), rel=1e-3, abs=1e-14)


def test_projection_factor_matches_the_camera_model():
    """gtsam's Cal3DS2 projection through T_body_cam gives the pixels of our PinholeCamera
    (OpenCV distortion): zero error at our projection, sigma_px-scaled error 1 px away."""
    rig = default_rig()
    cam = PinholeCamera(width_px=800, height_px=600, fx_px=560.0, fy_px=555.0, cx_px=399.5, cy_px=301.0, distortion=(-0.05, 0.01, 0.001, -0.0005, 0.0))
    K = calibration(cam)
    T = make_pose(rotation_from_rpy(0.02, 0.03, 0.5), [5.0, 2.0, 0.1])
    rng = np.random.default_rng(2)
    p_body = np.column_stack([rng.uniform(3, 8, 10), rng.uniform(-2, 2, 10), rng.uniform(-0.3, 0.3, 10)])
    X = transform_points(T, p_body)
    uv, in_front = cam.project(transform_points(invert(T @ rig.T_body_cam), X))
    assert in_front.all()
    for k in range(10):
        f = projection_factor(0, 1, uv[k], 2.0, K, rig.T_body_cam, robust=False)
        v = _values(0, T, 1, X[k])
        np.testing.assert_allclose(f.unwhitenedError(v), 0.0, atol=1e-6)
        g = projection_factor(0, 1, uv[k] + [1.0, 0.0], 2.0, K, rig.T_body_cam, robust=False)
        assert g.error(v) == pytest.approx(0.5 * (1.0 / 2.0) ** 2, rel=1e-6)
    with pytest.raises(ValueError):
        calibration(PinholeCamera(width_px=10, height_px=10, fx_px=1.0, fy_px=1.0, cx_px=5.0, cy_px=5.0, distortion=(0, 0, 0, 0, 0.1)))


@pytest.mark.parametrize("robust", [True, False])
def test_shared_projection_factors_are_the_one_off_factors(robust):
    """ProjectionFactors (the graph's hot loop) makes the factor made anew from gtsam's parts: the
    same whitened error and Jacobians, to the bit, at points on and off the measurement (in the
    Huber kernel's linear region too), with one noise model per sigma."""

    def one_off_factor(z, sigma_px):
        noise = gtsam.noiseModel.Isotropic.Sigma(2, sigma_px)
        if robust:
            noise = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(1.345), noise)
        return gtsam.GenericProjectionFactorCal3DS2(gtsam.Point2(z[0], z[1]), noise, 0, 1, K, gtsam.Pose3(rig.T_body_cam))

    rig = default_rig()
    K = calibration(rig.camera_model)
    make = ProjectionFactors(K, rig.T_body_cam, robust=robust)
    T = make_pose(rotation_from_rpy(0.01, -0.02, 0.3), [2.0, -1.0, 0.05])
    rng = np.random.default_rng(7)
    p_body = np.column_stack([rng.uniform(3, 8, 6), rng.uniform(-2, 2, 6), rng.uniform(-0.3, 0.3, 6)])
    X = transform_points(T, p_body)
    uv, in_front = rig.camera_model.project(transform_points(invert(T @ rig.T_body_cam), X))
    assert in_front.all()
    for k, (offset_px, sigma_px) in enumerate([(0.0, 0.3), (0.5, 0.3), (4.0, 0.3), (-3.0, 0.6), (0.2, 0.6), (9.0, 1.0)]):
        z = uv[k] + [offset_px, -0.5 * offset_px]
        v = _values(0, T, 1, X[k])
        shared, one_off = make(0, 1, z, sigma_px), one_off_factor(z, sigma_px)
        assert shared.error(v) == one_off.error(v)
        a, b = shared.linearize(v), one_off.linearize(v)
        np.testing.assert_array_equal(a.jacobian()[0], b.jacobian()[0])
        np.testing.assert_array_equal(a.jacobian()[1], b.jacobian()[1])
    assert make.noise(0.3) is make.noise(0.3) and make.noise(0.3) is not make.noise(0.6)


def test_range_factor_measures_from_the_sensor():
    """Along the sensor's ray the cost is d^2 / (2 sigma^2); across it, zero to first order."""
    from dem_graph.estimators.graph_factors import range_factor

    rig = default_rig()
    T = make_pose(rotation_from_rpy(0.0, 0.05, 1.0), [4.0, 1.0, 0.3])
    T_world_cam = T @ rig.T_body_cam
    ray = T_world_cam[:3, :3] @ np.array([0.1, 0.2, 1.0])
    ray /= np.linalg.norm(ray)
    X = T_world_cam[:3, 3] + 6.0 * ray
    f = range_factor(0, 1, 6.0, 0.5, rig.T_body_cam)
    assert f.error(_values(0, T, 1, X)) == pytest.approx(0.0, abs=1e-20)
    assert f.error(_values(0, T, 1, X + 0.3 * ray)) == pytest.approx(0.5 * (0.3 / 0.5) ** 2, rel=1e-9)
    across = np.cross(ray, [0.0, 0.0, 1.0])
    across /= np.linalg.norm(across)
    assert f.error(_values(0, T, 1, X + 1e-4 * across)) < 1e-15
    with pytest.raises(ValueError):
        range_factor(0, 1, -1.0, 0.5, rig.T_body_cam)


def test_many_seeds_give_the_factors_of_each_seed_alone():
    """``seeds_factors`` (the batch's graph, a keyframe's new points) gives, seed by seed and in the
    seeds' order, what ``seed_factors`` gives each seed alone: laser and camera seeds mixed, the same
    keys, errors and Jacobians to the bit at values off the seeds; a camera seed behind the camera is
    refused, as alone."""
    from dem_graph.estimators.graph_factors import seed_factors, seeds_factors
    from dem_graph.frontend.frontend import PointKind

    rig = default_rig()
    K = calibration(rig.camera_model)
    rng = np.random.default_rng(3)
    n = 12
    kinds = [PointKind.LASER if k % 3 else PointKind.CAMERA for k in range(n)]
    p_body = np.column_stack([rng.uniform(3, 8, n), rng.uniform(-2, 2, n), rng.uniform(-0.3, 0.3, n)])
    Sigma = np.array([np.diag(rng.uniform(0.01, 0.3, 3) ** 2) + 1e-4 for _ in range(n)])
    pose_keys, point_keys = [100 + k % 4 for k in range(n)], list(range(n))
    many = seeds_factors(pose_keys, point_keys, kinds, p_body, Sigma, rig.camera_model, K, rig.T_body_cam, 1.0)
    alone = [f for k in range(n) for f in seed_factors(pose_keys[k], point_keys[k], kinds[k], p_body[k], Sigma[k], rig.camera_model, K, rig.T_body_cam, 1.0)]
    assert len(many) == len(alone) == 2 * n
    T = make_pose(rotation_from_rpy(0.02, -0.01, 0.4), [1.0, 2.0, 0.1])
    for a, b in zip(many, alone):
        assert type(a) is type(b) and list(a.keys()) == list(b.keys())
        pose_key, point_key = a.keys()
        v = _values(pose_key, T, point_key, transform_points(T, p_body[point_key][None])[0] + rng.normal(scale=0.2, size=3))
        assert a.error(v) == b.error(v)
        la, lb = a.linearize(v), b.linearize(v)
        np.testing.assert_array_equal(la.jacobian()[0], lb.jacobian()[0])
    behind = p_body.copy()
    behind[0] = [-5.0, 0.0, 0.0]
    with pytest.raises(ValueError, match="in front of the camera"):
        seeds_factors(pose_keys, point_keys, kinds, behind, Sigma, rig.camera_model, K, rig.T_body_cam, 1.0)
