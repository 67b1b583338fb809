"""The per-point work after the correlation: gate, best and second peak, sub-pixel refinement.

One compiled function (numba, about 5 us a call) instead of some twenty small numpy calls:
tracking calls it once per point and frame, so its fixed cost matters more than its arithmetic.
A whole ``PatchTracker.track`` on an 800x600 frame went from 111 to 54 us with a 4 px^2 gate
and from 139 to 75 us with 25 px^2 (median of three runs).

:func:`select_match` takes the NCC score grid of a search and returns the status code, the best
candidate, its score, the best other peak and the sub-pixel offset; :mod:`.tracker` turns them into
a :class:`~dem_graph.frontend.tracker.TrackResult`.

The correlation itself is :func:`ncc_grid` (OpenCV's ``TM_CCOEFF_NORMED``, in float64). Called once
per point, ``cv2.matchTemplate`` cost 18 us on a 25 x 21 region with a 15 x 15 template, most of it
the call's own overhead.

For a whole frame (``PatchTracker.track_many``), :func:`plan_searches` computes every point's gate,
region and template spread in one call, :func:`ncc_grids` every point's score grid, and
:func:`select_matches` runs :func:`select_match` over every point's score grid in one call, with the
same floating-point operations as the per-point path.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from dem_graph.frontend.vector_kernel import BLOCK_LANES, BLOCK_ROWS, correlate_block

OK, LOW_SCORE, AMBIGUOUS = 0, 1, 2
# the best candidate is on the score grid's outer ring, which exists only where the image border cut it:
# the scores beyond it are unknown, so it may be the slope of a peak outside the image
PEAK_AT_BORDER = 9
# a neighbour of the best candidate outside the gate scores higher: the peak is outside the gate
PEAK_OUTSIDE_GATE = 10


@numba.njit(cache=True, nogil=True)
def _parabola_offset(left: float, centre: float, right: float) -> float:
    """Vertex offset of the parabola through three equally spaced samples, clamped to +-0.5."""
    curvature = left - 2.0 * centre + right
    if not curvature < 0.0:  # not a maximum (or NaN): keep the integer peak
        return 0.0
    return min(0.5, max(-0.5, 0.5 * (left - right) / curvature))


@numba.njit(cache=True, nogil=True)
def subpixel_offset(scores: np.ndarray, i: int, j: int) -> tuple[float, float]:
    """Sub-pixel (u, v) offset of the score peak at row ``i``, column ``j``, each clamped to +-0.5.

    A 2-D quadratic through the 3x3 neighbourhood (gradient and Hessian, cross term included) when
    the peak is inside the grid and the Hessian is negative definite; otherwise a 1-D parabola
    along each axis whose two neighbours exist. The cross term matters: the NCC peak of a small
    window of natural texture is often a tilted ellipse, and per-axis parabolas through the
    integer peak then miss its top (on blurred noise, 15x15 templates: worst error 0.47 px with
    per-axis parabolas, 0.11 px with the 2-D fit).
    """
    n_rows, n_cols = scores.shape
    inner_u = 0 < j < n_cols - 1
    inner_v = 0 < i < n_rows - 1
    if inner_u and inner_v:
        c = float(scores[i, j])
        g_u = 0.5 * (float(scores[i, j + 1]) - float(scores[i, j - 1]))
        g_v = 0.5 * (float(scores[i + 1, j]) - float(scores[i - 1, j]))
        h_uu = float(scores[i, j + 1]) - 2.0 * c + float(scores[i, j - 1])
        h_vv = float(scores[i + 1, j]) - 2.0 * c + float(scores[i - 1, j])
        h_uv = 0.25 * (float(scores[i + 1, j + 1]) - float(scores[i + 1, j - 1]) - float(scores[i - 1, j + 1]) + float(scores[i - 1, j - 1]))
        det = h_uu * h_vv - h_uv * h_uv
        if h_uu < 0.0 and det > 0.0:
            off_u = -(h_vv * g_u - h_uv * g_v) / det
            off_v = -(h_uu * g_v - h_uv * g_u) / det
            return min(0.5, max(-0.5, off_u)), min(0.5, max(-0.5, off_v))
    off_u = _parabola_offset(float(scores[i, j - 1]), float(scores[i, j]), float(scores[i, j + 1])) if inner_u else 0.0
    off_v = _parabola_offset(float(scores[i - 1, j]), float(scores[i, j]), float(scores[i + 1, j])) if inner_v else 0.0
    return off_u, off_v


@numba.njit(cache=True, nogil=True)
def select_match(
    scores: np.ndarray,
    i0: int,
    i1: int,
    j0: int,
    j1: int,
    use_ellipse: bool,
    a: float,
    b: float,
    c: float,
    gamma: float,
    dv0: float,
    du0: float,
    i_near: int,
    j_near: int,
    min_score: float,
    exclusion_radius_px: float,
    ambiguity_margin: float,
    subpixel: bool,
    refuse_outside_gate: bool = False,
):
    """Pick the match in the score grid ``scores`` (row i, column j).

    Candidates are rows ``i0:i1`` and columns ``j0:j1``; with ``use_ellipse``, only those inside
    ``a du^2 + 2 b du dv + c dv^2 <= gamma``, where ``dv = i - i0 + dv0`` and ``du = j - j0 + du0``
    are the offsets from the prediction, plus the candidate ``(i_near, j_near)`` nearest to it.
    The second peak is the best candidate that is a 3x3 local maximum of the whole grid and lies
    farther than ``exclusion_radius_px`` from the best.

    The grid holds a one-pixel ring around the candidates unless the image border cut it off; a
    best candidate on the grid's outer ring is therefore at the image border, where the scores
    beyond it are unknown. It is refused (PEAK_AT_BORDER): taken, it is the last row or column
    where the template fits, not the point, and a point leaving the image (ground points leave
    by the bottom row as the vehicle drives forward) would be measured short of where it is, by
    up to the distance it has left the usable image. On ``paper`` seed 1, 472 of 211 000 matches
    had their true position past that row and were off by -1.09 px on average, all upwards.

    With ``refuse_outside_gate``, a best candidate with a neighbour scoring higher (necessarily
    outside the gate, in the ring) is refused too (PEAK_OUTSIDE_GATE): the peak is outside the
    gate, and the candidate on the gate's edge is off towards the prediction (tests/test_tracker.py:
    0.23-2.7 px when taken). Off by default: an estimator whose gate is too tight then loses the
    matches (docs/isam2_design.md, "Where the row bias came from").

    Returns ``(status, i_best, j_best, best, second, off_u, off_v)``; ``best`` and ``second`` are
    NaN when there is none (``second`` also for the two PEAK_ refusals), the offsets 0 unless the status is OK.
    """
    n_rows, n_cols = scores.shape
    inside = np.zeros((n_rows, n_cols), dtype=np.bool_)
    for i in range(i0, i1):
        if use_ellipse:
            dv = i - i0 + dv0
            quarter_disc = b * b * dv * dv - a * (c * dv * dv - gamma)
            if quarter_disc < 0.0:
                continue  # the row misses the ellipse
            du_half = math.sqrt(quarter_disc) / a
            du_mid = (-b / a) * dv
            for j in range(j0, j1):
                inside[i, j] = abs(j - j0 + du0 - du_mid) <= du_half
        else:
            for j in range(j0, j1):
                inside[i, j] = True
    if use_ellipse and i0 <= i_near < i1 and j0 <= j_near < j1:
        inside[i_near, j_near] = True

    best = -np.inf
    i_best = -1
    j_best = -1
    for i in range(i0, i1):
        for j in range(j0, j1):
            if inside[i, j] and scores[i, j] > best:
                best = float(scores[i, j])
                i_best, j_best = i, j
    if i_best < 0:
        return LOW_SCORE, -1, -1, np.nan, np.nan, 0.0, 0.0
    if not best >= min_score:
        return LOW_SCORE, i_best, j_best, best, np.nan, 0.0, 0.0
    if i_best == 0 or j_best == 0 or i_best == n_rows - 1 or j_best == n_cols - 1:
        return PEAK_AT_BORDER, i_best, j_best, best, np.nan, 0.0, 0.0
    if refuse_outside_gate:
        for di in range(-1, 2):
            for dj in range(-1, 2):
                if scores[i_best + di, j_best + dj] > best:
                    return PEAK_OUTSIDE_GATE, i_best, j_best, best, np.nan, 0.0, 0.0

    second = np.nan
    r2 = exclusion_radius_px * exclusion_radius_px
    for i in range(i0, i1):
        for j in range(j0, j1):
            if not inside[i, j] or (i - i_best) ** 2 + (j - j_best) ** 2 <= r2:
                continue
            s = scores[i, j]
            if second >= s:
                continue  # cannot raise the second peak: skip the local-maximum test
            peak = True
            for di in range(-1, 2):
                for dj in range(-1, 2):
                    ii, jj = i + di, j + dj
                    if 0 <= ii < n_rows and 0 <= jj < n_cols and scores[ii, jj] > s:
                        peak = False
            if peak:
                second = float(s)
    if second == second and best - second < ambiguity_margin:
        return AMBIGUOUS, i_best, j_best, best, second, 0.0, 0.0

    off_u, off_v = 0.0, 0.0
    if subpixel:
        off_u, off_v = subpixel_offset(scores, i_best, j_best)
    return OK, i_best, j_best, best, second, off_u, off_v


# ---------------------------------------------------------------------- a whole frame's points

# status codes of :func:`plan_searches` besides OK, LOW_SCORE and AMBIGUOUS
OUT_OF_IMAGE, SEARCH_TOO_LARGE, LOW_TEXTURE = 3, 4, 5
SEARCH = 6  # the point is to be searched (its score grid is computed between the two kernels)
TEXTURE_BORDERLINE = 7  # the template's spread is within rounding of the minimum: decided by the caller
BAD_COVARIANCE = 8  # the innovation covariance is not finite positive definite: the caller raises


@numba.njit(cache=True, nogil=True)
def plan_searches(uv_pred: np.ndarray, S: np.ndarray, half_size: int, templates: np.ndarray, params: np.ndarray):
    """The search of each of ``n`` points, before any correlation: what :meth:`PatchTracker.track`
    did per point ahead of ``cv2.matchTemplate``, with the same floating-point operations.

    ``uv_pred`` (n,2) predictions; ``S`` (n,2,2) innovation covariances, or (0,2,2) for square
    regions of ``half_size``; ``templates`` (n,t,t) float32; ``params``: chi-square gate, the
    largest half size allowed, the minimum template spread, image width and height.

    Returns ``status`` (n,) int8 (SEARCH for the points still to be searched), ``box`` (n,8)
    int64: half sizes (u, v), the nearest pixel (u, v) and the candidate centres' bounds u_lo,
    u_hi, v_lo, v_hi (inclusive), and ``ellipse`` (n,3): the inverse covariance (a, b, c) of the
    gate (1, 0, 1 for a square).
    """
    gamma, max_half, min_std = params[0], params[1], params[2]
    width, height = int(params[3]), int(params[4])
    n = uv_pred.shape[0]
    use_ellipse = S.shape[0] == n and n > 0
    ht = templates.shape[1] // 2
    n_px = templates.shape[1] * templates.shape[2]
    # a spread this close to the minimum may compare differently from cv2.meanStdDev's
    std_tol = 1e-9 * max(1.0, min_std)
    status = np.full(n, SEARCH, dtype=np.int8)
    box = np.zeros((n, 8), dtype=np.int64)
    ellipse = np.zeros((n, 3))
    for k in range(n):
        if use_ellipse:
            s_uu, s_vv = S[k, 0, 0], S[k, 1, 1]
            s_uv = 0.5 * (S[k, 0, 1] + S[k, 1, 0])
            det = s_uu * s_vv - s_uv * s_uv
            if not (0 < s_uu < math.inf and 0 < s_vv < math.inf and det > 0):
                status[k] = BAD_COVARIANCE
                continue
            half_u_f = max(1.0, math.ceil(math.sqrt(gamma * s_uu)))
            half_v_f = max(1.0, math.ceil(math.sqrt(gamma * s_vv)))
            ellipse[k, 0], ellipse[k, 1], ellipse[k, 2] = s_vv / det, -s_uv / det, s_uu / det
        else:
            half_u_f = half_v_f = float(half_size)
            ellipse[k, 0], ellipse[k, 1], ellipse[k, 2] = 1.0, 0.0, 1.0
        if half_u_f > max_half or half_v_f > max_half:
            status[k] = SEARCH_TOO_LARGE
            continue
        u_pred, v_pred = uv_pred[k, 0], uv_pred[k, 1]
        if not (math.isfinite(u_pred) and math.isfinite(v_pred)):
            status[k] = OUT_OF_IMAGE
            continue
        cu_f, cv_f = math.floor(u_pred + 0.5), math.floor(v_pred + 0.5)
        if cu_f - ht < 0 or cv_f - ht < 0 or cu_f + ht > width - 1 or cv_f + ht > height - 1:
            status[k] = OUT_OF_IMAGE
            continue
        total = 0.0
        total_sq = 0.0
        for a in range(templates.shape[1]):
            for b in range(templates.shape[2]):
                x = np.float64(templates[k, a, b])  # float() would stay float32 in numba
                total += x
                total_sq += x * x
        mean = total / n_px
        std = math.sqrt(max(total_sq / n_px - mean * mean, 0.0))
        if abs(std - min_std) <= std_tol:
            status[k] = TEXTURE_BORDERLINE
        elif std < min_std:
            status[k] = LOW_TEXTURE
            continue
        half_u, half_v, cu, cv = int(half_u_f), int(half_v_f), int(cu_f), int(cv_f)
        box[k, 0], box[k, 1], box[k, 2], box[k, 3] = half_u, half_v, cu, cv
        box[k, 4], box[k, 5] = max(cu - half_u - 1, ht), min(cu + half_u + 1, width - 1 - ht)
        box[k, 6], box[k, 7] = max(cv - half_v - 1, ht), min(cv + half_v + 1, height - 1 - ht)
    return status, box, ellipse


@numba.njit(cache=True, nogil=True)
def ncc_grid(grey: np.ndarray, row0: int, col0: int, n_rows: int, n_cols: int, template: np.ndarray, out: np.ndarray) -> None:
    """The normalised cross-correlation (OpenCV's ``TM_CCOEFF_NORMED``) of ``template`` (t,t) at
    every placement of its top-left corner at ``grey[row0 + i, col0 + j]`` (a uint8 image), ``i < n_rows``,
    ``j < n_cols``, into ``out`` (n_rows * n_cols, row-major).

    The sums are taken in float64 from the grey levels: a score is within 3e-8 of the definition,
    where OpenCV's float32 correlation was up to 2.3e-4 off it (tests/test_track_many.py). Where OpenCV's rules decide a score without dividing, they are
    kept: a flat template scores 1 everywhere; where the window's spread times the template's is
    not above the numerator (a flat window, or rounding), the score is +-1 up to 1.125 times,
    else 0.

    The numerators are :func:`~dem_graph.frontend.vector_kernel.correlate_block`'s blocks of sums held
    in vector registers (the grid padded to whole blocks; the padding's sums are not used). The
    windows' sums of grey levels and of their squares are integers, summed exactly in int64."""
    t_rows, t_cols = template.shape
    n_px = t_rows * t_cols
    h, w = n_rows + t_rows - 1, n_cols + t_cols - 1
    cols_padded = (n_cols + BLOCK_LANES - 1) // BLOCK_LANES * BLOCK_LANES
    rows_padded = (n_rows + BLOCK_ROWS - 1) // BLOCK_ROWS * BLOCK_ROWS
    stride = cols_padded + t_cols - 1
    region = np.zeros((rows_padded + t_rows - 1) * stride)
    # each column's sums over the window's rows, slid down the grid one row at a time
    col1 = np.zeros(w, dtype=np.int64)
    col2 = np.zeros(w, dtype=np.int64)
    for r in range(h):
        for c in range(w):
            g = np.int64(grey[row0 + r, col0 + c])
            region[r * stride + c] = g
            if r < t_rows:
                col1[c] += g
                col2[c] += g * g
    window1 = np.empty(n_rows * n_cols, dtype=np.int64)
    window2 = np.empty(n_rows * n_cols, dtype=np.int64)
    for i in range(n_rows):
        if i > 0:
            for c in range(w):
                g_in = np.int64(grey[row0 + i + t_rows - 1, col0 + c])
                g_out = np.int64(grey[row0 + i - 1, col0 + c])
                col1[c] += g_in - g_out
                col2[c] += g_in * g_in - g_out * g_out
        sum1 = np.int64(0)
        sum2 = np.int64(0)
        for c in range(t_cols):
            sum1 += col1[c]
            sum2 += col2[c]
        for j in range(n_cols):
            if j > 0:
                sum1 += col1[j + t_cols - 1] - col1[j - 1]
                sum2 += col2[j + t_cols - 1] - col2[j - 1]
            window1[i * n_cols + j] = sum1
            window2[i * n_cols + j] = sum2
    t_mean = 0.0
    for a in range(t_rows):
        for b in range(t_cols):
            t_mean += np.float64(template[a, b])
    t_mean /= n_px
    t_zero_mean = np.empty(t_rows * t_cols)
    t_norm2 = 0.0
    for a in range(t_rows):
        for b in range(t_cols):
            d = np.float64(template[a, b]) - t_mean
            t_zero_mean[a * t_cols + b] = d
            t_norm2 += d * d
    if t_norm2 < 2.220446049250313e-16:  # OpenCV: a flat template matches everywhere
        out[: n_rows * n_cols] = 1.0
        return
    t_norm = math.sqrt(t_norm2)
    num = np.empty(rows_padded * cols_padded)
    for i in range(0, rows_padded, BLOCK_ROWS):
        for j in range(0, cols_padded, BLOCK_LANES):
            correlate_block(region, stride, t_zero_mean, t_rows, t_cols, i, j, num[i * cols_padded + j :], cols_padded)
    for i in range(n_rows):
        for j in range(n_cols):
            w1 = np.float64(window1[i * n_cols + j])
            w2 = np.float64(window2[i * n_cols + j])
            denom = math.sqrt(max(w2 - w1 * w1 / n_px, 0.0)) * t_norm
            v = num[i * cols_padded + j]
            # (selects rather than branches, so that the loop compiles to vector code)
            sign = 1.0 if v > 0 else -1.0
            out[i * n_cols + j] = v / denom if abs(v) < denom else (sign if abs(v) < denom * 1.125 else 0.0)


@numba.njit(cache=True, nogil=True)
def ncc_grids(grey: np.ndarray, u0: int, v0: int, templates: np.ndarray, status: np.ndarray, box: np.ndarray):
    """:func:`ncc_grid` of every point whose ``status`` is SEARCH over its candidate centres
    (``box`` of :func:`plan_searches`), ``grey`` holding the image from column ``u0``, row ``v0``.
    Returns the scores (float32, the grids one after the other, as :func:`select_matches` takes
    them) and each point's offset into them."""
    n = status.shape[0]
    ht = templates.shape[1] // 2
    offsets = np.zeros(n, dtype=np.int64)
    size = 0
    for k in range(n):
        if status[k] == SEARCH:
            offsets[k] = size
            size += (box[k, 7] - box[k, 6] + 1) * (box[k, 5] - box[k, 4] + 1)
    scores64 = np.empty(size)
    for k in range(n):
        if status[k] != SEARCH:
            continue
        n_rows, n_cols = box[k, 7] - box[k, 6] + 1, box[k, 5] - box[k, 4] + 1
        ncc_grid(grey, box[k, 6] - ht - v0, box[k, 4] - ht - u0, n_rows, n_cols, templates[k], scores64[offsets[k] : offsets[k] + n_rows * n_cols])
    return scores64.astype(np.float32), offsets


@numba.njit(cache=True, nogil=True)
def select_matches(
    status: np.ndarray, box: np.ndarray, ellipse: np.ndarray, uv_pred: np.ndarray, scores: np.ndarray, offsets: np.ndarray, gamma: float, params: np.ndarray
):
    """:func:`select_match` for every point whose status is SEARCH; its score grid (rows ``v_lo..v_hi``,
    columns ``u_lo..u_hi`` of ``box``) is ``scores[offsets[k]:]``, row-major. ``params``: use the
    ellipse (1.0) or the square, min score, exclusion radius, ambiguity margin, sub-pixel (1.0),
    refuse a peak outside the gate (1.0).

    Returns the final ``status`` (n,) int8, the matches ``uv`` (n,2) (NaN unless OK), ``score`` and
    ``second`` (n,) (NaN when not computed)."""
    n = status.shape[0]
    use_ellipse = params[0] != 0.0
    min_score, exclusion, margin, subpixel, refuse_outside = params[1], params[2], params[3], params[4] != 0.0, params[5] != 0.0
    out_status = status.copy()
    uv = np.full((n, 2), np.nan)
    score = np.full(n, np.nan)
    second = np.full(n, np.nan)
    for k in range(n):
        if status[k] != SEARCH:
            continue
        half_u, half_v, cu, cv = box[k, 0], box[k, 1], box[k, 2], box[k, 3]
        u_lo, u_hi, v_lo, v_hi = box[k, 4], box[k, 5], box[k, 6], box[k, 7]
        n_rows, n_cols = v_hi - v_lo + 1, u_hi - u_lo + 1
        grid = scores[offsets[k] : offsets[k] + n_rows * n_cols].reshape((n_rows, n_cols))
        # the region inside the computed grid: rows i0:i1, columns j0:j1
        i0, i1 = max(cv - half_v, v_lo) - v_lo, min(cv + half_v, v_hi) - v_lo + 1
        j0, j1 = max(cu - half_u, u_lo) - u_lo, min(cu + half_u, u_hi) - u_lo + 1
        s, i_best, j_best, best, sec, off_u, off_v = select_match(
            grid, i0, i1, j0, j1, use_ellipse, ellipse[k, 0], ellipse[k, 1], ellipse[k, 2], gamma,
            v_lo + i0 - uv_pred[k, 1], u_lo + j0 - uv_pred[k, 0], cv - v_lo, cu - u_lo, min_score, exclusion, margin, subpixel, refuse_outside,
        )  # fmt: skip
        out_status[k] = s
        score[k] = best
        second[k] = sec  # NaN unless OK or AMBIGUOUS
        if s == OK:
            uv[k, 0] = u_lo + j_best + off_u
            uv[k, 1] = v_lo + i_best + off_v
    return out_status, uv, score, second
