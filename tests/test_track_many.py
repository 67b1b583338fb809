"""The batched tracker (PatchTracker.track_many, FrontEnd.track_many) against the per-point
reference it replaced: the same status, match, scores and region for every point, to the bit.

``_reference_track`` is the per-point ``PatchTracker.track`` as it was before the batched path
(commit 96577d7), kept here as the oracle: every number it computes in Python the batched path
computes in a compiled pass, so the two must agree exactly, on synthetic images with known
shifts and warps and on a whole recorded run of each estimator. Its score grid is the compiled
correlation's (``ncc_grid``, which replaced ``cv2.matchTemplate``); that correlation is checked on
its own against OpenCV and against its definition in float64 (sums over sliding windows), and the
tracker against the reference with that definition.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from dem_graph.datasets.events import CameraFrame
from dem_graph.frontend.match_kernel import AMBIGUOUS, LOW_SCORE, PEAK_AT_BORDER, PEAK_OUTSIDE_GATE, ncc_grid, select_match
from dem_graph.frontend.tracker import PatchTracker, TrackBatch, TrackResult, TrackStatus
from dem_graph.pipeline import RunConfig, run_estimator

WIDTH_PX, HEIGHT_PX = 320, 240
TRACKER = PatchTracker()


def _ncc_compiled(roi: np.ndarray, tpl: np.ndarray) -> np.ndarray:
    """The tracker's correlation of one region: ``ncc_grid``'s float64 scores as float32."""
    n_rows, n_cols = roi.shape[0] - tpl.shape[0] + 1, roi.shape[1] - tpl.shape[1] + 1
    out = np.empty(n_rows * n_cols)
    ncc_grid(roi, 0, 0, n_rows, n_cols, tpl, out)
    return out.astype(np.float32).reshape(n_rows, n_cols)


def _ncc_opencv(roi: np.ndarray, tpl: np.ndarray) -> np.ndarray:
    return cv2.matchTemplate(roi.astype(np.float32), tpl, cv2.TM_CCOEFF_NORMED)


def _reference_track(tracker: PatchTracker, image, template, uv_pred_px, S_px2=None, half_size_px=None, correlate=_ncc_compiled) -> TrackResult:
    """The per-point search as it was implemented before ``track_many`` (see the module doc), the
    score grid from ``correlate`` (region, template)."""
    img = image
    tpl = np.asarray(template, dtype=np.float32)
    uv = np.asarray(uv_pred_px, dtype=float)
    cfg = tracker.config
    S_inv = None
    gamma = math.inf
    if S_px2 is not None:
        (s_uu, s_uv_upper), (s_uv_lower, s_vv) = np.asarray(S_px2, dtype=float).tolist()
        s_uv = 0.5 * (s_uv_upper + s_uv_lower)
        det = s_uu * s_vv - s_uv * s_uv
        gamma = tracker.gate_chi2
        half_u = max(1, math.ceil(math.sqrt(gamma * s_uu)))
        half_v = max(1, math.ceil(math.sqrt(gamma * s_vv)))
        S_inv = (s_vv / det, -s_uv / det, s_uu / det)
    else:
        half_u = half_v = int(half_size_px)
    if half_u > cfg.max_search_half_size_px or half_v > cfg.max_search_half_size_px:
        return TrackResult(TrackStatus.SEARCH_TOO_LARGE, None, math.nan, math.nan, (0, 0))
    ht = tpl.shape[0] // 2
    height, width = img.shape[:2]
    u_pred, v_pred = float(uv[0]), float(uv[1])
    if not (math.isfinite(u_pred) and math.isfinite(v_pred)):
        return TrackResult(TrackStatus.OUT_OF_IMAGE, None, math.nan, math.nan, (0, 0))
    cu, cv = math.floor(u_pred + 0.5), math.floor(v_pred + 0.5)
    if cu - ht < 0 or cv - ht < 0 or cu + ht > width - 1 or cv + ht > height - 1:
        return TrackResult(TrackStatus.OUT_OF_IMAGE, None, math.nan, math.nan, (0, 0))
    _, tpl_std = cv2.meanStdDev(tpl)
    if float(tpl_std[0, 0]) < cfg.min_patch_std_dn:
        return TrackResult(TrackStatus.LOW_TEXTURE, None, math.nan, math.nan, (0, 0))
    u_lo, u_hi = max(cu - half_u - 1, ht), min(cu + half_u + 1, width - 1 - ht)
    v_lo, v_hi = max(cv - half_v - 1, ht), min(cv + half_v + 1, height - 1 - ht)
    window = img[v_lo - ht : v_hi + ht + 1, u_lo - ht : u_hi + ht + 1]
    roi = cv2.cvtColor(window, cv2.COLOR_BGR2GRAY) if window.ndim == 3 else window
    scores = correlate(roi, tpl)
    i0, i1 = max(cv - half_v, v_lo) - v_lo, min(cv + half_v, v_hi) - v_lo + 1
    j0, j1 = max(cu - half_u, u_lo) - u_lo, min(cu + half_u, u_hi) - u_lo + 1
    a, b, c = S_inv if S_inv is not None else (1.0, 0.0, 1.0)
    status, i_best, j_best, best, second, off_u, off_v = select_match(
        scores, i0, i1, j0, j1, S_inv is not None, a, b, c, gamma, v_lo + i0 - v_pred, u_lo + j0 - u_pred, cv - v_lo, cu - u_lo,
        cfg.min_score, cfg.exclusion_radius_px, cfg.ambiguity_margin, cfg.subpixel, cfg.refuse_peak_outside_gate,
    )  # fmt: skip
    searched = (half_u, half_v)
    if status == LOW_SCORE:
        return TrackResult(TrackStatus.LOW_SCORE, None, best, math.nan, searched)
    if status == AMBIGUOUS:
        return TrackResult(TrackStatus.AMBIGUOUS, None, best, second, searched)
    if status == PEAK_AT_BORDER:  # added with the peak tests in select_match
        return TrackResult(TrackStatus.PEAK_AT_BORDER, None, best, math.nan, searched)
    if status == PEAK_OUTSIDE_GATE:
        return TrackResult(TrackStatus.PEAK_OUTSIDE_GATE, None, best, math.nan, searched)
    return TrackResult(TrackStatus.OK, np.array([u_lo + j_best + off_u, v_lo + i_best + off_v]), best, second, searched)


def _reference_track_many(tracker, image, templates, uv_pred_px, S_px2=None, half_size_px=None, track=_reference_track) -> TrackBatch:
    """``track_many`` as a loop over the reference (or another one-point ``track``), its results as a :class:`TrackBatch`."""
    code = {TrackStatus.OK: 0, TrackStatus.LOW_SCORE: 1, TrackStatus.AMBIGUOUS: 2, TrackStatus.OUT_OF_IMAGE: 3, TrackStatus.SEARCH_TOO_LARGE: 4, TrackStatus.LOW_TEXTURE: 5, TrackStatus.PEAK_AT_BORDER: 9, TrackStatus.PEAK_OUTSIDE_GATE: 10}
    res = [
        track(tracker, image, templates[k], uv_pred_px[k], None if S_px2 is None else S_px2[k], half_size_px)
        for k in range(len(templates))
    ]
    return TrackBatch(
        np.array([code[r.status] for r in res], dtype=np.int8).reshape(-1),
        np.array([r.uv_px if r.ok else (np.nan, np.nan) for r in res], dtype=float).reshape(-1, 2),
        np.array([r.score for r in res], dtype=float),
        np.array([r.second_score for r in res], dtype=float),
        np.array([r.search_half_size_px for r in res], dtype=np.int64).reshape(-1, 2),
    )


def _assert_same(new: TrackBatch, ref: TrackBatch) -> None:
    np.testing.assert_array_equal(new.status, ref.status)
    np.testing.assert_array_equal(new.uv_px, ref.uv_px)  # NaN where not OK in both
    np.testing.assert_array_equal(new.score, ref.score)
    np.testing.assert_array_equal(new.second_score, ref.second_score)
    np.testing.assert_array_equal(new.search_half_size_px, ref.search_half_size_px)


def _texture(seed: int, blur_px: float = 2.0) -> np.ndarray:
    noise = np.random.default_rng(seed).uniform(0.0, 255.0, (HEIGHT_PX, WIDTH_PX)).astype(np.float32)
    grey = cv2.GaussianBlur(noise, (0, 0), blur_px)
    return np.clip(np.rint((grey - grey.mean()) / grey.std() * 30.0 + 128.0), 0, 255).astype(np.uint8)


def _scene(seed: int, n: int = 400):
    """Image A, image B (A moved by a known sub-pixel shift, plus noise and a flat band), the
    patches' points in A, their truth in B, predictions with errors, covariances of every size
    (some too large, some not positive definite left out), and a few predictions at or over the
    border or not finite."""
    rng = np.random.default_rng(seed)
    A = _texture(seed)
    A[100:130, :] = 90  # flat: low-score searches nearby
    A[150:200, :160] = np.rint(128 + 60 * np.sin(2 * np.pi * np.arange(160) / 8.0)).astype(np.uint8)  # stripes: ambiguous
    shift = rng.uniform(-4.0, 4.0, 2)
    M = np.float32([[1, 0, shift[0]], [0, 1, shift[1]]])
    B = cv2.warpAffine(A, M, (WIDTH_PX, HEIGHT_PX), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    B = np.clip(np.rint(B + rng.normal(0.0, 2.0, B.shape)), 0, 255).astype(np.uint8)
    p = rng.uniform([16.0, 16.0], [WIDTH_PX - 16.0, HEIGHT_PX - 16.0], (n, 2))
    q = p + shift
    pred = q + rng.normal(0.0, 1.5, (n, 2))
    pred[:12] = [[3.0, 50.0], [WIDTH_PX - 4.0, 60.0], [50.0, HEIGHT_PX - 7.6], [7.4, 7.6], [np.nan, 9.0], [np.inf, 5.0],
                 [-30.0, 10.0], [1e300, 4.0], [50.0, 1e20], [8.49, 100.0], [WIDTH_PX - 8.51, 30.0], [160.0, 7.5]]  # fmt: skip
    L = rng.normal(0.0, 1.0, (n, 2, 2)) * rng.choice([0.3, 1.0, 3.0, 8.0, 20.0], n)[:, None, None]
    S = L @ np.swapaxes(L, 1, 2) + 0.09 * np.eye(2)
    S[12, 0, 1] += 1e-3  # not symmetric: the mean of both off-diagonal terms is used
    return A, B, p, q, pred, S


def _border_scene(seed: int, n: int = 60):
    """Image A, image B (A moved 9.6 px right and down), points whose truth in B lies near or past
    the last row and column where a template fits, and predictions where it still fits."""
    rng = np.random.default_rng(seed)
    A = _texture(seed + 10)
    shift = np.array([9.6, 9.6])
    B = cv2.warpAffine(A, np.float32([[1, 0, shift[0]], [0, 1, shift[1]]]), (WIDTH_PX, HEIGHT_PX), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    bottom = np.column_stack([rng.uniform(40.0, WIDTH_PX - 60.0, n // 2), rng.uniform(218.0, 224.0, n // 2)])
    right = np.column_stack([rng.uniform(298.0, 304.0, n - n // 2), rng.uniform(40.0, 180.0, n - n // 2)])
    p = np.vstack([bottom, right])
    pred = np.minimum(p + shift + rng.normal(0.0, 0.3, p.shape), [WIDTH_PX - 8.0, HEIGHT_PX - 8.0])
    return A, B, p, pred


def _templates(tracker, A, points, warp_seed=None):
    """Templates of the patches around ``points`` in A: unwarped, or through random small similarities."""
    patches = [tracker.make_patch(A, x, 0.0) for x in points]
    keep = np.array([pt is not None for pt in patches])
    patches = [pt for pt in patches if pt is not None]
    if warp_seed is None:
        return keep, np.array([tracker.template(pt) for pt in patches])
    rng = np.random.default_rng(warp_seed)
    out = []
    for pt in patches:
        a, z = math.radians(rng.uniform(-10, 10)), rng.uniform(0.9, 1.1)
        H = np.eye(3)
        H[:2, :2] = z * np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
        H[:2, 2] = pt.center_px - H[:2, :2] @ pt.center_px
        H[2, :2] = rng.normal(0.0, 1e-4, 2)
        out.append(tracker.template(pt, H))
    return keep, np.array(out)


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("warped", [False, True])
def test_track_many_equals_the_per_point_reference(seed, warped):
    A, B, p, q, pred, S = _scene(seed)
    keep, tpl = _templates(TRACKER, A, p, warp_seed=seed if warped else None)
    pred, S = pred[keep], S[keep]
    rng = np.random.default_rng(seed)
    tpl[20:23] = 100 + rng.normal(0.0, [[[1.0]], [[2.9]], [[0.0]]], (3, 15, 15))  # too flat
    strict = PatchTracker(TRACKER.config.model_copy(update=dict(refuse_peak_outside_gate=True)))
    for config in (TRACKER, PatchTracker(TRACKER.config.model_copy(update=dict(subpixel=False, min_patch_std_dn=0.0))), strict):
        new = config.track_many(B, tpl, pred, S_px2=S)
        _assert_same(new, _reference_track_many(config, B, tpl, pred, S_px2=S))
        # the one-point `track` (PTPM's) gives the same
        _assert_same(new, _reference_track_many(config, B, tpl, pred, S_px2=S, track=PatchTracker.track))
        _assert_same(config.track_many(B, tpl, pred, half_size_px=20), _reference_track_many(config, B, tpl, pred, half_size_px=20, track=PatchTracker.track))
        for half in (0, 3, 20, 41):
            _assert_same(config.track_many(B, tpl, pred, half_size_px=half), _reference_track_many(config, B, tpl, pred, half_size_px=half))
    # points leaving the image: some refused at the border
    A_b, B_b, p_b, pred_b = _border_scene(seed)
    keep_b, tpl_b = _templates(TRACKER, A_b, p_b)
    pred_b = pred_b[keep_b]
    for config in (TRACKER, PatchTracker(TRACKER.config.model_copy(update=dict(subpixel=False)))):
        for track in (_reference_track, PatchTracker.track):
            _assert_same(config.track_many(B_b, tpl_b, pred_b, half_size_px=4), _reference_track_many(config, B_b, tpl_b, pred_b, half_size_px=4, track=track))
    # every outcome occurs
    statuses = set(TRACKER.track_many(B, tpl, pred, S_px2=S).statuses()) | set(TRACKER.track_many(B, tpl, pred, half_size_px=41).statuses())
    statuses |= set(strict.track_many(B, tpl, pred, S_px2=S).statuses())
    statuses |= set(TRACKER.track_many(B_b, tpl_b, pred_b, half_size_px=4).statuses())
    assert statuses == set(TrackStatus)
    # a template whose spread is the minimum, to rounding: decided as cv2.meanStdDev decides it
    for k in (30, 31):
        std = float(cv2.meanStdDev(tpl[k])[1][0, 0])
        for min_std in (std, np.nextafter(std, 0.0), np.nextafter(std, np.inf)):
            t = PatchTracker(TRACKER.config.model_copy(update=dict(min_patch_std_dn=min_std)))
            _assert_same(t.track_many(B, tpl[k : k + 1], pred[k : k + 1], half_size_px=3), _reference_track_many(t, B, tpl[k : k + 1], pred[k : k + 1], half_size_px=3))
    # BGR images: the same as their grey
    bgr = cv2.cvtColor(B, cv2.COLOR_GRAY2BGR)
    _assert_same(TRACKER.track_many(bgr, tpl, pred, S_px2=S), _reference_track_many(TRACKER, bgr, tpl, pred, S_px2=S))


def _ncc_float64(roi: np.ndarray, tpl: np.ndarray) -> np.ndarray:
    """TM_CCOEFF_NORMED from its definition: zero-mean window and template, float64 sums over sliding windows."""
    windows = np.lib.stride_tricks.sliding_window_view(roi.astype(float), tpl.shape)
    w = windows - windows.mean(axis=(2, 3), keepdims=True)
    t = tpl.astype(float) - tpl.mean(dtype=float)
    return (w * t).sum(axis=(2, 3)) / np.sqrt((w**2).sum(axis=(2, 3)) * (t**2).sum())


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_compiled_correlation_is_opencvs_and_the_definitions(seed):
    """``ncc_grid`` against its definition in float64 (to 1e-6: its scores are rounded to float32)
    and against ``cv2.matchTemplate`` (to 5e-4: OpenCV correlates in float32, which put its scores
    up to 2.3e-4 off the definition with the warped templates of the scenes below), on blurred-noise regions of the sizes the tracker
    searches, textured templates and flat ones; and where OpenCV decides without dividing (a flat
    window: 0; a flat template: 1), the same."""
    rng = np.random.default_rng(seed)
    A = _texture(seed)
    for rows, cols, t in [(25, 21, 15), (17, 17, 15), (15, 15, 15), (61, 47, 15), (13, 19, 9)]:
        for _ in range(10):
            r0, c0 = rng.integers(0, HEIGHT_PX - rows), rng.integers(0, WIDTH_PX - cols)
            roi = A[r0 : r0 + rows, c0 : c0 + cols]
            tr, tc = rng.integers(0, HEIGHT_PX - t), rng.integers(0, WIDTH_PX - t)
            tpl = (A[tr : tr + t, tc : tc + t] + rng.normal(0.0, 3.0, (t, t))).astype(np.float32)
            got = _ncc_compiled(roi, tpl)
            np.testing.assert_allclose(got, _ncc_float64(roi, tpl).astype(np.float32), rtol=0, atol=1e-6)
            np.testing.assert_allclose(got, _ncc_opencv(roi, tpl), rtol=0, atol=5e-4)
    flat_roi = np.full((25, 21), 90, dtype=np.uint8)
    flat_roi[:, 15:] = A[:25, :6]  # flat windows on the left, textured on the right
    tpl = A[40:55, 40:55].astype(np.float32)
    np.testing.assert_allclose(_ncc_compiled(flat_roi, tpl), _ncc_opencv(flat_roi, tpl), rtol=0, atol=5e-4)
    assert np.all(_ncc_compiled(flat_roi, tpl)[:, 0] == 0.0)
    np.testing.assert_array_equal(_ncc_compiled(A[:25, :21], np.full((15, 15), 7.0, dtype=np.float32)), _ncc_opencv(A[:25, :21], np.full((15, 15), 7.0, dtype=np.float32)))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_tracker_with_the_correlations_definition(seed):
    """The tracker against the reference with the correlation from its definition in float64
    (``_ncc_float64``), on the scenes above (400 points each, warped templates): the same outcome
    for every point, the scores within their float32 rounding (1e-6) and the matches within
    1e-4 px (the sub-pixel fit divides score differences by the peak's curvature)."""
    A, B, p, q, pred, S = _scene(seed)
    keep, tpl = _templates(TRACKER, A, p, warp_seed=seed)
    pred, S = pred[keep], S[keep]
    new = TRACKER.track_many(B, tpl, pred, S_px2=S)

    def with_definition(tracker, image, template, uv, S_px2=None, half_size_px=None):
        return _reference_track(tracker, image, template, uv, S_px2, half_size_px, correlate=lambda r, t: _ncc_float64(r, t).astype(np.float32))

    ref = _reference_track_many(TRACKER, B, tpl, pred, S_px2=S, track=with_definition)
    np.testing.assert_array_equal(new.status, ref.status)
    np.testing.assert_allclose(new.uv_px, ref.uv_px, rtol=0, atol=1e-4)
    np.testing.assert_allclose(new.score, ref.score, rtol=0, atol=1e-6)
    assert new.ok.sum() > 100


def test_track_many_recovers_known_subpixel_shifts():
    """Points tracked from A into A shifted by a known sub-pixel translation: within the 0.15 px of
    test_tracker, and each point's result is what the single-point `track` gives it."""
    A = _texture(5)
    shift = np.array([2.3, -1.6])
    B = cv2.warpAffine(A, np.float32([[1, 0, shift[0]], [0, 1, shift[1]]]), (WIDTH_PX, HEIGHT_PX), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    p = np.random.default_rng(5).uniform([40.0, 40.0], [WIDTH_PX - 40.0, HEIGHT_PX - 40.0], (60, 2))
    keep, tpl = _templates(TRACKER, A, p)
    q = p[keep] + shift
    pred = q + [1.2, -0.8]
    S = np.repeat((4.0 * np.eye(2))[None], len(q), axis=0)
    batch = TRACKER.track_many(B, tpl, pred, S_px2=S)
    assert batch.ok.all() and np.abs(batch.uv_px - q).max() < 0.15
    for k in range(len(q)):
        single = TRACKER.track(B, tpl[k], pred[k], S_px2=S[k])
        assert single.status is TrackStatus.OK and np.array_equal(single.uv_px, batch.uv_px[k])
        assert single.score == batch.score[k] and single.search_half_size_px == tuple(batch.search_half_size_px[k])


def test_track_many_argument_checks_and_empty_batch():
    A = _texture(0)
    tpl = np.zeros((2, 15, 15), dtype=np.float32)
    with pytest.raises(ValueError, match="exactly one"):
        TRACKER.track_many(A, tpl, np.zeros((2, 2)))
    with pytest.raises(ValueError, match="positive definite"):
        TRACKER.track_many(A, tpl, np.full((2, 2), 50.0), S_px2=np.array([np.eye(2), -np.eye(2)]))
    with pytest.raises(ValueError, match="shape"):
        TRACKER.track_many(A, tpl, np.zeros((3, 2)), half_size_px=3)
    with pytest.raises(ValueError, match=">= 0"):
        TRACKER.track_many(A, tpl, np.zeros((2, 2)), half_size_px=-1)
    empty = TRACKER.track_many(A, np.zeros((0, 15, 15), dtype=np.float32), np.zeros((0, 2)), S_px2=np.zeros((0, 2, 2)))
    assert len(empty) == 0 and empty.uv_px.shape == (0, 2) and empty.search_half_size_px.shape == (0, 2)


@pytest.mark.parametrize("estimator", ["ptpm", "gm", "isam2"])
def test_recorded_run_is_the_same_with_the_reference_tracker(smoke_log, smoke_run, estimator, monkeypatch):
    """A whole run of `smoke`: every frame's pose and the front end's counters are identical with
    the tracker (batched for GM and isam2, one point at a time for PTPM) and with the per-point
    reference in its place. The run with the tracker is the session's run of `smoke` with the
    defaults (``run_estimator(smoke_log, RunConfig(estimator=estimator))``, made once: other files
    check it too); the one with the reference is made here."""

    def frames(result):
        assert result.error is None
        est = result.estimator
        return np.array([f.T_world_body for f in est.frames]), [f.n_tracked for f in est.frames], dict(est.counters)

    T_new, n_new, counters_new = frames(smoke_run({"estimator": estimator}))
    monkeypatch.setattr(PatchTracker, "track_many", _reference_track_many)
    monkeypatch.setattr(PatchTracker, "track", _reference_track)
    T_ref, n_ref, counters_ref = frames(run_estimator(smoke_log, RunConfig(estimator=estimator)))
    assert len(T_new) == sum(isinstance(e, CameraFrame) for e in smoke_log.events())
    assert n_new == n_ref and counters_new == counters_ref
    np.testing.assert_array_equal(T_new, T_ref)


def test_the_front_ends_batch_bookkeeping_is_the_point_by_point_one(smoke_log):
    """``FrontEnd.track_many`` over five frames against ``FrontEnd.track`` one point at a time on a
    twin front end (patches refreshed every 2nd match, a third of the points predicted where they
    are lost or cannot be placed): the same counters (their order too), misses, matches counted,
    patches and their sources, and the same patch store."""
    from dem_graph.frontend.frontend import FrontEnd, FrontendConfig, PointKind

    config = FrontendConfig(refresh_patch_every=2)
    batch_fe, point_fe = FrontEnd(config, smoke_log.rig), FrontEnd(config, smoke_log.rig)
    A = _texture(4)
    rng = np.random.default_rng(4)
    uv0 = rng.uniform(25, [WIDTH_PX - 25, HEIGHT_PX - 25], (30, 2))
    for fe in (batch_fe, point_fe):
        ids = np.array([fe._register(PointKind.CAMERA if k % 2 else PointKind.LASER, A, uv, 0.0, np.eye(4)) for k, uv in enumerate(uv0)])
    shift = np.array([1.0, 2.0])
    for frame in range(1, 6):
        image = np.roll(A, (2 * frame, frame), axis=(0, 1))
        pred = uv0 + frame * shift + 0.3
        pred[::3] = np.where(frame % 2, [-50.0, 10.0], [60.0, 200.0])  # out of the image, or in the wrong place
        T_world_cam = np.eye(4)
        T_world_cam[0, 3] = 0.1 * frame
        tpl = batch_fe.templates(ids, None)
        np.testing.assert_array_equal(tpl, point_fe.templates(ids, None))
        batch = batch_fe.track_many(image, ids, tpl, pred, half_size_px=4, t_s=0.04 * frame, T_world_cam=T_world_cam)
        singles = [point_fe.track(image, int(p), tpl[k], pred[k], half_size_px=4, t_s=0.04 * frame, T_world_cam=T_world_cam) for k, p in enumerate(ids)]
        assert [s.status for s in singles] == batch.statuses()
        assert list(batch_fe.counters.items()) == list(point_fe.counters.items())
    assert batch_fe.counters["patch_refreshed"] > 0 and batch_fe.counters["track_ok"] > 0 and batch_fe.counters["track_out_of_image"] > 0
    for p in ids.tolist():
        a, b = batch_fe.tracks[p], point_fe.tracks[p]
        assert (a.misses, a.n_tracked, a.segment) == (b.misses, b.n_tracked, b.segment)
        np.testing.assert_array_equal(a.patch.region, b.patch.region)
        np.testing.assert_array_equal(a.T_world_cam_source, b.T_world_cam_source)
    slots = batch_fe.patches.slots(ids)
    np.testing.assert_array_equal(batch_fe.patches.regions[slots], np.stack([batch_fe.tracks[p].patch.region_f32 for p in ids.tolist()]))
    np.testing.assert_array_equal(batch_fe.patches.T_world_cam_source[slots], np.stack([batch_fe.tracks[p].T_world_cam_source for p in ids.tolist()]))
