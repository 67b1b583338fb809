"""The pose history's spline (a scan's pose between camera frames) against a known smooth motion."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from dem_graph.frontend.pose_history import PoseHistory
from dem_graph.geometry.se3 import make_pose


def _motion(t):
    """A vehicle at 1.5 m/s, turning at about 0.3 rad/s, rolling and pitching by a few degrees."""
    rpy = np.stack([0.05 * np.sin(2 * np.pi * 0.8 * t), 0.04 * np.cos(2 * np.pi * 1.1 * t), 0.3 * t + 0.2 * np.sin(t)], -1)
    p = np.stack([1.5 * t, 0.3 * np.sin(0.5 * t), 0.1 * np.sin(2 * t)], -1)
    return make_pose(Rotation.from_euler("xyz", rpy).as_matrix(), p)


def _errors(T, t):
    truth = _motion(t)
    return np.linalg.norm(Rotation.from_matrix(truth[:3, :3].T @ T[:3, :3]).as_rotvec()), np.linalg.norm(T[:3, 3] - truth[:3, 3])


def test_spline_interpolates_a_smooth_motion_from_25_hz_poses():
    history = PoseHistory(window=6)
    rotation, position = [], []
    for k, t in enumerate(np.arange(0.0, 3.0, 0.04)):  # camera poses at 25 Hz
        history.append(t, _motion(t))
        np.testing.assert_allclose(history.at(t), _motion(t), atol=1e-12)  # through every pose
        if k >= 5:
            for t_scan in (t - 0.02, t - 0.1, t - 0.17):  # newest, middle and oldest intervals
                dr, dp = _errors(history.at(t_scan), t_scan)
                rotation.append(dr)
                position.append(dp)
    # a cubic through 40 ms steps: errors of order h^4 times the motion's 4th derivative
    assert max(rotation) < 2e-5  # rad (0.001 degree)
    assert max(position) < 1e-6  # m


def test_beyond_the_span_is_linear_and_a_correction_moves_the_spline():
    history = PoseHistory(window=6)
    T0, T1 = _motion(0.0), _motion(0.04)
    history.append(0.0, T0)
    history.append(0.04, T1)
    mid = history.at(0.02)  # two poses: linear in position, half the relative rotation
    np.testing.assert_allclose(mid[:3, 3], 0.5 * (T0[:3, 3] + T1[:3, 3]), atol=1e-12)
    half = Rotation.from_matrix(T0[:3, :3].T @ T1[:3, :3]).as_rotvec() / 2
    np.testing.assert_allclose(Rotation.from_matrix(T0[:3, :3].T @ mid[:3, :3]).as_rotvec(), half, atol=1e-12)
    for t in (0.08, 0.12, 0.16):
        history.append(t, _motion(t))
    before = history.at(0.1)
    C = make_pose(Rotation.from_rotvec([0.0, 0.0, 0.1]).as_matrix(), [1.0, -2.0, 0.5])
    history.correct(C)  # the spline is rebuilt from the corrected poses
    np.testing.assert_allclose(history.at(0.1), C @ before, atol=1e-9)


def test_across_a_camera_gap_the_poses_are_interpolated_linearly_not_swung_by_the_cubic():
    """Frames at 25 Hz, then none for 1.5 s (a blackout), then one: a scan inside the gap is placed
    between the poses on either side, within what a linear interpolation over 1.5 s of this motion
    allows, instead of where a cubic through such uneven knots swings."""
    history = PoseHistory(window=6)
    times = [*np.arange(0.0, 0.21, 0.04), 1.7]
    for t in times:
        history.append(t, _motion(t))
    t0, t1 = times[-2], times[-1]
    worst_rotation = 0.0
    for t_scan in np.linspace(t0 + 0.01, t1 - 0.01, 30):
        a = (t_scan - t0) / (t1 - t0)
        T = history.at(t_scan)
        linear = (1 - a) * _motion(t0)[:3, 3] + a * _motion(t1)[:3, 3]
        np.testing.assert_allclose(T[:3, 3], linear, atol=1e-12)
        worst_rotation = max(worst_rotation, _errors(T, t_scan)[0])
    # this motion turns 26 degrees in the gap and rocks: slerp is 5.9 degrees off it at worst; the cubic
    # through the uneven knots swung 14.9 degrees off (its positions were 3 cm off, the chord's 9 cm)
    assert np.degrees(worst_rotation) < 6.5
    # the knots before the gap keep their spline: a scan between two 25 Hz poses is placed as before
    dr, dp = _errors(history.at(0.14), 0.14)
    assert dp < 1e-4 and dr < 1e-3
