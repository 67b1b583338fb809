"""The laser returns that lie on the board: straight segments of a planar scan, and the one that is the board.

A scan is cut into runs of neighbouring returns (a range jump or missing beams end a run), each run is
split where it bends (recursive split at the farthest point from the chord), and each straight piece gets
a total-least-squares line with outliers rejected (residuals beyond three robust standard deviations).
The board is the straight piece whose length fits the board and which stands in front of what lies
beside it (the returns just past both of its ends are farther away, or missing), the longest such; a
user-given angular window narrows the search when the scene has other board-like objects.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class LineSegment:
    """A straight piece of a scan: its inlier beams, line fit and whether it stands free of its neighbours."""

    indices: np.ndarray  # beam indices of the inliers
    points_laser: np.ndarray  # (M,3) inlier points, laser frame (z = 0)
    length_m: float
    rms_m: float  # perpendicular residuals of the inliers
    free_ends: int  # 0, 1 or 2 ends with a jump to farther (or missing) returns


def points_from_ranges(ranges_m: np.ndarray, angles_rad: np.ndarray) -> np.ndarray:
    """(B,3) points in the laser frame: ``r (cos a, sin a, 0)``; NaN rows where there is no return."""
    r = np.asarray(ranges_m, dtype=float)
    return np.stack([r * np.cos(angles_rad), r * np.sin(angles_rad), np.zeros_like(r)], axis=1)


def range_noise_from_scans(ranges_m: np.ndarray, range_min_m: float = 0.1, range_max_m: float = 30.0) -> tuple[float, int]:
    """The scanner's range noise (metres, one sigma) seen in the scans themselves, and the number of samples.

    Over three neighbouring returns of a smooth surface the second difference ``r[k-1] - 2 r[k] + r[k+1]``
    is nearly all noise, of variance ``6 sigma^2`` (the curvature of a plane seen at a quarter degree adds
    well under a tenth of a millimetre at the ranges of a calibration). Edges, steps and biased dark squares
    are a minority, and the median absolute deviation ignores them. NaN when fewer than 30 triples exist."""
    r = np.atleast_2d(np.asarray(ranges_m, dtype=float))
    with np.errstate(invalid="ignore"):
        r = np.where((r >= range_min_m) & (r <= range_max_m), r, np.nan)
    d2 = (r[:, :-2] - 2.0 * r[:, 1:-1] + r[:, 2:]).ravel()
    d2 = d2[np.isfinite(d2)]
    if len(d2) < 30:
        return float("nan"), len(d2)
    mad = float(np.median(np.abs(d2 - np.median(d2))))
    return 1.4826 * mad / np.sqrt(6.0), len(d2)


def _fit_line(xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Centroid, unit direction and signed perpendicular residuals of a total-least-squares line."""
    c = xy.mean(axis=0)
    _, _, Vt = np.linalg.svd(xy - c, full_matrices=False)
    normal = np.array([-Vt[0, 1], Vt[0, 0]])
    return c, Vt[0], (xy - c) @ normal


def _split(xy: np.ndarray, lo: int, hi: int, tol_m: float, out: list[tuple[int, int]]) -> None:
    """Split ``xy[lo:hi]`` recursively at the point farthest from the chord until every piece is within ``tol_m``."""
    if hi - lo < 3:
        out.append((lo, hi))
        return
    a, b = xy[lo], xy[hi - 1]
    chord = b - a
    length = np.linalg.norm(chord)
    rel = xy[lo:hi] - a
    dist = np.abs(rel[:, 0] * chord[1] - rel[:, 1] * chord[0]) / length if length > 0 else np.linalg.norm(rel, axis=1)
    k = int(np.argmax(dist))
    if dist[k] <= tol_m or k in (0, hi - lo - 1):
        out.append((lo, hi))
        return
    _split(xy, lo, lo + k + 1, tol_m, out)
    _split(xy, lo + k, hi, tol_m, out)


def line_segments(
    ranges_m: np.ndarray,
    angles_rad: np.ndarray,
    range_min_m: float = 0.1,
    range_max_m: float = 30.0,
    window_rad: tuple[float, float] | None = None,
    min_points: int = 8,
    split_tol_m: float = 0.07,
    jump_m: float = 0.08,
    max_gap_m: float = 0.0,
) -> list[LineSegment]:
    """Every straight piece of a scan with at least ``min_points`` inliers (see the module's docstring).

    A run of returns goes on across missing beams (dark squares often return nothing) while the gap spans at
    most ``max_gap_m`` at its range (one missing beam always), and across a step no larger than ``jump_m``, or
    five beam spacings per beam crossed."""
    r = np.asarray(ranges_m, dtype=float)
    angles_rad = np.asarray(angles_rad, dtype=float)
    inc = float(np.median(np.diff(angles_rad)))
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(r) & (r >= range_min_m) & (r <= range_max_m)
    if window_rad is not None:
        valid &= (angles_rad >= window_rad[0]) & (angles_rad <= window_rad[1])
    idx = np.flatnonzero(valid)
    if len(idx) < min_points:
        return []
    xy = points_from_ranges(r[idx], angles_rad[idx])[:, :2]
    step = np.linalg.norm(np.diff(xy, axis=0), axis=1)
    beams_crossed = np.diff(idx)
    spacing_m = r[idx[:-1]] * abs(inc)
    limit = np.maximum(jump_m, 5.0 * spacing_m * beams_crossed)
    too_wide = (beams_crossed > 2) & ((beams_crossed - 1) * spacing_m > max_gap_m)
    breaks = np.flatnonzero(too_wide | (step > limit)) + 1
    segments = []
    for run in np.split(np.arange(len(idx)), breaks):
        if len(run) < min_points:
            continue
        pieces: list[tuple[int, int]] = []
        _split(xy[run], 0, len(run), split_tol_m, pieces)
        for lo, hi in pieces:
            if hi - lo < min_points:
                continue
            segment = _robust_segment(xy[run[lo:hi]], idx[run[lo:hi]], r, min_points)
            if segment is not None:
                segments.append(segment)
    return segments


def _robust_segment(xy: np.ndarray, beams: np.ndarray, ranges_m: np.ndarray, min_points: int) -> LineSegment | None:
    keep = np.ones(len(xy), dtype=bool)
    for _ in range(4):
        c, direction, res = _fit_line(xy[keep])
        res_all = (xy - c) @ np.array([-direction[1], direction[0]])
        sigma = max(1.4826 * float(np.median(np.abs(res - np.median(res)))), 0.003)
        new_keep = np.abs(res_all) <= 3.0 * sigma
        if new_keep.sum() < min_points:
            return None
        if np.array_equal(new_keep, keep):
            break
        keep = new_keep
    c, direction, res = _fit_line(xy[keep])
    along = (xy[keep] - c) @ direction
    beams_in = beams[keep]
    free = sum(_end_is_free(ranges_m, int(b), step) for b, step in ((beams_in[0], -1), (beams_in[-1], 1)))
    points = np.column_stack([xy[keep], np.zeros(int(keep.sum()))])
    return LineSegment(beams_in, points, float(along.max() - along.min()), float(np.sqrt(np.mean(res**2))), free)


def _end_is_free(ranges_m: np.ndarray, beam: int, step: int, n_look: int = 3, margin_m: float = 0.05) -> bool:
    """Whether the returns just past ``beam`` (towards ``step``) are farther than it, or missing."""
    look = beam + step * np.arange(1, n_look + 1)
    look = look[(look >= 0) & (look < len(ranges_m))]
    if len(look) == 0:
        return False
    beyond = ranges_m[look]
    with np.errstate(invalid="ignore"):
        return bool(np.all(~np.isfinite(beyond) | (beyond > ranges_m[beam] + margin_m)))


def pick_board_segment(segments: list[LineSegment], min_length_m: float, max_length_m: float) -> LineSegment | None:
    """The segment that is most likely the board: length within the limits, most free ends, then most returns."""
    fits = [s for s in segments if min_length_m <= s.length_m <= max_length_m]
    if not fits:
        return None
    return max(fits, key=lambda s: (s.free_ends, len(s.indices)))
