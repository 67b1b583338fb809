"""Camera-laser calibration against simulated truth: closed form, refinement accuracy, Jacobian,
covariance consistency, degenerate input."""

from __future__ import annotations

import numpy as np
import pytest

from dem_graph.calibration.accuracy import errors_over_seeds
from dem_graph.calibration.board import board_from_corners
from dem_graph.calibration.pipeline import CalibrationOptions, calibrate_views
from dem_graph.calibration.simulate import simulate_calibration
from dem_graph.calibration.solve import PlaneView, closed_form, point_plane_jacobian, point_plane_residuals
from dem_graph.errors import CalibrationError
from dem_graph.geometry.lie import local, retract


def _boards(sim, sigma_px):
    return [board_from_corners(c, sim.board, sim.intrinsics.K, sim.intrinsics.distortion, sigma_px) for c in sim.corners_px]


def _errors(sim, T):
    xi = local(sim.T_cam_laser, T)
    return np.degrees(np.linalg.norm(xi[:3])), 1000.0 * np.linalg.norm(T[:3, 3] - sim.T_cam_laser[:3, 3]), xi


def test_closed_form_recovers_truth_without_noise():
    sim = simulate_calibration(seed=3, n_views=8, corner_sigma_px=0.0, range_sigma_m=0.0)
    boards = _boards(sim, 0.01)
    result = calibrate_views(boards, sim.scans.ranges_m, sim.scans.angles_rad, sim.board, CalibrationOptions(range_sigma_m=0.001))
    xi = local(sim.T_cam_laser, result.T_initial)
    assert np.max(np.abs(xi)) < 1e-6  # radians and metres
    assert np.max(np.abs(local(sim.T_cam_laser, result.T_cam_laser))) < 1e-6


def test_board_outline_and_containment():
    from dem_graph.calibration.board import BoardSpec

    board = BoardSpec(9, 6, 0.09)  # inner corners 0..8 x 0..5 squares; the squares reach one square beyond them
    np.testing.assert_allclose(board.outline(0.05), (-0.14, 0.86, -0.14, 0.59), atol=1e-12)
    points = np.array([[-0.139, 0.0, 0.0], [-0.141, 0.0, 0.0], [0.4, 0.589, 0.0], [0.4, 0.591, 0.0], [np.nan, 0.1, 0.0]])
    assert board.contains(points, 0.05).tolist() == [True, False, True, False, False]


def test_jacobian_matches_numerical_derivative():
    rng = np.random.default_rng(0)
    T = retract(simulate_calibration(0, 3).T_cam_laser, 0.05 * rng.standard_normal(6))
    points = np.column_stack([rng.uniform(0.5, 2.0, 20), rng.uniform(-0.5, 0.5, 20), np.zeros(20)])
    view = PlaneView(np.array([0.2, -0.3, 0.93]) / np.linalg.norm([0.2, -0.3, 0.93]), 1.4, np.eye(4) * 1e-6, points)
    J = point_plane_jacobian(T, view)
    numeric = np.zeros_like(J)
    for k in range(6):
        step = np.zeros(6)
        step[k] = 1e-6
        numeric[:, k] = (point_plane_residuals(retract(T, step), view) - point_plane_residuals(retract(T, -step), view)) / 2e-6
    np.testing.assert_allclose(J, numeric, atol=1e-8)


def test_the_views_packed_in_one_array_give_the_view_by_view_numbers_to_the_bit():
    """The refinements evaluate every view at once (solve._PackedViews); the covariance and views of
    fewer than four points go view by view. Both must give the same numbers, bit for bit: views of
    different sizes (the padding), dark returns moved by a bias, and none."""
    from dem_graph.calibration.solve import _PackedViews, _whitened, _whiteners

    rng = np.random.default_rng(4)
    T = retract(simulate_calibration(0, 3).T_cam_laser, 0.05 * rng.standard_normal(6))
    views = []
    for m in (7, 20, 13):
        points = np.column_stack([rng.uniform(0.5, 2.0, m), rng.uniform(-0.5, 0.5, m), np.zeros(m)])
        n = rng.standard_normal(3) + [0.0, 0.0, 3.0]
        A = rng.standard_normal((4, 4)) * 1e-3
        views.append(PlaneView(n / np.linalg.norm(n), rng.uniform(1.0, 2.0), A @ A.T, points, rng.uniform(0.0, 1.0, m)))
    packed = _PackedViews(views)
    assert np.array_equal(packed.residuals(T), np.concatenate([point_plane_residuals(T, v) for v in views]))
    assert np.array_equal(packed.jacobian(T), np.vstack([point_plane_jacobian(T, v) for v in views]))
    for bias_m in (0.0, 0.004):
        moved = [v.with_dark_bias(bias_m) for v in views]
        by_view = _whitened(T, moved, _whiteners(T, moved, 0.01), False)[0]
        assert np.array_equal(packed.whitened_residuals(T, 0.01, bias_m), by_view)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_refinement_meets_the_acceptance_with_1cm_ranges(seed):
    # 0.3 px corners, 1 cm ranges, 15 views: rotation under 0.3 degrees, translation under 1 cm at every seed
    sim = simulate_calibration(seed=seed, n_views=15, corner_sigma_px=0.3, range_sigma_m=0.01)
    result = calibrate_views(_boards(sim, None), sim.scans.ranges_m, sim.scans.angles_rad, sim.board, CalibrationOptions(range_sigma_m=0.01))
    rot_deg, trans_mm, _ = _errors(sim, result.T_cam_laser)
    assert rot_deg < 0.3 and trans_mm < 10.0
    assert all(v.used for v in result.views)


def test_accuracy_and_covariance_over_seeds_with_2cm_ranges():
    # 8 seeds at 0.3 px and 2 cm. Accuracy: translation under 1 cm at every seed, rotation under 0.3 degrees
    # in the median and under 0.4 at worst (measured over seeds 0-9: 9 of 10 under 0.3, worst 0.33).
    # Covariance: the normalised squared errors (chi-square, 6 dof) average 6; the mean of 8 has a standard
    # deviation of sqrt(12/8) = 1.2, so 3 to 9.5 is a band of about three of them.
    rot, trans, nees = [], [], []
    for seed in range(8):
        sim = simulate_calibration(seed=100 + seed, n_views=15, corner_sigma_px=0.3, range_sigma_m=0.02)
        result = calibrate_views(_boards(sim, None), sim.scans.ranges_m, sim.scans.angles_rad, sim.board)
        rot_deg, trans_mm, xi = _errors(sim, result.T_cam_laser)
        rot.append(rot_deg)
        trans.append(trans_mm)
        nees.append(xi @ np.linalg.solve(result.covariance, xi))
    assert max(trans) < 10.0
    assert np.median(rot) < 0.3 and max(rot) < 0.4
    assert 3.0 < np.mean(nees) < 9.5


def test_guided_board_poses_at_3cm_ranges():
    # 0.3 px and 3 cm, 15 views held as docs/calibration.md asks (tilted 34-57 deg forward or back), seeds 0-9:
    # measured rotation median 0.15 and max 0.32 deg (8 of 10 under 0.3), translation at most 9.6 mm, mean NEES
    # 6.7; with random tilts the same seeds gave 0.17 / 0.54 deg (6 of 10). The formal rotation sigma about the
    # laser's y axis (the scan plane's pitch, the weakest) falls by about a third.
    guided = errors_over_seeds(range(10), range_sigma_m=0.03, pose_protocol="guided")
    random = errors_over_seeds(range(10), range_sigma_m=0.03, pose_protocol="random")
    rot = np.array([e.rotation_deg for e in guided])
    assert max(e.translation_mm for e in guided) < 10.0
    assert np.median(rot) < 0.3 and rot.max() < 0.35 and (rot < 0.3).sum() >= 8
    assert 3.0 < np.mean([e.nees for e in guided]) < 9.5
    sigma_y = [np.mean([e.sigma_rotation_deg[1] for e in errs]) for errs in (guided, random)]
    assert sigma_y[0] < 0.75 * sigma_y[1]


def test_weak_rotation_gets_recording_advice(caplog):
    weak = simulate_calibration(seed=7, n_views=15, corner_sigma_px=0.3, range_sigma_m=0.03)  # formal sigma 0.24 deg about y
    with caplog.at_level("WARNING", logger="dem_graph.calibration.pipeline"):
        result = calibrate_views(_boards(weak, None), weak.scans.ranges_m, weak.scans.angles_rad, weak.board, CalibrationOptions(range_sigma_m=0.03))
    assert result.sigma_rot_deg[1] > 0.2
    assert "laser's y axis is known to 0.2" in caplog.text and "tilted 35-55 deg forward or back, 1.5-2 m away" in caplog.text
    good = simulate_calibration(seed=0, n_views=15, corner_sigma_px=0.3, range_sigma_m=0.01, pose_protocol="guided")
    result = calibrate_views(_boards(good, None), good.scans.ranges_m, good.scans.angles_rad, good.board, CalibrationOptions(range_sigma_m=0.01))
    assert result.sigma_rot_deg.max() < 0.1 and result.recording_advice() is None


def test_too_few_views_is_an_error():
    sim = simulate_calibration(seed=1, n_views=2)
    with pytest.raises(CalibrationError, match="usable views"):
        calibrate_views(_boards(sim, None), sim.scans.ranges_m, sim.scans.angles_rad, sim.board)


def test_no_board_in_the_images_skips_views_then_errors():
    sim = simulate_calibration(seed=1, n_views=6)
    boards = _boards(sim, None)
    boards[0] = None
    result = calibrate_views(boards, sim.scans.ranges_m, sim.scans.angles_rad, sim.board)
    assert result.views[0].reason == "no 9x6 inner-corner board found in the image" and not result.views[0].used
    with pytest.raises(CalibrationError, match="2 usable views"):
        calibrate_views([None] * 4 + boards[4:], sim.scans.ranges_m, sim.scans.angles_rad, sim.board)


def test_no_laser_return_on_the_board_is_an_error():
    sim = simulate_calibration(seed=2, n_views=5)
    ranges = np.full_like(sim.scans.ranges_m, np.nan)
    with pytest.raises(CalibrationError, match="0 usable views"):
        calibrate_views(_boards(sim, None), ranges, sim.scans.angles_rad, sim.board)


def test_parallel_boards_are_an_error():
    sim = simulate_calibration(seed=4, n_views=6)
    boards = _boards(sim, None)
    same = [boards[0]] * 6  # one board pose seen six times
    scans = np.repeat(sim.scans.ranges_m[:1], 6, axis=0)
    with pytest.raises(CalibrationError, match="parallel"):
        calibrate_views(same, scans, sim.scans.angles_rad, sim.board)


def test_closed_form_without_enough_constraints_is_an_error():
    view = PlaneView(np.array([0.0, 0.0, 1.0]), 1.0, np.eye(4) * 1e-6, np.array([[1.0, 0.0, 0.0], [1.0, 0.1, 0.0]]))
    with pytest.raises(CalibrationError, match="rank"):
        closed_form([view])


def test_pose_groups_and_leave_one_pose_out_spread():
    from dem_graph.calibration.laser_line import points_from_ranges
    from dem_graph.calibration.solve import jackknife_covariance, pose_groups, refine

    sim = simulate_calibration(seed=7, n_views=12, corner_sigma_px=0.3, range_sigma_m=0.02)
    boards = _boards(sim, None)
    result = calibrate_views(boards, sim.scans.ranges_m, sim.scans.angles_rad, sim.board, CalibrationOptions(jackknife=True))
    assert result.n_poses == 12 and result.jackknife_covariance is not None
    # white noise: the spread agrees with the formal covariance within what 12 poses can tell (a standard
    # deviation to about 20 %) and the jackknife's known excess (seeds 7-9: ratios 0.7-1.8)
    ratio = np.sqrt(np.diag(result.jackknife_covariance) / np.diag(result.covariance))
    assert np.all((ratio > 0.5) & (ratio < 2.5)), ratio
    assert result.rig_covariance is result.covariance  # the rig keeps the formal one on white noise
    # a pose seen three times is one pose
    views = [PlaneView(boards[k].n_cam, boards[k].d_m, boards[k].plane_covariance, points_from_ranges(sim.scans.ranges_m[k, idx], sim.scans.angles_rad[idx])) for k, idx in result.on_board.items()]
    tripled = [v for v in views[:5] for _ in range(3)]
    assert pose_groups(tripled) == [[0, 1, 2], [3, 4, 5], [6, 7, 8], [9, 10, 11], [12, 13, 14]]
    assert jackknife_covariance(tripled[:9], refine(views, result.T_cam_laser, 0.02).T_cam_laser, 0.02) is None  # three poses


def test_a_window_away_from_the_board_leaves_no_usable_view():
    sim = simulate_calibration(seed=1, n_views=4)
    with pytest.raises(CalibrationError, match="0 usable views"):
        calibrate_views(_boards(sim, None), sim.scans.ranges_m, sim.scans.angles_rad, sim.board, CalibrationOptions(window_rad=(-1.5, -1.2)))
