"""Calibration on recordings of other kinds (issue 24), against simulated truth: range noise from the data,
dark squares that drop returns and read long, a small board with an object beside it, the errors a new
user meets."""

from __future__ import annotations

import logging

import numpy as np
import pytest
from click.testing import CliRunner

from dem_graph.calibration.board import BoardSpec, board_from_corners, dark_parity
from dem_graph.calibration.laser_line import line_segments, range_noise_from_scans
from dem_graph.calibration.pipeline import CalibrationOptions, calibrate_recording, calibrate_views, tolerances
from dem_graph.calibration.readers import read_radlocc_recording
from dem_graph.calibration.simulate import DARK_PARITY, _hit_rectangle, render_board_image, simulate_calibration, write_recording
from dem_graph.errors import CalibrationError
from dem_graph.geometry.lie import local

SMALL = BoardSpec(7, 5, 0.03)  # 8 x 6 squares of 3 cm: a 0.24 x 0.18 m board


def _hard(seed: int, **kw):
    """The issue's recording: 2 mm noise, the small board with a 1 cm border, 80 % of the dark squares' returns lost
    and the rest 5 mm long, a panel beside the board, 15 views."""
    args = dict(n_views=15, corner_sigma_px=0.3, range_sigma_m=0.002, board=SMALL, margin_m=0.01, dark_dropout=0.8, dark_bias_m=0.005, neighbour=True)
    return simulate_calibration(seed=seed, **{**args, **kw})


def _boards(sim, parity=DARK_PARITY):
    from dataclasses import replace

    return [replace(board_from_corners(c, sim.board, sim.intrinsics.K, sim.intrinsics.distortion), dark_parity=parity) for c in sim.corners_px]


def _errors(sim, T):
    xi = local(sim.T_cam_laser, T)
    return np.degrees(np.linalg.norm(xi[:3])), 1000.0 * np.linalg.norm(T[:3, 3] - sim.T_cam_laser[:3, 3])


def _true_hits(sim, view):
    """Per beam: whether it truly hits the board, and where on the board (board frame x, y)."""
    T = sim.T_cam_laser
    a = sim.scans.angles_rad
    dirs = np.stack([np.cos(a), np.sin(a), np.zeros_like(a)], axis=1) @ T[:3, :3].T
    s, xy = _hit_rectangle(T[:3, 3], dirs, sim.T_cam_board[view], sim.board.outline(sim.margin_m))
    return np.isfinite(s), xy, s


# ------------------------------------------------------------------ the simulator renders the cases


def test_simulated_dark_squares_drop_and_bias_their_returns_and_a_panel_stands_beside():
    sim = _hard(0)
    lost, kept, bias = 0, 0, []
    for k in range(len(sim.T_cam_board)):
        on, xy, s = _true_hits(sim, k)
        dark = on & sim.board.dark(xy, DARK_PARITY)
        r = sim.scans.ranges_m[k]
        lost += int(np.sum(dark & np.isnan(r)))
        kept += int(np.sum(dark & np.isfinite(r)))
        bias += list((r - s)[dark & np.isfinite(r)])
        assert np.all(np.isfinite(r[on & ~dark]))  # light squares lose nothing
    frac = lost / (lost + kept)
    assert abs(frac - 0.8) < 0.05  # binomial over ~900 dark returns: sd 0.013
    assert abs(np.mean(bias) - 0.005) < 3 * 0.002 / np.sqrt(len(bias)) + 1e-4  # 5 mm long, noise 2 mm
    assert sim.T_cam_neighbour is not None and sim.T_cam_neighbour.shape == (15, 4, 4)


def test_rendered_board_shows_which_squares_are_dark():
    sim = _hard(1, n_views=2)
    image = render_board_image(sim, 0, np.random.default_rng(0))
    obs = _boards(sim, None)[0]
    assert dark_parity(image, obs, sim.board, sim.intrinsics.K, sim.intrinsics.distortion) == DARK_PARITY
    assert dark_parity(255 - image, obs, sim.board, sim.intrinsics.K, sim.intrinsics.distortion) == 1 - DARK_PARITY
    flat = np.full_like(image, 128)
    assert dark_parity(flat, obs, sim.board, sim.intrinsics.K, sim.intrinsics.distortion) is None


def test_dark_probability_is_the_colour_away_from_edges_and_a_half_on_them():
    board = BoardSpec(3, 3, 0.1)
    pts = np.array([[0.05, 0.05], [0.15, 0.05], [0.1, 0.05], [-0.05, -0.05]])
    p = board.dark_probability(pts, 0, 0.005)
    np.testing.assert_allclose(p, [1.0, 0.0, 0.5, 1.0], atol=1e-6)  # squares (0,0) and (-1,-1) dark, (1,0) light


# ------------------------------------------------------------------ the noise, from the data


def test_range_noise_from_neighbouring_returns():
    rng = np.random.default_rng(3)
    a = np.radians(np.arange(-60, 60, 0.25))
    r = 1.5 / np.cos(a - 0.3)  # a wall seen obliquely
    r = np.where(np.abs(a) < 0.2, r - 0.3, r)  # and an object before it: two steps
    ranges = np.tile(r, (10, 1)) + 0.002 * rng.standard_normal((10, len(a)))
    ranges[:, 100:110] = np.nan
    sigma, n = range_noise_from_scans(ranges)
    assert abs(sigma - 0.002) < 0.0001 and n > 4000  # MAD of ~4500 samples: about 2 % sd


def test_noise_is_estimated_from_a_start_ten_times_wrong_and_the_user_warned(caplog):
    sim = _hard(2)
    boards = _boards(sim)
    found = []
    for given in (None, 0.02, 0.0002):
        with caplog.at_level(logging.WARNING, logger="dem_graph.calibration.pipeline"):
            caplog.clear()
            result = calibrate_views(boards, sim.scans.ranges_m, sim.scans.angles_rad, sim.board, CalibrationOptions(range_sigma_m=given))
        found.append(result.noise.sigma_m)
        warned = [r.message for r in caplog.records if "stated range noise" in r.message]
        assert bool(warned) == (given is not None), warned
    # the residuals' noise: the 2 mm simulated, within 10 % (seeds 0-9 gave 2.0-2.4 mm before the colours settled)
    assert all(abs(s - 0.002) < 0.0002 for s in found), found
    assert max(found) - min(found) < 1e-5  # the start does not matter


def test_held_noise_needs_a_value():
    sim = _hard(2, n_views=4)
    with pytest.raises(CalibrationError, match="held"):
        calibrate_views(_boards(sim), sim.scans.ranges_m, sim.scans.angles_rad, sim.board, CalibrationOptions(estimate_range_sigma=False))


# ------------------------------------------------------------------ segments, selection, dark squares


def test_a_segment_bridges_a_dark_squares_dropout_and_not_a_wider_gap():
    a = np.radians(np.arange(-20, 20, 0.25))
    r = 1.0 / np.cos(a)  # a flat board 1 m ahead
    r[70:78] = np.nan  # 8 beams lost: 3.5 cm at 1 m
    plain = line_segments(r, a, split_tol_m=0.01, jump_m=0.02)
    bridged = line_segments(r, a, split_tol_m=0.01, jump_m=0.02, max_gap_m=0.045)
    assert len(plain) == 2 and len(bridged) == 1
    assert len(bridged[0].indices) == len(a) - 8
    assert len(line_segments(r, a, split_tol_m=0.01, jump_m=0.02, max_gap_m=0.03)) == 2  # 3.5 cm is more than 3 cm


def test_tolerances_follow_the_board_and_the_noise():
    small, large = tolerances(SMALL, 0.002), tolerances(BoardSpec(9, 6, 0.09), 0.002)
    assert small.margin_m == pytest.approx(0.015) and large.margin_m == pytest.approx(0.045)  # half a square
    assert small.plane_m == pytest.approx(0.008) and tolerances(SMALL, 0.02).plane_m == pytest.approx(0.08)  # 4 sigma
    assert small.first_plane_m < large.first_plane_m and small.gap_m == pytest.approx(0.045)
    given = tolerances(SMALL, 0.002, CalibrationOptions(board_margin_m=0.05, plane_tol_m=0.01))
    assert given.margin_m == 0.05 and given.plane_m == given.first_plane_m == 0.01


def test_only_the_boards_returns_are_selected_with_an_object_beside_it():
    sim = _hard(4)
    result = calibrate_views(_boards(sim), sim.scans.ranges_m, sim.scans.angles_rad, sim.board, CalibrationOptions())
    for k, idx in result.on_board.items():
        on, _, _ = _true_hits(sim, k)
        assert np.all(on[idx]), k  # no return of the panel or the room
    # the fixed tolerances of before (15 cm beyond the outline, 5 cm from the plane) took the panel's returns
    wide = CalibrationOptions(board_margin_m=0.15, plane_tol_m=0.05)
    result = calibrate_views(_boards(sim), sim.scans.ranges_m, sim.scans.angles_rad, sim.board, wide)
    assert any(not np.all(_true_hits(sim, k)[0][idx]) for k, idx in result.on_board.items())


def test_dark_square_bias_is_estimated_and_removed():
    sim = _hard(0)
    result = calibrate_views(_boards(sim), sim.scans.ranges_m, sim.scans.angles_rad, sim.board, CalibrationOptions())
    d = result.dark
    # 5 mm simulated; over seeds 0-9 the estimates were 4.2-5.2 mm at a formal sigma of 0.2 mm (the colour under
    # a return is taken at the estimate, and some are wrong near the edges): within 1 mm
    assert abs(d.bias_m - 0.005) < 0.001 and d.bias_sigma_m < 0.0005
    assert d.n_returns > 50
    off = calibrate_views(_boards(sim), sim.scans.ranges_m, sim.scans.angles_rad, sim.board, CalibrationOptions(dark_bias=False))
    assert off.dark.bias_m is None and "not estimated" in off.dark.summary()
    # the noise model's sensitivity: without the bias term the estimate moves; that move is part of what is reported
    assert result.model_sensitivity is not None and np.all(np.isfinite(result.model_sensitivity))
    assert np.max(result.model_sensitivity[3:]) >= 0.5 * np.max(np.abs(local(result.T_cam_laser, off.T_cam_laser)[3:]))
    unknown = calibrate_views(_boards(sim, None), sim.scans.ranges_m, sim.scans.angles_rad, sim.board, CalibrationOptions())
    assert unknown.dark.bias_m is None and "did not show which squares are dark" in unknown.dark.summary()


@pytest.mark.parametrize("seed", [0, 5, 7])
def test_small_board_with_dropouts_and_a_neighbour_meets_the_acceptance_with_the_noise_ten_times_wrong(seed):
    # acceptance over 10 seeds: rotation median under 0.2 deg, worst under 0.4; translation median under 5 mm.
    # Here three seeds, each under the worst-case bounds: 0.4 deg and 5 mm.
    sim = _hard(seed)
    result = calibrate_views(_boards(sim), sim.scans.ranges_m, sim.scans.angles_rad, sim.board, CalibrationOptions(range_sigma_m=0.02))
    rot_deg, trans_mm = _errors(sim, result.T_cam_laser)
    assert rot_deg < 0.4 and trans_mm < 5.0, (rot_deg, trans_mm)
    assert sum(v.used for v in result.views) == 15


# ------------------------------------------------------------------ the errors a new user meets


def test_a_board_given_in_squares_is_a_clear_error(tmp_path):
    sim = _hard(6, n_views=3, dark_dropout=0.0, neighbour=False)
    rec = read_radlocc_recording(write_recording(sim, tmp_path / "rec", seed=6))
    squares = BoardSpec(8, 6, 0.03)  # the board's squares, not its inner corners
    with pytest.raises(CalibrationError) as info:
        calibrate_recording(rec, CalibrationOptions(), squares)
    message = str(info.value)
    assert "8x6 inner corners" in message and "9x7 squares" in message and "--board 7x5" in message and "\n" not in message


def test_fix_range_sigma_needs_the_value(tmp_path):
    from dem_graph.cli import main

    run = CliRunner().invoke(main, ["calibrate", str(tmp_path), "--out", str(tmp_path / "o"), "--fix-range-sigma"])
    assert run.exit_code == 2 and "--fix-range-sigma holds the value of --range-sigma-m" in run.output
