"""The calibration from end to end: boards and scans in, ``T_cam_laser`` with its covariance and a report per view out.

:func:`calibrate_views` works on arrays (board observations and scans); :func:`calibrate_recording` owns
the loop over a recording (any layout: it asks the :class:`~dem_graph.calibration.readers.CalibrationRecording`
for each image): it pairs images with scans by time, reads the images and finds the boards.

Which returns lie on the board is decided with the camera's help. Each scan offers straight segments of
board-like length (:mod:`~dem_graph.calibration.laser_line`); random sets of five views' preferred
segments give closed-form hypotheses, and the hypothesis under which most views have a segment on their
board plane (and inside the board's outline) wins. Under it, each view's on-board returns are all the
returns near the plane and inside the outline; the refinement then reselects them once more.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace

import numpy as np

from dem_graph.calibration.board import BoardObservation, BoardSpec, board_from_corners, dark_parity, detect_corners
from dem_graph.calibration.laser_line import LineSegment, line_segments, pick_board_segment, points_from_ranges, range_noise_from_scans
from dem_graph.calibration.readers import CalibrationRecording, pair_nearest
from dem_graph.calibration.result import CalibrationResult, DarkSquares, RangeNoise, Tolerances, ViewReport
from dem_graph.calibration.solve import (
    PlaneView,
    Solution,
    check_geometry,
    closed_form,
    estimate_range_sigma,
    jackknife_covariance,
    pose_groups,
    refine,
    refine_unweighted,
)
from dem_graph.errors import CalibrationError
from dem_graph.geometry.lie import local
from dem_graph.geometry.se3 import invert, transform_points
from dem_graph.progress import progress

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class CalibrationOptions:
    """Settings of a calibration; units in the names. Tolerances left at None are derived from the board's
    size and the range noise (:func:`tolerances`)."""

    window_rad: tuple[float, float] | None = None  # search the board only between these beam angles
    max_dt_s: float = 0.05  # longest time between an image and its scan
    range_sigma_m: float | None = None  # range noise: a starting value (None: the scans' own); see estimate_range_sigma
    estimate_range_sigma: bool = True  # False: hold range_sigma_m, which must then be given
    corner_sigma_px: float | None = None  # corner noise; None: from each board's reprojection residuals
    range_min_m: float = 0.1
    range_max_m: float = 30.0
    board_margin_m: float | None = None  # how far the board may extend beyond its outer squares [half a square]
    plane_tol_m: float | None = None  # farthest an on-board return may lie from the board's plane [4 sigma, at least 3 mm]
    dark_bias: bool = True  # estimate the range bias of returns on dark squares (when the images show which are dark)
    min_views: int = 3
    min_normal_spread: float = 0.03  # see solve.normal_spread
    ransac_iterations: int = 200  # at most; it stops once every view has a segment on its board
    seed: int = 0
    jackknife: bool = False  # also the leave-one-pose-out covariance (one more refinement per pose)


def tolerances(board: BoardSpec, range_sigma_m: float, options: CalibrationOptions = CalibrationOptions()) -> Tolerances:
    """Tolerances from the board's square and the range noise; ``options`` may set the margin and the plane's.

    The hypothesis from segments is good to about a tenth of a square on the board (a few millimetres on a
    3 cm board, a centimetre on a 9 cm one); the first selection allows a quarter of a square beyond four
    sigma, as the noise the scans show can be less than what the board's returns carry (a scanner that
    smooths neighbouring beams). A run is split where it bends by half a square beyond two sigma: a real
    scanner's spikes (a Hokuyo's reach 3 cm on a 9 cm board) must not cut the board in pieces, while a
    neighbouring object, which the selection's outline and plane tolerance keep out, may stay joined. A gap of
    a square and a half is what a dark square that returns nothing leaves in a run."""
    sq, sigma = board.square_m, range_sigma_m
    plane = options.plane_tol_m if options.plane_tol_m is not None else max(4.0 * sigma, 0.003)
    return Tolerances(
        margin_m=options.board_margin_m if options.board_margin_m is not None else 0.5 * sq,
        plane_m=plane,
        first_plane_m=plane if options.plane_tol_m is not None else plane + 0.25 * sq,
        hypothesis_m=2.0 * sigma + 0.5 * sq,
        hypothesis_margin_m=max(1.5 * sq, options.board_margin_m or 0.0),
        split_m=max(5.0 * sigma, 0.5 * sq + 2.0 * sigma),
        jump_m=max(5.0 * sigma, 0.2 * sq),
        gap_m=1.5 * sq,
    )


def _returns_on_board(T: np.ndarray, obs: BoardObservation, points_laser: np.ndarray, board: BoardSpec, tol_m: float, margin_m: float) -> np.ndarray:
    """Mask of the finite points near the board plane and inside its outline under ``T``."""
    finite = np.all(np.isfinite(points_laser), axis=1)
    X = transform_points(T, np.where(finite[:, None], points_laser, 0.0))
    near = np.abs(X @ obs.n_cam - obs.d_m) <= tol_m
    inside = board.contains(transform_points(invert(obs.T_cam_board), X), margin_m)
    return finite & near & inside


def _segment_score(T: np.ndarray, obs: BoardObservation, seg: LineSegment, board: BoardSpec, margin_m: float) -> float:
    """RMS distance of the segment from the board plane under ``T`` (inf when it is mostly outside the board)."""
    X = transform_points(T, seg.points_laser)
    if np.mean(board.contains(transform_points(invert(obs.T_cam_board), X), margin_m)) < 0.8:
        return np.inf
    return float(np.sqrt(np.mean((X @ obs.n_cam - obs.d_m) ** 2)))


def _view(obs: BoardObservation, points_laser: np.ndarray) -> PlaneView:
    return PlaneView(obs.n_cam, obs.d_m, obs.plane_covariance, points_laser)


def _best_hypothesis(
    candidates: dict[int, list[LineSegment]], preferred: dict[int, LineSegment], boards: dict[int, BoardObservation], board: BoardSpec, options: CalibrationOptions, tol: Tolerances
):
    """RANSAC over views: the closed form from every view's preferred segment, then from five random views'
    ones, each refined by a quick fit and scored (MSAC) by how far each view's best candidate segment lies
    from its board, capped at ``tol_m``."""
    keys = sorted(preferred)
    tol_m = tol.hypothesis_m
    rng = np.random.default_rng(options.seed)
    best, best_score = None, -np.inf
    sample_size = min(5, len(keys))
    for i in range(options.ransac_iterations):
        pick = keys if i == 0 else rng.choice(keys, size=sample_size, replace=False)
        views = [_view(boards[k], preferred[k].points_laser) for k in pick]
        try:
            T = refine_unweighted(views, closed_form(views), tol_m)
        except (CalibrationError, np.linalg.LinAlgError):
            continue
        costs = [min((_segment_score(T, boards[k], s, board, tol.hypothesis_margin_m) for s in candidates[k]), default=np.inf) for k in boards]
        score = -float(np.sum(np.minimum(np.square(costs), tol_m**2)))  # MSAC: a view off its board costs tol^2
        if score > best_score:
            best, best_score = T, score
        if max(costs) <= 0.5 * tol_m:  # every view has a segment well on its board: nothing left to find
            break
    return best


def _board_sized_segments(ranges_m: np.ndarray, angles_rad: np.ndarray, options: CalibrationOptions, tol: Tolerances, min_len: float, max_len: float) -> list[LineSegment]:
    """The scan's straight segments of a length the board can show."""
    segs = line_segments(
        ranges_m, angles_rad, options.range_min_m, options.range_max_m, options.window_rad, split_tol_m=tol.split_m, jump_m=tol.jump_m, max_gap_m=tol.gap_m
    )
    return [s for s in segs if min_len <= s.length_m <= max_len]


def _pre_fit_sigma(ranges_m: np.ndarray, angles_rad: np.ndarray, board: BoardSpec, options: CalibrationOptions, sigma_scans: float) -> float:
    """The range noise the segmentation and the first selection assume, before any fit: the larger of the scans'
    neighbour-to-neighbour noise and the median RMS about their lines of the board-sized straight segments
    (found with loose tolerances of half a square). A scanner that smooths neighbouring beams, or reads dark
    squares long, shows the first small and the second as large as the fit will find it (a Hokuyo: 3 and 9 mm)."""
    floor = sigma_scans if np.isfinite(sigma_scans) and sigma_scans > 0 else options.range_sigma_m or 0.01
    loose = 0.5 * board.square_m + 5.0 * floor
    rms = []
    for row in ranges_m:
        segs = line_segments(row, angles_rad, options.range_min_m, options.range_max_m, options.window_rad, split_tol_m=loose, jump_m=loose, max_gap_m=1.5 * board.square_m)
        best = pick_board_segment(segs, 2.0 * board.square_m, board.diagonal_m + board.square_m)
        if best is not None:
            rms.append(best.rms_m)
    return max(floor, float(np.median(rms))) if rms else floor


def _mark_dark(view: PlaneView, T: np.ndarray, obs: BoardObservation, board: BoardSpec) -> PlaneView:
    """The view with each return's probability of lying on a dark square (under ``T``), when the board's colours
    are known. A return is placed where its beam meets the board's plane, not at its range: at a slant, range
    noise and the bias itself move a return across a square's edge. Its place is taken as known to a
    twentieth of a square (the first estimate's error on the board is about a tenth)."""
    if obs.dark_parity is None:
        return view
    beams_cam = view.points_laser @ T[:3, :3].T / np.maximum(np.linalg.norm(view.points_laser, axis=1), 1e-9)[:, None]
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (obs.d_m - obs.n_cam @ T[:3, 3]) / (beams_cam @ obs.n_cam)
    X_board = transform_points(invert(obs.T_cam_board), T[:3, 3] + s[:, None] * beams_cam)
    return replace(view, dark=board.dark_probability(X_board, obs.dark_parity, 0.05 * board.square_m))


def calibrate_views(
    boards: list[BoardObservation | None],
    ranges_m: np.ndarray,
    angles_rad: np.ndarray,
    board: BoardSpec,
    options: CalibrationOptions = CalibrationOptions(),
    names: list[str] | None = None,
    reports: list[ViewReport] | None = None,
) -> CalibrationResult:
    """``T_cam_laser`` from one board observation (None: no board found) and one scan (NaN row: none) per view.

    Raises :class:`CalibrationError` when fewer than ``options.min_views`` views remain usable or their
    boards are (nearly) parallel.
    """
    ranges_m = np.asarray(ranges_m, dtype=float)
    n = len(boards)
    names = names or [f"view {k}" for k in range(n)]
    reports = reports or [ViewReport(k, names[k]) for k in range(n)]
    if not options.estimate_range_sigma and options.range_sigma_m is None:
        raise CalibrationError("the range noise is held (estimate_range_sigma off) but not given: give range_sigma_m")
    with_board = [k for k in range(n) if boards[k] is not None and not reports[k].reason]
    sigma_scans, n_triples = range_noise_from_scans(ranges_m[with_board], options.range_min_m, options.range_max_m) if with_board else (np.nan, 0)
    sigma = _pre_fit_sigma(ranges_m[with_board], angles_rad, board, options, sigma_scans)
    if not options.estimate_range_sigma:
        sigma = float(options.range_sigma_m)
    tol = tolerances(board, sigma, options)
    min_len, max_len = 2.0 * board.square_m, board.diagonal_m + 2.0 * tol.hypothesis_margin_m
    obs, candidates, preferred = {}, {}, {}
    for k in range(n):
        if reports[k].reason:
            continue
        if boards[k] is None:
            reports[k].reason = f"no {board.cols}x{board.rows} inner-corner board found in the image"
            continue
        reports[k].corner_rms_px = boards[k].reprojection_rms_px
        segs = _board_sized_segments(ranges_m[k], angles_rad, options, tol, min_len, max_len)
        if not segs:
            reports[k].reason = "no straight laser segment of the board's size in the scan"
            continue
        obs[k], candidates[k] = boards[k], segs
        preferred[k] = pick_board_segment(segs, min_len, max_len)
    usable = len(obs)
    if usable < options.min_views:
        raise CalibrationError(f"{usable} usable views (board found and a laser segment of its size), at least {options.min_views} are needed")
    check_geometry([_view(o, np.zeros((0, 3))) for o in obs.values()], options.min_views, options.min_normal_spread)
    T = _best_hypothesis(candidates, preferred, obs, board, options, tol)
    if T is None:
        raise CalibrationError("no consistent initial estimate: the laser segments and boards do not agree; give --window-deg around the board")
    solution: Solution | None = None
    selected: dict[int, np.ndarray] = {}
    views: list[PlaneView] = []
    points = {k: points_from_ranges(ranges_m[k], angles_rad) for k in obs}  # each scan's returns, laser frame
    sigma_fit = options.range_sigma_m if options.range_sigma_m is not None else sigma
    widest_plane_m = plane_tol = tol.first_plane_m
    for selection in range(3):  # the colours of the squares under the return follow the estimate: two more rounds
        if selection:  # four sigma of the noise the fit found, never wider than the first selection
            tol = tolerances(board, sigma_fit, options)
            plane_tol = min(tol.plane_m, widest_plane_m)
        selected, views = {}, []
        for k, o in obs.items():
            idx = np.flatnonzero(_returns_on_board(T, o, points[k], board, plane_tol, tol.margin_m))
            if len(idx) >= 5:
                selected[k] = idx
                views.append(_mark_dark(_view(o, points[k][idx]), T, o, board))
        check_geometry(views, options.min_views, options.min_normal_spread)
        if solution is None:
            T_closed_form = closed_form(views)  # reported; the refinement starts from the hypothesis
        if options.estimate_range_sigma:
            solution, sigma_fit = estimate_range_sigma(views, T, sigma_fit, dark_bias=options.dark_bias)
        else:
            solution = refine(views, T, sigma_fit, dark_bias=options.dark_bias)
        T = solution.T_cam_laser
    for k in obs:
        if k not in selected:
            reports[k].reason = "no laser return on the board"
    for (k, idx), rms in zip(selected.items(), solution.view_rms_m):
        reports[k].used, reports[k].n_returns, reports[k].rms_mm = True, len(idx), 1000.0 * float(rms)
    log.info("calibrated from %d of %d views, range noise %.1f mm, variance factor %.2f", len(selected), n, 1000 * sigma_fit, solution.variance_factor)
    result = CalibrationResult(solution.T_cam_laser, solution.covariance, T_closed_form, solution.variance_factor, reports, selected, obs)
    result.n_poses = len(pose_groups(views))
    result.noise = RangeNoise(sigma_fit, float(sigma_scans), n_triples, options.range_sigma_m, options.estimate_range_sigma)
    result.dark = DarkSquares(solution.n_dark, solution.n_points, solution.dark_bias_m, solution.dark_bias_sigma_m, sum(o.dark_parity is not None for o in obs.values()))
    result.tolerances = tol
    warning = result.noise.warning()
    if warning:
        log.warning(warning)
    result.model_sensitivity = model_sensitivity(views, solution, sigma_fit)
    if options.jackknife:
        found = jackknife_covariance(views, solution.T_cam_laser, sigma_fit, dark_bias=options.dark_bias)
        if found is None:
            log.warning("fewer than four distinct board poses: no leave-one-pose-out spread")
        else:
            result.jackknife_covariance = found[0]
    advice = result.recording_advice()
    if advice:
        log.warning(advice)
    return result


def model_sensitivity(views: list[PlaneView], solution: Solution, range_sigma_m: float) -> np.ndarray:
    """How far the estimate moves when the noise model changes: refined again with the range noise halved,
    with it doubled, and (when it was estimated) without the dark squares' bias; per axis of the right
    perturbation [rot, trans] (rad, m), the largest move. A change the formal covariance cannot show."""
    moves = []
    alternatives = [(0.5 * range_sigma_m, True), (2.0 * range_sigma_m, True)]
    if solution.dark_bias_m is not None:
        alternatives.append((range_sigma_m, False))
    for sigma, with_bias in alternatives:
        other = refine(views, solution.T_cam_laser, sigma, passes=1, dark_bias=with_bias)
        moves.append(np.abs(local(solution.T_cam_laser, other.T_cam_laser)))
    return np.max(moves, axis=0)


def calibrate_recording(recording: CalibrationRecording, options: CalibrationOptions = CalibrationOptions(), board: BoardSpec | None = None) -> CalibrationResult:
    """Pair images with scans, find the boards in the images and calibrate (see :func:`calibrate_views`).
    ``board``, when given, replaces the recording's own (a bag has none)."""
    board = board or recording.board
    if board is None:
        raise CalibrationError("the board's size is not known: the recording does not give it (give --board COLSxROWS and --square-m)")
    scans = recording.scans
    pairs = pair_nearest(recording.image_times_s, scans.times_s, options.max_dt_s)
    n = len(recording.image_names)
    reports = [ViewReport(k, recording.image_names[k], recording.view_numbers[k]) for k in range(n)]
    boards: list[BoardObservation | None] = [None] * n
    ranges = np.full((n, scans.n_beams), np.nan)
    K, dist = recording.intrinsics.K, recording.intrinsics.distortion
    for k in progress(range(n), total=n, desc="boards", unit="image"):
        if pairs[k] < 0:
            reports[k].reason = f"no scan within {options.max_dt_s} s of the image"
            continue
        ranges[k] = scans.ranges_m[pairs[k]]
        image = recording.load_image(k)
        corners = detect_corners(image, board)
        if corners is None:
            log.warning("%s: no %dx%d inner-corner board found", recording.image_names[k], board.cols, board.rows)
            continue
        found = board_from_corners(corners, board, K, dist, options.corner_sigma_px)
        boards[k] = replace(found, dark_parity=dark_parity(image, found, board, K, dist))
    searched = sum(pairs >= 0)
    if searched and not any(b is not None for b in boards):
        raise CalibrationError(no_board_message(board, searched))
    return calibrate_views(boards, ranges, scans.angles_rad, board, options, reports=reports)


def no_board_message(board: BoardSpec, n_images: int) -> str:
    """The error when no image shows the board: the inner corners searched for, and what to give if the
    board's size was given in squares."""
    cols, rows = board.squares
    hint = f"--board {board.cols - 1}x{board.rows - 1}" if min(board.cols, board.rows) > 2 else "a board of at least 3x3 squares"
    return (
        f"no board of {board.cols}x{board.rows} inner corners (a board of {cols}x{rows} squares) found in any of {n_images} images; "
        f"--board counts inner corners: if the board has {board.cols}x{board.rows} squares, give {hint}"
    )
