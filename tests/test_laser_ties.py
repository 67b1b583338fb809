"""Laser ties (dem_graph.estimators.laser_ties): a landmark takes the laser's height of its ground, its
place across the ground left to the camera; the start's ground levels the world."""

from __future__ import annotations

from collections import Counter

import numpy as np
import pytest

from dem_graph.datasets.events import LaserScan
from dem_graph.estimators.laser_ties import LEVEL_START_SIGMAS, LaserTieMaker, level_prior, level_start_covariance
from dem_graph.frontend.pose_history import PoseHistory
from dem_graph.geometry.rig import car_rig
from dem_graph.geometry.se3 import make_pose, rotation_from_rpy, transform_points

SPEED_MPS = 7.0
GROUND_Z_M = 0.05  # the road 5 cm above the world's z = 0


def _pose(t_s: float) -> np.ndarray:
    return make_pose(np.eye(3), [SPEED_MPS * t_s, 0.0, 0.0])


def _scan(rig, t_s: float, wall_y_m: float | None = None, ground_z_m: float = GROUND_Z_M) -> LaserScan:
    """The laser's ranges at ``t_s`` to the road at ``ground_z_m``, and to a wall at y = ``wall_y_m`` if given."""
    T = _pose(t_s) @ rig.T_body_laser
    d = rig.laser.beam_directions() @ T[:3, :3].T
    o = T[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        r = np.where(d[:, 2] < 0, (ground_z_m - o[2]) / d[:, 2], np.nan)
        if wall_y_m is not None:
            r_wall = np.where(d[:, 1] * wall_y_m > 0, (wall_y_m - o[1]) / d[:, 1], np.nan)
            r = np.where(np.isfinite(r_wall) & ~(r_wall > r), r_wall, r)
    return LaserScan(t_s, r)


P_START = np.eye(6) * 1e-8


def _swept(ground_z_m: float):
    rig = car_rig()
    history = PoseHistory(window=10)
    for t in np.arange(0.0, 0.26, 1 / 16):
        history.append(float(t), _pose(float(t)))
    t_kf = float(np.arange(0.0, 0.26, 1 / 16)[-1])
    scans = [_scan(rig, float(t), wall_y_m=3.0, ground_z_m=ground_z_m) for t in np.arange(0.01, t_kf, 0.02)]
    maker = LaserTieMaker(rig, np.eye(4), P_START, 0.0, Counter())
    maker.add_scans(4, 4, t_kf, _pose(t_kf), scans, history)
    return rig, maker, t_kf


@pytest.fixture()
def swept():
    """A car rig driven straight at 7 m/s for 0.25 s (frames at 16 Hz, scans at 50 Hz), one keyframe
    at the end with the scans since the start; a wall 3 m to the left; the road 5 cm above the body's
    ground (within the mount's 5 cm: it agrees)."""
    return _swept(GROUND_Z_M)


def test_a_landmark_takes_the_lasers_ground_height_and_keeps_its_place(swept):
    """A landmark 25 cm above the swept road (a flat-ground seed of a camera mounted wrong) is tied to
    the keyframe: in that keyframe's frame its height is the road's (to the float64 of the ray-plane
    intersection, 1e-9 m), its x, y its own, the height's sigma the range noise (the road is a
    plane: no spread), x and y within 1 m (the laser does not say where across the ground it is)."""
    rig, maker, t_kf = swept
    X = np.array([[2.6, 0.4, GROUND_Z_M + 0.25], [2.4, -1.0, GROUND_Z_M - 0.1]])
    ties = maker.ties({4: _pose(t_kf)}, np.array([7, 8]), X, t_kf)
    assert ties.landmarks.tolist() == [7, 8] and ties.keyframes.tolist() == [4, 4] and ties.frames.tolist() == [4, 4]
    in_world = transform_points(_pose(t_kf), ties.p_frame)
    np.testing.assert_allclose(in_world[:, 2], GROUND_Z_M, atol=1e-9)
    np.testing.assert_allclose(in_world[:, :2], X[:, :2], atol=1e-12)
    np.testing.assert_allclose(np.sqrt(np.diagonal(ties.Sigma_frame, axis1=1, axis2=2)), [[1.0, 1.0, rig.laser.range_sigma_m]] * 2, rtol=1e-9)
    assert maker.start is None  # the first second has not passed


def _decided(ground_z_m: float, slope: float = 0.0):
    """40 landmarks tied over the first second on a road ``ground_z_m`` above the start's ground,
    climbing ``slope`` (m/m); the decision at the next keyframe, 1.1 s in."""
    _, maker, t_kf = _swept(ground_z_m)
    rng = np.random.default_rng(0)
    maker._start_ground = {i: np.array([x, y, ground_z_m + slope * x]) for i, (x, y) in enumerate(zip(rng.uniform(2, 9, 40), rng.uniform(-2, 2, 40)))}
    return maker, maker.ties({4: _pose(t_kf)}, np.zeros(0, dtype=np.int64), np.zeros((0, 3)), 1.1)


def test_the_start_pose_prior_goes_back_where_the_mount_agrees_with_the_lasers_ground():
    """The ground of the first second 3 cm above the start's ground and level: the mount agrees, the
    start pose's own prior goes back once and nothing levels the world."""
    maker, ties = _decided(0.03)
    assert maker.start == "pinned" and len(ties.level_landmarks) == 0
    np.testing.assert_array_equal(ties.pin_start, P_START)
    assert maker.ties({4: _pose(0.25)}, np.zeros(0, dtype=np.int64), np.zeros((0, 3)), 1.2).pin_start is None


@pytest.mark.parametrize(("ground_z_m", "slope"), [(0.15, 0.0), (0.0, np.tan(np.radians(2.0)))])
def test_a_mount_off_the_lasers_ground_levels_the_world_from_it(ground_z_m, slope):
    """The ground of the first second 15 cm above the start's ground, or tilted 2 degrees against it
    (the mount off): its 40 landmarks each get a prior on the start pose's ground plane, their
    height there 0, and the start pose's own prior is not put back. The fitted plane is the one
    the ground was made on (to 1 mm and 1 mdeg)."""
    maker, ties = _decided(ground_z_m, slope)
    assert maker.start == "levelled" and len(ties.level_landmarks) == 40 and ties.pin_start is None
    np.testing.assert_allclose(ties.level_mean[:, 2], 0.0, atol=1e-12)
    assert maker.counters["laser_start_ground_mm"] == round(1000 * ground_z_m)
    assert maker.counters["laser_start_ground_tilt_mdeg"] == round(1000 * np.degrees(np.arctan(slope)))


def test_a_landmark_is_tied_once_and_only_over_swept_flat_ground(swept):
    """Tied once; none away from the scans (10 m ahead), on the wall (its returns' heights spread over
    decimetres) or 0.6 m off the road's height (the gate: not that ground)."""
    _, maker, t_kf = swept
    poses = {4: _pose(t_kf)}
    assert len(maker.ties(poses, np.array([7]), np.array([[2.6, 0.4, GROUND_Z_M]]), t_kf)) == 1
    assert len(maker.ties(poses, np.array([7]), np.array([[2.6, 0.4, GROUND_Z_M]]), t_kf)) == 0
    far, wall, high = [12.0, 0.0, GROUND_Z_M], [3.0, 3.0, 0.3], [2.6, 0.0, GROUND_Z_M + 0.6]
    assert len(maker.ties(poses, np.array([1, 2, 3]), np.array([far, wall, high]), t_kf)) == 0
    assert maker.counters["laser_ties_not_flat"] == 1 and maker.counters["laser_ties_gated"] == 1


def test_a_keyframe_out_of_the_window_ties_nothing(swept):
    _, maker, t_kf = swept
    assert len(maker.ties({5: _pose(t_kf)}, np.array([7]), np.array([[2.6, 0.4, GROUND_Z_M]]), t_kf)) == 0


def test_the_level_prior_is_tight_across_the_start_pose_ground_plane_only():
    """On a start pose pitched 3 degrees and 0.2 m up: the prior's mean is the point moved onto the
    start's body z = 0 plane, its sigma 3 cm along the plane's normal and 10 m along the plane."""
    T0 = make_pose(rotation_from_rpy(0.0, np.radians(3.0), 0.0), [1.0, 0.0, 0.2])
    n = T0[:3, 2]
    mean, Sigma = level_prior(T0, np.array([4.0, 1.0, 0.5]), 0.03)
    assert float(n @ (mean - T0[:3, 3])) == pytest.approx(0.0, abs=1e-12)
    assert float(n @ Sigma @ n) == pytest.approx(0.03**2, rel=1e-9)
    along = np.cross(n, [0.0, 1.0, 0.0])
    along /= np.linalg.norm(along)
    assert float(along @ Sigma @ along) == pytest.approx(100.0, rel=1e-9)


def test_the_start_prior_frees_roll_pitch_and_height_only():
    P = level_start_covariance(np.eye(6) * 1e-8)
    np.testing.assert_allclose(np.diag(P), [LEVEL_START_SIGMAS[0] ** 2, LEVEL_START_SIGMAS[1] ** 2, 1e-8, 1e-8, 1e-8, LEVEL_START_SIGMAS[5] ** 2])
