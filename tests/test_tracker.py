"""Truth-checked tests of dem_graph.frontend.tracker: patches, warped templates, active search.

The images are synthetic: smoothed uniform noise (std 30 grey levels, 320x240), moved by a known
sub-pixel translation or homography, so the true position of every point is known exactly.
"""

from __future__ import annotations

import math
from functools import cache

import cv2
import numpy as np
import pytest
from pydantic import ValidationError

from dem_graph.frontend.tracker import Patch, PatchTracker, TrackerConfig, TrackResult, TrackStatus

WIDTH_PX, HEIGHT_PX = 320, 240
SHIFT_PX = np.array([3.3, -2.6])  # the translation from image A to image B
PRED_ERROR_PX = np.array([1.2, -0.8])  # how far the prediction misses the truth in most tests
TRACKER = PatchTracker()


def _normalise(grey: np.ndarray, std_dn: float = 30.0) -> np.ndarray:
    out = (grey - grey.mean()) / grey.std() * std_dn + 128.0
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)


@cache
def _texture(seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    noise = rng.uniform(0.0, 255.0, (HEIGHT_PX, WIDTH_PX)).astype(np.float32)
    return _normalise(cv2.GaussianBlur(noise, (0, 0), 2.0))


def _translate(image: np.ndarray, shift_px: np.ndarray) -> np.ndarray:
    """B(x) = A(x - shift): a point at p in A is at p + shift in B (bilinear)."""
    M = np.float32([[1, 0, shift_px[0]], [0, 1, shift_px[1]]])
    return cv2.warpAffine(image, M, (image.shape[1], image.shape[0]), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)


def _add_noise(image: np.ndarray, sigma_dn: float, rng: np.random.Generator) -> np.ndarray:
    return np.clip(np.rint(image + rng.normal(0.0, sigma_dn, image.shape)), 0, 255).astype(np.uint8)


def _points(n: int, seed: int) -> np.ndarray:
    """Sub-pixel points away from the border."""
    return np.random.default_rng(seed).uniform([40.0, 40.0], [WIDTH_PX - 40.0, HEIGHT_PX - 40.0], (n, 2))


def _similarity_about(p_px: np.ndarray, q_px: np.ndarray, zoom: float, angle_deg: float) -> np.ndarray:
    """Homography taking p to q, zooming by `zoom` and rotating by `angle_deg` about it."""
    a = math.radians(angle_deg)
    R = zoom * np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
    H = np.eye(3)
    H[:2, :2] = R
    H[:2, 2] = q_px - R @ p_px
    return H


def _track_shifted(tracker, A, B, p_px, pred_px, **search) -> TrackResult:
    patch = tracker.make_patch(A, p_px, 0.0)
    assert patch is not None
    return tracker.track(B, tracker.template(patch), pred_px, **search)


# ---------------------------------------------------------------------- configuration and patches


def test_config_defaults_and_strictness():
    cfg = TrackerConfig()
    assert (cfg.patch_half_size_px, cfg.warp_margin_px, cfg.max_search_half_size_px) == (7, 8, 40)
    assert (cfg.min_score, cfg.ambiguity_margin, cfg.exclusion_radius_px, cfg.gate_probability) == (0.7, 0.08, 3, 0.99)
    assert cfg.min_patch_std_dn == 3.0 and cfg.subpixel is True
    for name, field in TrackerConfig.model_fields.items():
        assert field.description, name
    with pytest.raises(ValidationError):
        TrackerConfig(patch_size=7)
    with pytest.raises(ValidationError):
        TrackerConfig(gate_probability=1.0)


def test_gate_matches_chi_square_quantile_and_sets_the_box():
    from scipy.stats import chi2

    assert TRACKER.gate_chi2 == pytest.approx(chi2.ppf(0.99, 2), rel=1e-12)
    A = _texture()
    p = np.array([160.0, 120.0])
    r = _track_shifted(TRACKER, A, A, p, p, S_px2=np.diag([4.0, 9.0]))
    gamma = chi2.ppf(0.99, 2)
    assert r.search_half_size_px == (math.ceil(math.sqrt(gamma * 4.0)), math.ceil(math.sqrt(gamma * 9.0))) == (7, 10)
    # the patch is found where it was taken (score 1); the quadratic fit of the scores around the
    # peak is not exactly symmetric on a small window, hence not exactly 0
    assert r.ok and r.score == pytest.approx(1.0, abs=1e-5) and np.abs(r.uv_px - p).max() < 0.15
    # a tiny covariance still searches at least one pixel either side
    r = _track_shifted(TRACKER, A, A, p, p, S_px2=np.diag([1e-4, 1e-4]))
    assert r.search_half_size_px == (1, 1) and r.ok


def test_make_patch_geometry():
    A = _texture()
    p = np.array([100.37, 80.81])
    patch = TRACKER.make_patch(A, p, 2.5)
    assert isinstance(patch, Patch)
    assert patch.region.dtype == np.uint8 and patch.region.shape == (31, 31)  # 2 * (7 + 8) + 1
    assert patch.t_s == 2.5 and np.array_equal(patch.center_px, p)
    # the centre pixel is the bilinear sample at p, the corner the one at p - 15
    expected = cv2.getRectSubPix(A, (1, 1), (p[0], p[1]))[0, 0]
    assert abs(int(patch.region[15, 15]) - int(expected)) <= 1
    expected = cv2.getRectSubPix(A, (1, 1), (p[0] - 15, p[1] - 15))[0, 0]
    assert abs(int(patch.region[0, 0]) - int(expected)) <= 1
    # integer point: the region is an exact crop
    patch = TRACKER.make_patch(A, (100.0, 80.0), 0.0)
    assert np.array_equal(patch.region, A[65:96, 85:116])
    tpl = TRACKER.template(patch)
    assert tpl.dtype == np.float32 and np.array_equal(tpl, A[73:88, 93:108].astype(np.float32))


def test_make_patch_rejects_border_flat_and_accepts_bgr():
    A = _texture()
    assert TRACKER.make_patch(A, (14.9, 120.0), 0.0) is None  # needs 15 px either side
    assert TRACKER.make_patch(A, (15.0, 120.0), 0.0) is not None
    assert TRACKER.make_patch(A, (WIDTH_PX - 15.5, 120.0), 0.0) is None
    assert TRACKER.make_patch(A, (np.nan, 120.0), 0.0) is None
    flat = np.full((HEIGHT_PX, WIDTH_PX), 100, np.uint8)
    flat = _add_noise(flat, 1.0, np.random.default_rng(3))  # std about 1 DN < 3 DN
    assert TRACKER.make_patch(flat, (160.0, 120.0), 0.0) is None  # LOW_TEXTURE
    bgr = cv2.cvtColor(A, cv2.COLOR_GRAY2BGR)
    p = (123.4, 101.7)
    assert np.abs(TRACKER.make_patch(bgr, p, 0.0).region.astype(int) - TRACKER.make_patch(A, p, 0.0).region).max() <= 1
    with pytest.raises(ValueError):
        TRACKER.make_patch(A.astype(np.float32), p, 0.0)


# ---------------------------------------------------------------------- translation


@pytest.mark.parametrize("search", [dict(S_px2=4.0 * np.eye(2)), dict(half_size_px=6)], ids=["ellipse", "square"])
def test_subpixel_translation_is_recovered(search):
    A = _texture()
    B = _translate(A, SHIFT_PX)
    for p in _points(10, seed=1):
        r = _track_shifted(TRACKER, A, B, p, p + SHIFT_PX + PRED_ERROR_PX, **search)
        assert r.status is TrackStatus.OK and r.ok
        # both images are bilinear resamplings of the same texture; 0.15 px is the brief's
        # tolerance (measured worst case over 400 points: 0.10 px)
        assert np.abs(r.uv_px - (p + SHIFT_PX)).max() < 0.15
        assert r.score > 0.95
        assert math.isnan(r.second_score) or r.second_score < r.score - 0.08


def test_translation_with_noise():
    rng = np.random.default_rng(5)
    A = _texture()
    B = _translate(A, SHIFT_PX)
    A_noisy, B_noisy = _add_noise(A, 3.0, rng), _add_noise(B, 3.0, rng)
    for p in _points(10, seed=2):
        r = _track_shifted(TRACKER, A_noisy, B_noisy, p, p + SHIFT_PX + PRED_ERROR_PX, S_px2=4.0 * np.eye(2))
        assert r.ok
        assert np.abs(r.uv_px - (p + SHIFT_PX)).max() < 0.3  # independent 3 DN noise in both images
        assert r.score > 0.9


def test_bgr_image_gives_the_grey_result():
    A = _texture()
    B = _translate(A, SHIFT_PX)
    p = np.array([150.2, 110.6])
    patch = TRACKER.make_patch(A, p, 0.0)
    r_grey = TRACKER.track(B, TRACKER.template(patch), p + SHIFT_PX, half_size_px=5)
    r_bgr = TRACKER.track(cv2.cvtColor(B, cv2.COLOR_GRAY2BGR), TRACKER.template(patch), p + SHIFT_PX, half_size_px=5)
    assert r_grey.ok and r_bgr.ok and np.allclose(r_grey.uv_px, r_bgr.uv_px, atol=1e-6)


def test_without_subpixel_the_match_is_an_integer():
    tracker = PatchTracker(TrackerConfig(subpixel=False))
    A = _texture()
    B = _translate(A, SHIFT_PX)
    p = np.array([150.0, 110.0])
    r = _track_shifted(tracker, A, B, p, p + SHIFT_PX, half_size_px=5)
    assert r.ok and np.array_equal(r.uv_px, np.round(p + SHIFT_PX))


# ---------------------------------------------------------------------- warped templates


def test_identity_and_translation_homographies_reproduce_the_plain_template():
    A = _texture()
    patch = TRACKER.make_patch(A, (140.0, 100.0), 0.0)
    plain = TRACKER.template(patch)
    np.testing.assert_allclose(TRACKER.template(patch, np.eye(3), (140.0, 100.0)), plain, atol=1e-3)
    H = np.array([[1.0, 0.0, 7.25], [0.0, 1.0, -3.5], [0.0, 0.0, 1.0]])
    np.testing.assert_allclose(TRACKER.template(patch, H, (147.25, 96.5)), plain, atol=1e-3)
    with pytest.raises(ValueError):
        TRACKER.template(patch, np.zeros((3, 3)), (0.0, 0.0))


def test_warped_template_follows_a_homography():
    A = _texture()
    S = 4.0 * np.eye(2)
    err_plain, err_warped, gain = [], [], []
    for p in _points(6, seed=3):
        q = p + SHIFT_PX
        # zoom 1.15 and 8 degrees about the point, as when approaching the ground and turning
        H = _similarity_about(p, q, 1.15, 8.0)
        B = cv2.warpPerspective(A, H, (WIDTH_PX, HEIGHT_PX), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        patch = TRACKER.make_patch(A, p, 0.0)
        pred = q + PRED_ERROR_PX
        plain = TRACKER.track(B, TRACKER.template(patch), pred, S_px2=S)
        warped = TRACKER.track(B, TRACKER.template(patch, H, pred), pred, S_px2=S)
        assert warped.ok
        assert np.linalg.norm(warped.uv_px - q) < 0.3
        assert warped.score > 0.95
        assert warped.score > plain.score
        gain.append(warped.score - plain.score)
        err_warped.append(np.linalg.norm(warped.uv_px - q))
        err_plain.append(np.linalg.norm(plain.uv_px - q) if plain.ok else np.inf)
    assert np.mean(gain) > 0.03  # measured 0.06
    assert np.median(err_plain) > 2.0 * np.median(err_warped)  # measured 0.33 px against 0.05 px


def test_templates_are_the_bilinear_samples_of_their_region():
    """Warped templates against bilinear interpolation by its definition (scipy's ``map_coordinates``,
    order 1, the border repeated) at the positions their matrices give, to float32 rounding;
    and against ``cv2.warpPerspective``, which rounds each position to 1/32 pixel: within 1/32 of
    the region's steepest step between neighbouring pixels. Positions past the border included."""
    from scipy.ndimage import map_coordinates

    A = _texture()
    patches = [TRACKER.make_patch(A, (100.0 + 9 * k, 80.0 + 7 * k), 0.0) for k in range(8)]
    radius = patches[0].region.shape[0] // 2
    rng = np.random.default_rng(4)
    Hs = np.array([_similarity_about(p.center_px, p.center_px + rng.normal(0, 3, 2), rng.uniform(0.6, 1.4), rng.uniform(-30, 30)) for p in patches])
    Hs[:, 2, :2] = rng.normal(0.0, 1e-3, (8, 2))  # perspective
    M = TRACKER.template_warps(np.array([p.center_px for p in patches]), radius, Hs)
    got = TRACKER.warp_templates(patches, M)
    side = got.shape[1]
    b, a = np.meshgrid(np.arange(side), np.arange(side))
    for k, patch in enumerate(patches):
        q = np.einsum("ij,jab->iab", M[k], np.stack([b, a, np.ones_like(a)]).astype(float))
        x, y = q[0] / q[2], q[1] / q[2]
        expected = map_coordinates(patch.region.astype(float), [y, x], order=1, mode="nearest")
        np.testing.assert_allclose(got[k], expected, rtol=0, atol=1e-4)
        region = patch.region.astype(float)
        steepest = max(np.abs(np.diff(region, axis=0)).max(), np.abs(np.diff(region, axis=1)).max())
        opencv = cv2.warpPerspective(patch.region_f32, M[k], (side, side), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_REPLICATE)
        assert np.abs(got[k] - opencv).max() <= steepest / 32.0
    zoomed_out = TRACKER.warp_templates(patches[:1], np.array([[[10.0, 0.0, -40.0], [0.0, 10.0, -40.0], [0.0, 0.0, 1.0]]]))[0]
    assert zoomed_out[0, 0] == patches[0].region_f32[0, 0] and zoomed_out[-1, -1] == patches[0].region_f32[-1, -1]  # the corners repeated


def test_warped_template_is_centred_on_the_point_even_with_a_poor_prediction():
    # the template depends on H and the patch, not on the prediction: a prediction 5 px off
    # still finds the patch's point, not the point that happens to lie under the prediction
    A = _texture()
    p = np.array([170.4, 95.3])
    q = p + SHIFT_PX
    H = _similarity_about(p, q, 1.15, 8.0)
    B = cv2.warpPerspective(A, H, (WIDTH_PX, HEIGHT_PX), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    patch = TRACKER.make_patch(A, p, 0.0)
    pred = q + np.array([4.0, -3.0])
    np.testing.assert_array_equal(TRACKER.template(patch, H, pred), TRACKER.template(patch, H, q))
    r = TRACKER.track(B, TRACKER.template(patch, H, pred), pred, S_px2=9.0 * np.eye(2))
    assert r.ok and np.linalg.norm(r.uv_px - q) < 0.3


# ---------------------------------------------------------------------- gating


def test_match_outside_the_ellipse_is_not_accepted_inside_it_is():
    A = _texture()
    B = _translate(A, SHIFT_PX)
    for p in _points(4, seed=4):
        q = p + SHIFT_PX
        far_pred = q + np.array([12.0, 0.0])
        r = _track_shifted(TRACKER, A, B, p, far_pred, S_px2=2.0 * np.eye(2))  # gate radius 4.3 px
        assert r.status is TrackStatus.LOW_SCORE and r.uv_px is None and r.score < 0.7
        r = _track_shifted(TRACKER, A, B, p, far_pred, S_px2=25.0 * np.eye(2))  # 144 / 25 = 5.8 < 9.21
        assert r.ok and np.abs(r.uv_px - q).max() < 0.15


def test_ellipse_not_its_bounding_box_decides():
    # the truth lies at (+6, -6) from the prediction: inside the bounding box of both ellipses
    # (half size 13), outside the one elongated along (1, 1), inside the round one
    A = _texture()
    B = _translate(A, SHIFT_PX)
    for p in _points(4, seed=5):
        q = p + SHIFT_PX
        pred = q - np.array([6.0, -6.0])
        r = _track_shifted(TRACKER, A, B, p, pred, S_px2=np.array([[16.0, 15.0], [15.0, 16.0]]))  # d'S^-1 d = 72
        assert r.search_half_size_px == (13, 13)
        assert r.status is TrackStatus.LOW_SCORE
        r = _track_shifted(TRACKER, A, B, p, pred, S_px2=16.0 * np.eye(2))  # d'S^-1 d = 4.5
        assert r.search_half_size_px == (13, 13)
        assert r.ok and np.abs(r.uv_px - q).max() < 0.15


def test_search_too_large():
    A = _texture()
    p = np.array([160.0, 120.0])
    r = _track_shifted(TRACKER, A, A, p, p, S_px2=np.diag([1e4, 1.0]))
    assert r.status is TrackStatus.SEARCH_TOO_LARGE and not r.ok
    assert r.uv_px is None and r.search_half_size_px == (0, 0)
    assert _track_shifted(TRACKER, A, A, p, p, half_size_px=41).status is TrackStatus.SEARCH_TOO_LARGE
    assert _track_shifted(TRACKER, A, A, p, p, half_size_px=40).ok


def test_out_of_image_and_clipped_search():
    A = _texture()
    B = _translate(A, SHIFT_PX)
    patch = TRACKER.make_patch(A, (25.0, 120.0), 0.0)
    tpl = TRACKER.template(patch)
    for pred in [(6.4, 120.0), (-30.0, 120.0), (160.0, HEIGHT_PX - 7.0), (np.nan, 10.0)]:
        r = TRACKER.track(B, tpl, pred, half_size_px=5)
        assert r.status is TrackStatus.OUT_OF_IMAGE and r.search_half_size_px == (0, 0)
    assert TRACKER.track(B, tpl, (7.0, 120.0), half_size_px=0).status is TrackStatus.LOW_SCORE  # fits: searched
    # a region cut by the image border is searched where the template fits
    q = np.array([25.0, 120.0]) + SHIFT_PX
    r = TRACKER.track(B, tpl, (12.0, 118.0), half_size_px=20)
    assert r.ok and np.abs(r.uv_px - q).max() < 0.15


def test_a_point_past_the_last_usable_row_or_column_is_refused_not_clamped():
    """The template's centre can sit no nearer the image border than its half size (row and column
    232 and 312 here). A point whose truth is past that is refused (PEAK_AT_BORDER), not matched at
    the border row: before the refusal, 19 of these points were matched, up to 1.4 px short of the
    truth, all towards the image's inside: the error that made ground points leaving the image by its
    bottom rows pull the trajectory's height up. Points inside are matched to 0.15 px."""
    A = _texture(3)
    shift = np.array([9.8, 10.3])
    B = _add_noise(_translate(A, shift), 1.0, np.random.default_rng(3))
    last_u, last_v = WIDTH_PX - 1 - 7, HEIGHT_PX - 1 - 7
    rng = np.random.default_rng(4)
    bottom = np.column_stack([rng.uniform(40.0, WIDTH_PX - 60.0, 40), rng.uniform(218.0, 223.0, 40)])  # truth rows 228.3-233.3
    right = np.column_stack([rng.uniform(298.0, 304.0, 40), rng.uniform(40.0, 180.0, 40)])  # truth columns 307.8-313.8
    refused = matched = 0
    for p in np.vstack([bottom, right]):
        q = p + shift
        pred = np.minimum(q + rng.normal(0.0, 0.3, 2), [last_u, last_v])  # a prediction where the template still fits
        r = _track_shifted(TRACKER, A, B, p, pred, half_size_px=4)
        past = max(q[0] - last_u, q[1] - last_v)
        if past > 0.1:  # the truth's nearest candidate is the border row or column: no peak to fit
            # refused; far past the border, the border row's score may already be too low
            assert r.status in (TrackStatus.PEAK_AT_BORDER, TrackStatus.LOW_SCORE) and r.uv_px is None, (p, q, r)
            refused += r.status is TrackStatus.PEAK_AT_BORDER
        elif past < -0.6:  # the candidate nearest the truth has neighbours on both sides
            assert r.ok and np.abs(r.uv_px - q).max() < 0.15, (p, q, r)
            matched += 1
        else:  # within rounding of the border: refused, or matched to the truth
            assert r.status is TrackStatus.PEAK_AT_BORDER or np.abs(r.uv_px - q).max() < 0.15, (p, q, r)
    assert refused >= 15 and matched >= 15, (refused, matched)


def test_a_peak_outside_the_gate_is_refused_not_taken_at_its_edge():
    """With ``refuse_peak_outside_gate``: truth more than half a pixel past the search region's last
    candidate, a candidate just outside (in the grid's one-pixel ring) scores higher than every one
    inside, and the match is refused (PEAK_OUTSIDE_GATE). Taken (the default), it is the edge
    candidate, off towards the prediction: 74 of this test's 105 points past the region are matched,
    0.23 to 2.7 px from the truth. Truths inside the region are matched to 0.15 px either way."""
    A = _texture()
    B = _add_noise(_translate(A, SHIFT_PX), 1.0, np.random.default_rng(5))
    rng = np.random.default_rng(6)
    half = 2
    strict = PatchTracker(TRACKER.config.model_copy(update=dict(refuse_peak_outside_gate=True)))
    refused = matched = taken = 0
    for p in _points(150, 7):
        q = p + SHIFT_PX
        pred = q + rng.uniform(-4.5, 4.5, 2)
        default = _track_shifted(TRACKER, A, B, p, pred, half_size_px=half)
        r = _track_shifted(strict, A, B, p, pred, half_size_px=half)
        past = np.max(np.abs(q - np.floor(pred + 0.5))) - half  # how far the truth is past the last candidate
        if past > 0.7:
            assert not r.ok and r.status in (TrackStatus.PEAK_OUTSIDE_GATE, TrackStatus.LOW_SCORE), (p, pred, r)
            refused += r.status is TrackStatus.PEAK_OUTSIDE_GATE
            if default.ok:  # the edge candidate: towards the prediction, short of the truth
                assert np.abs(default.uv_px - q).max() > 0.2, (p, pred, default)
                taken += 1
        elif past < 0.3:
            assert r.ok and np.abs(r.uv_px - q).max() < 0.15, (p, pred, r)
            assert default.ok and np.array_equal(default.uv_px, r.uv_px)
            matched += 1
    assert refused >= 30 and matched >= 30 and taken >= 30, (refused, matched, taken)


def test_flat_template_is_low_texture():
    A = _texture()
    r = TRACKER.track(A, np.full((15, 15), 90.0, np.float32), (160.0, 120.0), half_size_px=5)
    assert r.status is TrackStatus.LOW_TEXTURE and r.uv_px is None


# ---------------------------------------------------------------------- ambiguity and occlusion


@cache
def _stripes(period_px: int = 8) -> np.ndarray:
    """Texture periodic along u (period 8 px), random along v."""
    rng = np.random.default_rng(7)
    tile = rng.uniform(0.0, 255.0, (HEIGHT_PX + 40, period_px)).astype(np.float32)
    wide = np.tile(tile, (1, (WIDTH_PX + 40) // period_px + 1))
    blurred = cv2.GaussianBlur(wide, (0, 0), 1.5)[20 : 20 + HEIGHT_PX, 16 : 16 + WIDTH_PX]  # crop keeps the period
    return _normalise(blurred)


def test_periodic_texture_is_ambiguous_with_a_wide_region_and_ok_with_a_narrow_one():
    A = _stripes()
    B = _translate(A, SHIFT_PX)
    p = np.array([160.3, 120.6])
    q = p + SHIFT_PX
    for search in [dict(half_size_px=12), dict(S_px2=16.0 * np.eye(2))]:  # both span three periods
        r = _track_shifted(TRACKER, A, B, p, q, **search)
        assert r.status is TrackStatus.AMBIGUOUS and r.uv_px is None
        assert r.score - r.second_score < 0.08
    r = _track_shifted(TRACKER, A, B, p, q, half_size_px=3)  # one period: only the true peak
    assert r.ok and np.abs(r.uv_px - q).max() < 0.15
    r = _track_shifted(TRACKER, A, B, p, q, S_px2=1.0 * np.eye(2))  # gate radius 3 px
    assert r.ok and np.abs(r.uv_px - q).max() < 0.15


def test_occlusion_is_rejected_without_exception():
    A = _texture()
    B = _translate(A, SHIFT_PX)
    p = np.array([150.6, 110.2])
    q = p + SHIFT_PX
    occluded = B.copy()
    u, v = np.round(q).astype(int)
    occluded[v - 30 : v + 31, u - 30 : u + 31] = 140  # covers the template at every searched position
    r = _track_shifted(TRACKER, A, occluded, p, q, S_px2=4.0 * np.eye(2))
    assert not r.ok and r.status is TrackStatus.LOW_SCORE
    # half of the template covered: whatever the outcome, a result and no exception
    half_covered = B.copy()
    half_covered[v - 20 : v + 21, u : u + 20] = 140
    r = _track_shifted(TRACKER, A, half_covered, p, q, S_px2=4.0 * np.eye(2))
    assert isinstance(r, TrackResult) and r.status in set(TrackStatus)


# ---------------------------------------------------------------------- programming errors


def test_exactly_one_search_region_must_be_given():
    A = _texture()
    tpl = TRACKER.template(TRACKER.make_patch(A, (160.0, 120.0), 0.0))
    with pytest.raises(ValueError):
        TRACKER.track(A, tpl, (160.0, 120.0))
    with pytest.raises(ValueError):
        TRACKER.track(A, tpl, (160.0, 120.0), S_px2=np.eye(2), half_size_px=5)
    with pytest.raises(ValueError):
        TRACKER.track(A, tpl, (160.0, 120.0), S_px2=np.array([[1.0, 2.0], [2.0, 1.0]]))  # not positive definite
    with pytest.raises(ValueError):
        TRACKER.track(A, tpl[:, :-1], (160.0, 120.0), half_size_px=5)


def test_batched_homographies_match_opencv():
    """The front end's batched 4-point homographies equal OpenCV's, and degenerate sets are NaN."""
    from dem_graph.frontend.warp_kernel import homographies_from_4_points

    rng = np.random.default_rng(11)
    src = rng.uniform(0, 800, (20, 4, 2))
    dst = src + rng.normal(0, 20, (20, 4, 2))
    src[3] = src[3, :1]  # four equal points
    H = homographies_from_4_points(src, dst)
    for k in range(20):
        if k == 3:
            assert np.isnan(H[k]).all()
            continue
        expected = cv2.getPerspectiveTransform(src[k].astype(np.float32), dst[k].astype(np.float32))
        np.testing.assert_allclose(H[k], expected, rtol=1e-3, atol=1e-6)  # OpenCV's from float32 corners
        mapped = np.c_[src[k], np.ones(4)] @ H[k].T
        np.testing.assert_allclose(mapped[:, :2] / mapped[:, 2:], dst[k], rtol=0, atol=1e-8)  # the definition, in float64
    src[5, 2, 0] = np.nan
    assert np.isnan(homographies_from_4_points(src, dst)[5]).all()


def test_ground_homographies_map_the_ground_squares_corners_between_the_views():
    """Each point's homography takes its ground square's corners, projected into the source view,
    onto the same corners projected into the current one (PinholeCamera.project, with distortion),
    to 1e-6 px; a point with a corner behind either camera gets NaN."""
    from dem_graph.frontend.warp_kernel import ground_homographies
    from dem_graph.geometry.camera import PinholeCamera
    from dem_graph.geometry.se3 import invert, make_pose, rotation_from_rpy

    camera = PinholeCamera(800, 600, 610.0, 605.0, 401.5, 298.0, (-0.28, 0.09, 1e-3, -5e-4, -0.01))
    rng = np.random.default_rng(4)
    down = rotation_from_rpy(-np.pi / 2 - 0.3, 0.0, -np.pi / 2)  # looking ahead along +x, pitched down
    n, half_m = 40, 0.15
    T_now = make_pose(down, [0.0, 0.0, 1.2])
    T_source = np.array([make_pose(down @ rotation_from_rpy(*rng.normal(0, 0.03, 3)), [rng.uniform(-1.0, 0.0), rng.normal(0, 0.1), 1.2 + rng.normal(0, 0.02)]) for _ in range(n)])
    X = np.column_stack([rng.uniform(2.5, 6.0, n), rng.uniform(-1.5, 1.5, n), rng.normal(0, 0.05, n)])
    X[7, 0] = -3.0  # behind both cameras
    H = ground_homographies(X, T_source, T_now, camera.intrinsics_array, half_m)
    corners = X[:, None, :] + np.array([[-half_m, -half_m, 0], [half_m, -half_m, 0], [half_m, half_m, 0], [-half_m, half_m, 0]])
    for k in range(n):
        if k == 7:
            assert np.isnan(H[k]).all()
            continue
        uv0, f0 = camera.project(corners[k] @ invert(T_source[k])[:3, :3].T + invert(T_source[k])[:3, 3])
        uv1, f1 = camera.project(corners[k] @ invert(T_now)[:3, :3].T + invert(T_now)[:3, 3])
        assert f0.all() and f1.all()
        mapped = np.c_[uv0, np.ones(4)] @ H[k].T
        np.testing.assert_allclose(mapped[:, :2] / mapped[:, 2:], uv1, rtol=0, atol=1e-6)


def _template_warps_numpy(centers_src_px, region_radius_px, half, H):
    """The template warps as numpy computed them before they were compiled: inverse by LAPACK."""
    n = len(H)
    c_src = np.concatenate([centers_src_px, np.ones((n, 1))], axis=1)
    finite = np.isfinite(H).all(axis=(1, 2))
    H = np.where(finite[:, None, None], H, np.eye(3))
    scale = np.abs(H).max(axis=(1, 2))
    c_h = np.einsum("nij,nj->ni", H, c_src)
    ok = finite & (np.abs(c_h[:, 2]) > 1e-12 * scale) & (np.abs(np.linalg.det(H)) > 1e-12 * scale**3)
    H = np.where(ok[:, None, None], H, np.eye(3))
    c_cur = c_h[:, :2] / np.where(ok, c_h[:, 2], 1.0)[:, None]
    M = np.linalg.inv(H)
    M[:, :, 2] += np.einsum("nij,nj->ni", M[:, :, :2], c_cur - half)
    M[:, :2, :] += (region_radius_px - c_src[:, :2])[:, :, None] * M[:, 2:3, :]
    M[~ok] = np.nan
    return M


def test_compiled_template_warps_equal_numpys():
    """The compiled template warps against the numpy formula they replaced, on random
    similarities with perspective, a singular homography, one sending the centre to infinity and
    one not finite: to 1e-9 relative, NaN where numpy gave NaN."""
    rng = np.random.default_rng(8)
    n = 50
    centers = rng.uniform(20, 300, (n, 2))
    H = np.array([_similarity_about(c, c + rng.normal(0, 4, 2), rng.uniform(0.7, 1.3), rng.uniform(-20, 20)) for c in centers])
    H[:, 2, :2] = rng.normal(0.0, 1e-3, (n, 2))
    H[1] = np.outer([1.0, 2.0, 3.0], [1.0, 0.5, 0.2])  # singular
    H[2, 2] = [1.0 / centers[2, 0], 0.0, -1.0]  # the centre to infinity
    H[3, 0, 0] = np.inf
    got = TRACKER.template_warps(centers, 20, H)
    expected = _template_warps_numpy(centers, 20, TRACKER.config.patch_half_size_px, H)
    assert np.isnan(got[1:4]).all() and np.array_equal(np.isnan(got), np.isnan(expected))
    ok = ~np.isnan(expected[:, 0, 0])
    np.testing.assert_allclose(got[ok], expected[ok], rtol=1e-9, atol=1e-9)


def test_batched_template_warps_equal_one_at_a_time():
    A = _texture()
    patches = [TRACKER.make_patch(A, (140.0 + 5 * k, 100.0 + 3 * k), 0.0) for k in range(3)]
    Hs = np.array([[[1.0, 0.02 * k, 3.0], [0.01, 1.0 + 0.05 * k, -2.0], [1e-4 * k, 0.0, 1.0]] for k in range(3)])
    radius = patches[0].region.shape[0] // 2
    M = TRACKER.template_warps(np.array([p.center_px for p in patches]), radius, Hs)
    for k, patch in enumerate(patches):
        np.testing.assert_array_equal(TRACKER.warp_template(patch, M[k]), TRACKER.template(patch, Hs[k], (0.0, 0.0)))
    bad = TRACKER.template_warps(np.array([[140.0, 100.0]]), radius, np.full((1, 3, 3), np.nan))
    assert np.isnan(bad).all()


def test_the_kernels_a_frame_runs_are_compiled_before_it():
    """After ``compile_kernels`` a frame's tracking (batched and one point at a time; a grey image,
    a read-only one as a ROS bag's raw images come, and a BGR one; warped templates) runs every
    compiled kernel with a signature it already has: nothing is compiled in the first frame."""
    from dem_graph.frontend import match_kernel, warp_kernel

    kernels = [match_kernel.plan_searches, match_kernel.ncc_grids, match_kernel.ncc_grid, match_kernel.select_matches, match_kernel.select_match,
               warp_kernel.sample_templates, warp_kernel.template_warps, warp_kernel.homographies_from_4_points, warp_kernel.ground_homographies]  # fmt: skip
    tracker = PatchTracker()
    tracker.compile_kernels()
    before = [len(k.signatures) for k in kernels]
    A = _texture()
    points = _points(12, seed=5)
    patches = [tracker.make_patch(A, p, 0.0) for p in points]
    H = warp_kernel.homographies_from_4_points(np.random.default_rng(0).uniform(0, 300, (12, 4, 2)), np.random.default_rng(1).uniform(0, 300, (12, 4, 2)))
    warp_kernel.ground_homographies(np.full((12, 3), 3.0), np.array([np.eye(4)] * 12), np.eye(4), np.array([500.0, 500.0, 0, 0, 0, 0, 0, 0, 0]), 0.15)  # as FrontEnd.template_warps
    M = tracker.template_warps(np.array([p.center_px for p in patches]), patches[0].region.shape[0] // 2, np.tile(np.eye(3), (12, 1, 1)))
    tpl = tracker.warp_templates(patches, M)
    S = np.tile(4.0 * np.eye(2), (12, 1, 1))
    read_only = A.copy()
    read_only.flags.writeable = False
    for image in (A, read_only, cv2.cvtColor(A, cv2.COLOR_GRAY2BGR)):
        tracker.track_many(image, tpl, points + 0.4, S_px2=S)
        tracker.track_many(image, tpl, points + 0.4, half_size_px=3)
        tracker.track(image, tpl[0], points[0] + 0.4, S_px2=S[0])
    assert np.isfinite(H).any() and [len(k.signatures) for k in kernels] == before and min(before) >= 1
