"""Truth-checked tests of dem_graph.geometry: se3 helpers, Trajectory and PinholeCamera."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp

from dem_graph.errors import ConfigError, DemGraphError
from dem_graph.geometry import (
    PinholeCamera,
    Trajectory,
    invert,
    make_pose,
    matrix_from_quat_xyzw,
    quat_xyzw_from_matrix,
    rotation_from_rpy,
    transform_points,
)
from dem_graph.geometry.rig import default_rig
from dem_graph.geometry.se3 import check_pose


def random_poses(rng: np.random.Generator, n: int) -> np.ndarray:
    R = Rotation.random(n, random_state=rng).as_matrix()
    t = rng.uniform(-50.0, 50.0, size=(n, 3))
    return make_pose(R, t)


def Rx(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def Ry(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def Rz(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


# ----------------------------------------------------------------------------- se3


def test_invert_times_pose_is_identity():
    rng = np.random.default_rng(1)
    T = random_poses(rng, 50)
    T_inv = invert(T)
    assert T_inv.shape == (50, 4, 4)
    for k in range(50):
        np.testing.assert_allclose(T_inv[k] @ T[k], np.eye(4), rtol=0, atol=1e-12)
        np.testing.assert_allclose(T[k] @ T_inv[k], np.eye(4), rtol=0, atol=1e-12)
        # single-matrix call agrees with the stacked call
        np.testing.assert_array_equal(invert(T[k]), T_inv[k])


def test_make_pose_layout():
    R = Rz(0.3)
    t = np.array([1.0, -2.0, 3.5])
    T = make_pose(R, t)
    np.testing.assert_array_equal(T[:3, :3], R)
    np.testing.assert_array_equal(T[:3, 3], t)
    np.testing.assert_array_equal(T[3], [0.0, 0.0, 0.0, 1.0])


def test_transform_points_matches_homogeneous_multiplication():
    rng = np.random.default_rng(2)
    T = random_poses(rng, 1)[0]
    p = rng.normal(scale=10.0, size=(100, 3))
    ph = np.concatenate([p, np.ones((100, 1))], axis=1)
    expected = (T @ ph.T).T[:, :3]
    np.testing.assert_allclose(transform_points(T, p), expected, rtol=0, atol=1e-12)
    # T_a_b maps b into a: composing with the inverse brings points back
    np.testing.assert_allclose(transform_points(invert(T), transform_points(T, p)), p, rtol=0, atol=1e-10)


def test_quaternion_matrix_round_trip():
    rng = np.random.default_rng(3)
    q = rng.normal(size=(200, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q[q[:, 3] < 0] *= -1.0  # the canonical sign the library returns
    R = matrix_from_quat_xyzw(q)
    assert R.shape == (200, 3, 3)
    np.testing.assert_allclose(np.einsum("nji,njk->nik", R, R), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)
    q_back = quat_xyzw_from_matrix(R)
    assert q_back.shape == (200, 4)
    assert np.all(q_back[:, 3] >= 0)
    np.testing.assert_allclose(q_back, q, rtol=0, atol=1e-12)
    # and the other way: matrix -> quaternion -> matrix
    np.testing.assert_allclose(matrix_from_quat_xyzw(q_back), R, rtol=0, atol=1e-12)


def test_quaternion_known_values_and_sign():
    # 90 degrees about z: q = [0, 0, sin45, cos45]
    q = quat_xyzw_from_matrix(Rz(np.pi / 2))
    np.testing.assert_allclose(q, [0.0, 0.0, np.sqrt(0.5), np.sqrt(0.5)], atol=1e-15)
    # a quaternion with qw < 0 represents the same rotation; the library returns the qw >= 0 one
    q_neg = -np.array([0.1, -0.2, 0.3, 0.9]) / np.linalg.norm([0.1, -0.2, 0.3, 0.9])
    np.testing.assert_allclose(quat_xyzw_from_matrix(matrix_from_quat_xyzw(q_neg)), -q_neg, atol=1e-12)
    # identity
    np.testing.assert_allclose(matrix_from_quat_xyzw(np.array([0.0, 0.0, 0.0, 1.0])), np.eye(3), atol=0)


@pytest.mark.parametrize(
    "roll, pitch, yaw",
    [(0.0, 0.0, 0.0), (0.1, 0.2, 0.3), (-0.7, 0.4, 2.5), (1.2, -1.1, -3.0), (np.pi / 2 - 1e-3, 0.3, -0.2)],
)
def test_rotation_from_rpy_matches_explicit_product(roll, pitch, yaw):
    np.testing.assert_allclose(rotation_from_rpy(roll, pitch, yaw), Rz(yaw) @ Ry(pitch) @ Rx(roll), rtol=0, atol=1e-14)


def test_rotation_from_rpy_broadcasts():
    roll = np.array([0.1, -0.2, 0.3])
    pitch = 0.25
    yaw = np.array([1.0, 2.0, -1.0])
    R = rotation_from_rpy(roll, pitch, yaw)
    assert R.shape == (3, 3, 3)
    for k in range(3):
        np.testing.assert_allclose(R[k], Rz(yaw[k]) @ Ry(pitch) @ Rx(roll[k]), atol=1e-14)


def test_rotation_from_rpy_sign_conventions():
    a = np.radians(15.0)
    # positive pitch: nose (+x) goes below the horizon
    nose = rotation_from_rpy(0.0, a, 0.0) @ [1.0, 0.0, 0.0]
    np.testing.assert_allclose(nose, [np.cos(a), 0.0, -np.sin(a)], atol=1e-15)
    assert nose[2] < 0
    # positive roll: the left side (+y) goes up
    left = rotation_from_rpy(a, 0.0, 0.0) @ [0.0, 1.0, 0.0]
    np.testing.assert_allclose(left, [0.0, np.cos(a), np.sin(a)], atol=1e-15)
    assert left[2] > 0
    # positive yaw: nose turns left (+y), counter-clockwise seen from above
    nose = rotation_from_rpy(0.0, 0.0, a) @ [1.0, 0.0, 0.0]
    np.testing.assert_allclose(nose, [np.cos(a), np.sin(a), 0.0], atol=1e-15)


def test_check_pose_accepts_valid_pose_and_nested_lists():
    T = random_poses(np.random.default_rng(4), 1)[0]
    out = check_pose(T.tolist(), "T_body_cam", "rig.yaml")
    assert out.dtype == float
    np.testing.assert_array_equal(out, T)


def _bad_poses():
    good = make_pose(Rz(0.3), [1.0, 2.0, 3.0])
    nan = good.copy()
    nan[1, 3] = np.nan
    inf = good.copy()
    inf[0, 0] = np.inf
    scaled = good.copy()
    scaled[:3, :3] *= 1.01
    sheared = good.copy()
    sheared[0, 1] += 0.05
    last_row = good.copy()
    last_row[3] = [0.0, 0.0, 0.1, 1.0]
    reflection = good.copy()
    reflection[:3, :3] = good[:3, :3] @ np.diag([1.0, 1.0, -1.0])
    return [
        ("3x4", good[:3], "4x4"),
        ("3x3", np.eye(3), "4x4"),
        ("ragged", [[1, 0, 0, 0], [0, 1, 0]], "4x4"),
        ("text", [["a"] * 4] * 4, "4x4"),
        ("nan", nan, "NaN"),
        ("inf", inf, "infinite"),
        ("scaled", scaled, "rotation"),
        ("sheared", sheared, "rotation"),
        ("last_row", last_row, "last row"),
        ("reflection", reflection, "det +1"),
    ]


@pytest.mark.parametrize("label, T, fragment", _bad_poses(), ids=[b[0] for b in _bad_poses()])
def test_check_pose_rejects_with_informative_message(label, T, fragment):
    with pytest.raises(ConfigError) as info:
        check_pose(T, "T_body_laser", "/some/rig.yaml")
    msg = str(info.value)
    assert "T_body_laser" in msg
    assert "/some/rig.yaml" in msg
    assert fragment in msg
    assert info.value.source == "/some/rig.yaml"


def test_check_pose_reflection_is_orthonormal_but_rejected():
    # make sure the reflection case is rejected for its determinant, not for non-orthonormality
    R = np.diag([1.0, 1.0, -1.0])
    assert np.allclose(R.T @ R, np.eye(3))
    with pytest.raises(ConfigError, match="det"):
        check_pose(make_pose(R, [0.0, 0.0, 0.0]), "T")


# ----------------------------------------------------------------------- Trajectory


def make_trajectory(rng: np.random.Generator, n: int = 20) -> Trajectory:
    t = np.cumsum(rng.uniform(0.05, 0.3, size=n)) + 100.0
    return Trajectory.from_poses(t, random_poses(rng, n))


def test_trajectory_at_sample_times_returns_samples():
    rng = np.random.default_rng(5)
    traj = make_trajectory(rng)
    poses = traj.poses_se3
    for k, tk in enumerate(traj.t_s):
        np.testing.assert_allclose(traj.at(tk), poses[k], rtol=0, atol=1e-12)
    np.testing.assert_allclose(traj.at(traj.t_s), poses, rtol=0, atol=1e-12)


def test_trajectory_midpoint_is_linear_translation_and_half_slerp():
    rng = np.random.default_rng(6)
    traj = make_trajectory(rng)
    rots = Rotation.from_quat(traj.orientations_quat_xyzw)
    for k in range(len(traj) - 1):
        t_mid = 0.5 * (traj.t_s[k] + traj.t_s[k + 1])
        T = traj.at(t_mid)
        np.testing.assert_allclose(T[:3, 3], 0.5 * (traj.positions_xyz[k] + traj.positions_xyz[k + 1]), atol=1e-12)
        # half of the relative rotation, applied to the first sample
        delta = (rots[k].inv() * rots[k + 1]).as_rotvec()
        R_expected = (rots[k] * Rotation.from_rotvec(0.5 * delta)).as_matrix()
        np.testing.assert_allclose(T[:3, :3], R_expected, atol=1e-12)
        # and scipy's own slerp over the two samples agrees
        R_scipy = Slerp([traj.t_s[k], traj.t_s[k + 1]], rots[k : k + 2])([t_mid]).as_matrix()[0]
        np.testing.assert_allclose(T[:3, :3], R_scipy, atol=1e-12)
        np.testing.assert_array_equal(T[3], [0.0, 0.0, 0.0, 1.0])


def test_trajectory_slerp_about_z_is_analytic():
    a, b = 0.4, 1.9  # radians about z
    T0 = make_pose(Rz(a), [0.0, 0.0, 0.0])
    T1 = make_pose(Rz(b), [2.0, -4.0, 6.0])
    traj = Trajectory.from_poses([0.0, 1.0], np.stack([T0, T1]))
    np.testing.assert_allclose(traj.at(0.5)[:3, :3], Rz((a + b) / 2), atol=1e-12)
    np.testing.assert_allclose(traj.at(0.25)[:3, :3], Rz(a + 0.25 * (b - a)), atol=1e-12)
    np.testing.assert_allclose(traj.at(0.25)[:3, 3], [0.5, -1.0, 1.5], atol=1e-12)
    # the short way round: from +170 deg to -170 deg passes through 180 deg, not 0
    traj = Trajectory.from_poses(
        [0.0, 2.0], np.stack([make_pose(Rz(np.radians(170)), np.zeros(3)), make_pose(Rz(np.radians(-170)), np.zeros(3))])
    )
    np.testing.assert_allclose(traj.at(1.0)[:3, :3], Rz(np.pi), atol=1e-12)


def test_trajectory_vector_query_shape_and_scalar_shape():
    traj = make_trajectory(np.random.default_rng(7))
    tq = np.linspace(traj.t_s[0], traj.t_s[-1], 37)
    T = traj.at(tq)
    assert T.shape == (37, 4, 4)
    assert traj.at(float(tq[3])).shape == (4, 4)
    assert traj.at(np.float64(tq[3])).shape == (4, 4)
    assert traj.at(tq[3:4]).shape == (1, 4, 4)
    for k in (0, 10, 36):
        np.testing.assert_allclose(T[k], traj.at(tq[k]), atol=1e-15)


def test_trajectory_query_outside_span_raises():
    traj = make_trajectory(np.random.default_rng(8))
    span = traj.duration_s
    for t in (traj.t_s[0] - 1e-3, traj.t_s[-1] + 1e-3, traj.t_s[0] - span):
        with pytest.raises(DemGraphError, match="outside"):
            traj.at(t)
    with pytest.raises(DemGraphError):
        traj.at(np.array([traj.t_s[0], traj.t_s[-1] + 0.5]))


@pytest.mark.parametrize("kind", ["equal", "decreasing"])
def test_trajectory_rejects_non_increasing_times(kind):
    t = np.array([0.0, 1.0, 2.0, 3.0])
    t[2] = 1.0 if kind == "equal" else 0.5
    with pytest.raises(DemGraphError, match="index 2"):
        Trajectory(t, np.zeros((4, 3)), np.tile([0.0, 0.0, 0.0, 1.0], (4, 1)))


@pytest.mark.parametrize("field", ["t", "p", "q"])
def test_trajectory_rejects_nan(field):
    t = np.array([0.0, 1.0, 2.0])
    p = np.zeros((3, 3))
    q = np.tile([0.0, 0.0, 0.0, 1.0], (3, 1))
    {"t": lambda: t.__setitem__(1, np.nan), "p": lambda: p.__setitem__((1, 2), np.nan), "q": lambda: q.__setitem__((2, 0), np.nan)}[field]()
    with pytest.raises(DemGraphError, match="NaN"):
        Trajectory(t, p, q)


def test_trajectory_rejects_bad_shapes_and_quaternions():
    with pytest.raises(DemGraphError):
        Trajectory(np.array([0.0, 1.0]), np.zeros((3, 3)), np.tile([0.0, 0.0, 0.0, 1.0], (2, 1)))
    with pytest.raises(DemGraphError):
        Trajectory(np.zeros(0), np.zeros((0, 3)), np.zeros((0, 4)))
    with pytest.raises(DemGraphError, match="unit"):
        Trajectory(np.array([0.0, 1.0]), np.zeros((2, 3)), np.tile([0.0, 0.0, 0.0, 2.0], (2, 1)))


def test_trajectory_from_poses_round_trip():
    rng = np.random.default_rng(9)
    T = random_poses(rng, 30)
    t = np.arange(30) * 0.1
    traj = Trajectory.from_poses(t, T)
    np.testing.assert_array_equal(traj.t_s, t)
    np.testing.assert_array_equal(traj.positions_xyz, T[:, :3, 3])
    assert np.all(traj.orientations_quat_xyzw[:, 3] >= 0)
    np.testing.assert_allclose(traj.poses_se3, T, rtol=0, atol=1e-12)
    assert len(traj) == 30
    assert traj.duration_s == pytest.approx(2.9, abs=1e-12)


def test_trajectory_path_length_of_known_polyline():
    p = np.array([[0.0, 0.0, 0.0], [3.0, 4.0, 0.0], [3.0, 4.0, 12.0], [3.0, 4.0, 12.0], [0.0, 0.0, 12.0]])
    q = np.tile([0.0, 0.0, 0.0, 1.0], (5, 1))
    traj = Trajectory(np.arange(5.0), p, q)
    assert traj.path_length_m == pytest.approx(5.0 + 12.0 + 0.0 + 5.0, abs=1e-12)
    assert Trajectory(np.array([0.0]), p[:1], q[:1]).path_length_m == 0.0


def test_single_sample_trajectory():
    T = make_pose(Rz(0.5), [1.0, 2.0, 3.0])
    traj = Trajectory.from_poses([5.0], T[None])
    np.testing.assert_allclose(traj.at(5.0), T, atol=1e-12)
    with pytest.raises(DemGraphError):
        traj.at(5.1)


def test_trajectory_slice():
    traj = make_trajectory(np.random.default_rng(10))
    lo, hi = traj.t_s[3], traj.t_s[8]
    sub = traj.slice(lo, hi)
    np.testing.assert_array_equal(sub.t_s, traj.t_s[3:9])
    np.testing.assert_array_equal(sub.positions_xyz, traj.positions_xyz[3:9])


# -------------------------------------------------------------------- PinholeCamera


@pytest.fixture(scope="module")
def rig_camera() -> PinholeCamera:
    cam = default_rig().camera_model
    assert cam.has_distortion  # the tests below rely on the default camera being distorted
    return cam


def plain_camera() -> PinholeCamera:
    return PinholeCamera(640, 480, 500.0, 480.0, 321.3, 238.7)


def test_project_optical_axis_hits_principal_point(rig_camera):
    for cam in (plain_camera(), rig_camera):
        p = np.array([[0.0, 0.0, 0.5], [0.0, 0.0, 3.0], [0.0, 0.0, 1000.0]])
        uv, in_front = cam.project(p)
        assert in_front.all()
        np.testing.assert_allclose(uv, np.tile([cam.cx_px, cam.cy_px], (3, 1)), rtol=0, atol=1e-12)


def test_project_without_distortion_is_K_p_over_z():
    cam = plain_camera()
    assert not cam.has_distortion
    rng = np.random.default_rng(11)
    p = rng.uniform([-5, -5, 0.2], [5, 5, 20], size=(500, 3))
    uv, in_front = cam.project(p)
    assert in_front.all()
    Kp = (cam.K @ p.T).T
    np.testing.assert_allclose(uv, Kp[:, :2] / Kp[:, 2:], rtol=0, atol=1e-10)


def test_project_matches_opencv(rig_camera):
    rng = np.random.default_rng(12)
    cams = [
        rig_camera,
        PinholeCamera(1024, 768, 700.0, 690.0, 510.2, 380.9, (-0.21, 0.08, 1.3e-3, -7e-4, -0.015)),
    ]
    for cam in cams:
        # points inside a ~60 degree cone, where the polynomial model is well-behaved
        p = rng.uniform([-1.2, -0.9, 1.0], [1.2, 0.9, 1.0], size=(400, 3)) * rng.uniform(0.5, 30.0, size=(400, 1))
        uv, in_front = cam.project(p)
        assert in_front.all()
        ref, _ = cv2.projectPoints(p.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), cam.K, cam.dist_coeffs)
        np.testing.assert_allclose(uv, ref.reshape(-1, 2), rtol=0, atol=1e-9)


def test_bearings_round_trip_through_projection(rig_camera):
    cam = rig_camera
    u = np.concatenate([np.linspace(-0.5, cam.width_px - 0.5, 33), [0.0, cam.width_px - 1.0]])
    v = np.concatenate([np.linspace(-0.5, cam.height_px - 0.5, 25), [0.0, cam.height_px - 1.0]])
    U, V = np.meshgrid(u, v)
    uv = np.stack([U.ravel(), V.ravel()], axis=1)
    # the four image corners are in the set
    for corner in ([-0.5, -0.5], [cam.width_px - 0.5, cam.height_px - 0.5], [0.0, cam.height_px - 1.0]):
        assert np.any(np.all(uv == corner, axis=1))
    b = cam.bearings_from_pixels(uv)
    np.testing.assert_allclose(np.linalg.norm(b, axis=1), 1.0, atol=1e-12)
    assert np.all(b[:, 2] > 0)
    for depth in (0.7, 4.2, 55.0):
        uv_back, in_front = cam.project(b * depth)
        assert in_front.all()
        np.testing.assert_allclose(uv_back, uv, rtol=0, atol=1e-6)


def test_bearings_without_distortion_are_analytic():
    cam = plain_camera()
    uv = np.array([[0.0, 0.0], [cam.cx_px, cam.cy_px], [639.0, 479.0]])
    b = cam.bearings_from_pixels(uv)
    d = np.stack([(uv[:, 0] - cam.cx_px) / cam.fx_px, (uv[:, 1] - cam.cy_px) / cam.fy_px, np.ones(3)], axis=1)
    np.testing.assert_allclose(b, d / np.linalg.norm(d, axis=1, keepdims=True), atol=1e-15)
    np.testing.assert_allclose(b[1], [0.0, 0.0, 1.0], atol=1e-15)


def test_points_behind_camera_are_flagged(rig_camera):
    p = np.array([[0.1, 0.2, 2.0], [0.1, 0.2, -2.0], [0.0, 0.0, 0.0], [1.0, 1.0, -1e-3], [0.3, -0.1, 1e-3]])
    for cam in (plain_camera(), rig_camera):
        uv, in_front = cam.project(p)
        np.testing.assert_array_equal(in_front, [True, False, False, False, True])
        assert np.all(np.isnan(uv[~in_front]))
        assert np.all(np.isfinite(uv[in_front]))
        assert not cam.in_image(uv)[~in_front].any()


def test_project_single_point_is_2d():
    uv, in_front = plain_camera().project(np.array([0.0, 0.0, 2.0]))
    assert uv.shape == (1, 2) and in_front.shape == (1,)


def test_in_image_margin_logic():
    cam = PinholeCamera(800, 600, 500.0, 500.0, 399.5, 299.5)
    e = 1e-9
    uv = np.array(
        [
            [-0.5, -0.5],  # top-left corner of the image
            [799.5, 599.5],  # bottom-right corner
            [-0.5 - e, 100.0],
            [799.5 + e, 100.0],
            [100.0, -0.5 - e],
            [100.0, 599.5 + e],
            [399.5, 299.5],
            [np.nan, 10.0],
        ]
    )
    np.testing.assert_array_equal(cam.in_image(uv), [True, True, False, False, False, False, True, False])
    m = 2.0
    uv = np.array(
        [
            [1.5, 1.5],  # exactly m inside the top-left corner
            [1.5 - e, 100.0],
            [100.0, 1.5 - e],
            [797.5, 597.5],  # exactly m inside the bottom-right corner
            [797.5 + e, 100.0],
            [100.0, 597.5 + e],
            [0.0, 0.0],  # inside the image but within the margin
        ]
    )
    np.testing.assert_array_equal(cam.in_image(uv, margin_px=m), [True, False, False, True, False, False, False])


def test_pixel_bearings_shape_norm_and_order():
    cam = PinholeCamera(40, 30, 35.0, 36.0, 19.2, 14.8, (-0.1, 0.02, 1e-3, -2e-3, 0.0))
    B = cam.pixel_bearings()
    assert B.shape == (30 * 40, 3)
    np.testing.assert_allclose(np.linalg.norm(B, axis=1), 1.0, atol=1e-12)
    for u, v in [(0, 0), (39, 0), (0, 29), (39, 29), (17, 11), (5, 22)]:
        np.testing.assert_allclose(B[v * cam.width_px + u], cam.bearings_from_pixels(np.array([[u, v]]))[0], atol=1e-15)
    # every bearing projects back onto its own pixel centre
    uv, _ = cam.project(B)
    U, V = np.meshgrid(np.arange(40.0), np.arange(30.0))
    np.testing.assert_allclose(uv, np.stack([U.ravel(), V.ravel()], axis=1), atol=1e-6)
    # cached
    assert cam.pixel_bearings() is B


def test_pixel_bearings_of_the_default_camera(rig_camera):
    B = rig_camera.pixel_bearings()
    W, H = rig_camera.width_px, rig_camera.height_px
    assert B.shape == (H * W, 3)
    np.testing.assert_allclose(np.linalg.norm(B, axis=1), 1.0, atol=1e-12)
    idx = np.array([0, W - 1, (H - 1) * W, H * W - 1, 123 * W + 456])
    uv, _ = rig_camera.project(B[idx])
    np.testing.assert_allclose(uv, [[0, 0], [W - 1, 0], [0, H - 1], [W - 1, H - 1], [456, 123]], atol=1e-6)


@pytest.mark.parametrize("angle", [0.0, 1e-12, 1e-7, 1e-3, 0.3, 2.0, 2.96, 3.0, np.pi - 1e-6])
def test_so3_exp_and_log_agree_with_scipy_at_every_angle(angle):
    # the plain-numpy forms (closed form below 170 degrees, scipy's route near pi) against scipy
    from dem_graph.geometry.lie import so3_exp, so3_log

    rng = np.random.default_rng(int(angle * 1000))
    for _ in range(20):
        axis = rng.normal(size=3)
        w = angle * axis / np.linalg.norm(axis)
        R = Rotation.from_rotvec(w).as_matrix()
        np.testing.assert_allclose(so3_exp(w), R, atol=1e-14)
        np.testing.assert_allclose(so3_log(R), w, atol=1e-9 if angle > 3.0 else 1e-14)
