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
from dataclasses import dataclass, field

import numpy as np

from dem_graph.calibration.board import BoardObservation, BoardSpec, board_from_corners, detect_corners
from dem_graph.calibration.laser_line import LineSegment, line_segments, pick_board_segment, points_from_ranges
from dem_graph.calibration.readers import CalibrationRecording, pair_nearest
from dem_graph.calibration.solve import (
    PlaneView,
    Solution,
    check_geometry,
    closed_form,
    jackknife_covariance,
    pose_groups,
    refine,
    refine_unweighted,
)
from dem_graph.errors import CalibrationError
from dem_graph.geometry.se3 import invert, transform_points
from dem_graph.progress import progress

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class CalibrationOptions:
    """Settings of a calibration; units in the names."""

    window_rad: tuple[float, float] | None = None  # search the board only between these beam angles
    max_dt_s: float = 0.05  # longest time between an image and its scan
    range_sigma_m: float = 0.02  # range noise of the scanner
    corner_sigma_px: float | None = None  # corner noise; None: from each board's reprojection residuals
    range_min_m: float = 0.1
    range_max_m: float = 30.0
    board_margin_m: float = 0.15  # how far the board may extend beyond its outer squares
    min_views: int = 3
    min_normal_spread: float = 0.03  # see solve.normal_spread
    ransac_iterations: int = 60
    seed: int = 0
    jackknife: bool = False  # also the leave-one-pose-out covariance (one more refinement per pose)


@dataclass
class ViewReport:
    """What became of one view."""

    index: int
    name: str
    used: bool = False
    reason: str = ""  # why the view was not used
    n_returns: int = 0  # laser returns on the board
    rms_mm: float | None = None  # point-to-plane RMS of those returns at the solution
    corner_rms_px: float | None = None  # board corners' reprojection RMS


@dataclass
class CalibrationResult:
    T_cam_laser: np.ndarray
    covariance: np.ndarray  # 6x6 [rot, trans] of the right perturbation T_cam_laser * Exp(xi); rad^2, m^2
    T_initial: np.ndarray
    variance_factor: float
    views: list[ViewReport]
    on_board: dict[int, np.ndarray] = field(default_factory=dict)  # view -> beam indices on the board
    boards: dict[int, BoardObservation] = field(default_factory=dict)
    jackknife_covariance: np.ndarray | None = None  # leave-one-pose-out, same convention as covariance
    n_poses: int = 0  # distinct board poses among the views used

    @property
    def rig_covariance(self) -> np.ndarray:
        """What the rig carries: the formal covariance, or the leave-one-pose-out one when that has more than
        three times the formal standard deviation on some axis (then the range errors are not white noise, as
        with the range bias real scanners show on dark squares). On white noise the leave-one-pose-out spread
        runs 1-1.8 times the formal one (simulated, 12 poses): the jackknife is conservative."""
        if self.jackknife_covariance is not None and np.any(np.diag(self.jackknife_covariance) > 9.0 * np.diag(self.covariance)):
            return self.jackknife_covariance
        return self.covariance

    @property
    def sigma_rot_deg(self) -> np.ndarray:
        return np.degrees(np.sqrt(np.diag(self.covariance)[:3]))

    def recording_advice(self, max_sigma_rot_deg: float = 0.1) -> str | None:
        """What to record next when the rotation the rig carries is known to worse than ``max_sigma_rot_deg``
        (1 sigma, about any laser axis; 0.1 deg keeps three sigma within 0.3 deg), else None. Tilting the board
        forward and back is what fixes the scan plane's tilt, turning it sideways its heading (docs/calibration.md,
        "Recording")."""
        sigma = np.degrees(np.sqrt(np.diag(self.rig_covariance)[:3]))
        worst = int(np.argmax(sigma))
        if sigma[worst] <= max_sigma_rot_deg:
            return None
        how = (
            "tilted 35-55 deg forward or back, held well to the left and right of the centre",  # the scan plane's roll
            "tilted 35-55 deg forward or back, 1.5-2 m away as well as near",  # its pitch: heights grow with distance
            "turned 20-40 deg to the left and to the right",  # the heading within the scan plane
        )[worst]
        return f"the rotation about the laser's {'xyz'[worst]} axis is known to {sigma[worst]:.2f} deg (1 sigma): record more views, with the board {how}"

    @property
    def sigma_trans_mm(self) -> np.ndarray:
        return 1000.0 * np.sqrt(np.diag(self.covariance)[3:])

    def to_dict(self) -> dict:
        used = [v for v in self.views if v.used]
        return {
            "T_cam_laser": self.T_cam_laser.tolist(),
            "covariance_rot_trans": self.covariance.tolist(),
            "covariance_convention": "right perturbation T_cam_laser * Exp([omega, v]), laser frame, gtsam order [rot, trans], rad^2 and m^2",
            "sigma_rot_deg": self.sigma_rot_deg.tolist(),
            "sigma_trans_mm": self.sigma_trans_mm.tolist(),
            "T_initial_closed_form": self.T_initial.tolist(),
            "variance_factor": self.variance_factor,
            "distinct_poses": self.n_poses,
            "rig_covariance": "jackknife" if self.rig_covariance is self.jackknife_covariance else "formal",
            "jackknife": None
            if self.jackknife_covariance is None
            else {
                "what": "leave-one-pose-out spread of the estimate, same convention as covariance_rot_trans",
                "covariance_rot_trans": self.jackknife_covariance.tolist(),
                "sigma_rot_deg": np.degrees(np.sqrt(np.diag(self.jackknife_covariance)[:3])).tolist(),
                "sigma_trans_mm": (1000.0 * np.sqrt(np.diag(self.jackknife_covariance)[3:])).tolist(),
            },
            "views_used": len(used),
            "views_rejected": len(self.views) - len(used),
            "residual_rms_mm": float(np.sqrt(np.mean([v.rms_mm**2 for v in used]))) if used else None,
            "views": [
                {
                    "index": v.index,
                    "name": v.name,
                    "used": v.used,
                    **({"reason": v.reason} if not v.used else {}),
                    "n_returns": v.n_returns,
                    "rms_mm": v.rms_mm,
                    "corner_rms_px": v.corner_rms_px,
                }
                for v in self.views
            ],
        }


def _returns_on_board(T: np.ndarray, obs: BoardObservation, points_laser: np.ndarray, board: BoardSpec, tol_m: float, margin_m: float) -> np.ndarray:
    """Mask of the finite points near the board plane and inside its outline under ``T``."""
    finite = np.all(np.isfinite(points_laser), axis=1)
    X = transform_points(T, np.where(finite[:, None], points_laser, 0.0))
    near = np.abs(X @ obs.n_cam - obs.d_m) <= tol_m
    inside = board.contains(transform_points(invert(obs.T_cam_board), X), margin_m)
    return finite & near & inside


def _segment_score(T: np.ndarray, obs: BoardObservation, seg: LineSegment, board: BoardSpec, tol_m: float, margin_m: float) -> float:
    """RMS distance of the segment from the board plane under ``T`` (inf when it is mostly outside the board)."""
    X = transform_points(T, seg.points_laser)
    if np.mean(board.contains(transform_points(invert(obs.T_cam_board), X), margin_m)) < 0.8:
        return np.inf
    return float(np.sqrt(np.mean((X @ obs.n_cam - obs.d_m) ** 2)))


def _view(obs: BoardObservation, points_laser: np.ndarray) -> PlaneView:
    return PlaneView(obs.n_cam, obs.d_m, obs.plane_covariance, points_laser)


def _best_hypothesis(candidates: dict[int, list[LineSegment]], preferred: dict[int, LineSegment], boards: dict[int, BoardObservation], board: BoardSpec, options: CalibrationOptions, tol_m: float):
    """RANSAC over views: the closed form from every view's preferred segment, then from five random views'
    ones, each refined by a quick fit and scored (MSAC) by how far each view's best candidate segment lies
    from its board, capped at ``tol_m``."""
    keys = sorted(preferred)
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
        costs = [min((_segment_score(T, boards[k], s, board, tol_m, options.board_margin_m) for s in candidates[k]), default=np.inf) for k in boards]
        score = -float(np.sum(np.minimum(np.square(costs), tol_m**2)))  # MSAC: a view off its board costs tol^2
        if score > best_score:
            best, best_score = T, score
        if max(costs) <= 0.5 * tol_m:  # every view has a segment well on its board: nothing left to find
            break
    return best


def _board_sized_segments(ranges_m: np.ndarray, angles_rad: np.ndarray, options: CalibrationOptions, min_len: float, max_len: float) -> list[LineSegment]:
    """The scan's straight segments of a length the board can show; splitting and jump limits grow with the range noise."""
    limit_m = 5.0 * options.range_sigma_m
    segs = line_segments(
        ranges_m, angles_rad, options.range_min_m, options.range_max_m, options.window_rad, split_tol_m=max(0.07, limit_m), jump_m=max(0.08, limit_m)
    )
    return [s for s in segs if min_len <= s.length_m <= max_len]


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
    tol_m = max(0.05, 4.0 * options.range_sigma_m)  # wide: the Huber loss, not a cut, deals with the tails
    min_len, max_len = 2.0 * board.square_m, board.diagonal_m + 2.0 * options.board_margin_m
    obs, candidates, preferred = {}, {}, {}
    for k in range(n):
        if reports[k].reason:
            continue
        if boards[k] is None:
            reports[k].reason = "no board found in the image"
            continue
        reports[k].corner_rms_px = boards[k].reprojection_rms_px
        segs = _board_sized_segments(ranges_m[k], angles_rad, options, min_len, max_len)
        if not segs:
            reports[k].reason = "no straight laser segment of the board's size in the scan"
            continue
        obs[k], candidates[k] = boards[k], segs
        preferred[k] = pick_board_segment(segs, min_len, max_len)
    usable = len(obs)
    if usable < options.min_views:
        raise CalibrationError(f"{usable} usable views (board found and a laser segment of its size), at least {options.min_views} are needed")
    check_geometry([_view(o, np.zeros((0, 3))) for o in obs.values()], options.min_views, options.min_normal_spread)
    T = _best_hypothesis(candidates, preferred, obs, board, options, max(0.04, 2.0 * options.range_sigma_m))
    if T is None:
        raise CalibrationError("no consistent initial estimate: the laser segments and boards do not agree; give --window-deg around the board")
    solution: Solution | None = None
    selected: dict[int, np.ndarray] = {}
    points = {k: points_from_ranges(ranges_m[k], angles_rad) for k in obs}  # each scan's returns, laser frame
    for _ in range(2):
        selected = {}
        for k, o in obs.items():
            mask = _returns_on_board(T, o, points[k], board, tol_m, options.board_margin_m)
            if mask.sum() >= 5:
                selected[k] = np.flatnonzero(mask)
        views = [_view(obs[k], points[k][idx]) for k, idx in selected.items()]
        check_geometry(views, options.min_views, options.min_normal_spread)
        if solution is None:
            T_closed_form = closed_form(views)  # reported; the refinement starts from the hypothesis
        solution = refine(views, T, options.range_sigma_m)
        T = solution.T_cam_laser
    for k in obs:
        if k not in selected:
            reports[k].reason = "no laser return on the board"
    for (k, idx), rms in zip(selected.items(), solution.view_rms_m):
        reports[k].used, reports[k].n_returns, reports[k].rms_mm = True, len(idx), 1000.0 * float(rms)
    log.info("calibrated from %d of %d views, variance factor %.2f", len(selected), n, solution.variance_factor)
    result = CalibrationResult(solution.T_cam_laser, solution.covariance, T_closed_form, solution.variance_factor, reports, selected, obs)
    result.n_poses = len(pose_groups(views))
    if options.jackknife:
        found = jackknife_covariance(views, solution.T_cam_laser, options.range_sigma_m)
        if found is None:
            log.warning("fewer than four distinct board poses: no leave-one-pose-out spread")
        else:
            result.jackknife_covariance = found[0]
    advice = result.recording_advice()
    if advice:
        log.warning(advice)
    return result


def calibrate_recording(recording: CalibrationRecording, options: CalibrationOptions = CalibrationOptions(), board: BoardSpec | None = None) -> CalibrationResult:
    """Pair images with scans, find the boards in the images and calibrate (see :func:`calibrate_views`).
    ``board``, when given, replaces the recording's own (a bag has none)."""
    board = board or recording.board
    if board is None:
        raise CalibrationError("the board's size is not known: the recording does not give it (give --board COLSxROWS and --square-m)")
    scans = recording.scans
    pairs = pair_nearest(recording.image_times_s, scans.times_s, options.max_dt_s)
    n = len(recording.image_names)
    reports = [ViewReport(k, recording.image_names[k]) for k in range(n)]
    boards: list[BoardObservation | None] = [None] * n
    ranges = np.full((n, scans.n_beams), np.nan)
    K, dist = recording.intrinsics.K, recording.intrinsics.distortion
    for k in progress(range(n), total=n, desc="boards", unit="image"):
        if pairs[k] < 0:
            reports[k].reason = f"no scan within {options.max_dt_s} s of the image"
            continue
        ranges[k] = scans.ranges_m[pairs[k]]
        corners = detect_corners(recording.load_image(k), board)
        if corners is None:
            log.warning("%s: no %dx%d board found", recording.image_names[k], board.cols, board.rows)
            continue
        boards[k] = board_from_corners(corners, board, K, dist, options.corner_sigma_px)
    return calibrate_views(boards, ranges, scans.angles_rad, board, options, reports=reports)
