"""The frame's fast paths against the plain computations they replaced: the same numbers, to the bit.

``ncc_grid`` forms its numerators in blocks held in vector registers
(:mod:`dem_graph.frontend.vector_kernel`) and its windows' sums in integers; the front end's
templates read the regions a :class:`PatchStore` keeps; a patch's spread is OpenCV's unless within
rounding of the minimum; new points' distances to the live ones are taken for many candidates at
once. These tests hold each to a reference that computes every number the plain way, in the
plain order: the results must be equal, not close, since the EKF baselines' tracks are asked to stay
the same to the bit.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from dem_graph.frontend.match_kernel import ncc_grid
from dem_graph.frontend.patch_store import PatchStore
from dem_graph.frontend.tracker import PatchTracker
from dem_graph.frontend.vector_kernel import BLOCK_LANES, BLOCK_ROWS, correlate_block


def _ncc_one_pixel_at_a_time(roi: np.ndarray, tpl: np.ndarray) -> np.ndarray:
    """The scores with each sum formed sequentially: template mean and spread pixel by pixel in
    row-major order, each numerator as zero plus one product per template pixel in row-major order
    (numpy's element-wise multiply, then add: one rounding each), the windows' sums exactly."""
    t_rows, t_cols = tpl.shape
    n_rows, n_cols = roi.shape[0] - t_rows + 1, roi.shape[1] - t_cols + 1
    n_px = t_rows * t_cols
    t_mean = 0.0
    for x in tpl.ravel().tolist():
        t_mean += float(np.float32(x))
    t_mean /= n_px
    d = tpl.astype(np.float64) - t_mean
    t_norm2 = 0.0
    for x in d.ravel().tolist():
        t_norm2 += x * x
    if t_norm2 < 2.220446049250313e-16:
        return np.ones((n_rows, n_cols))
    region = roi.astype(np.float64)
    num = np.zeros((n_rows, n_cols))
    for a in range(t_rows):
        for b in range(t_cols):
            num = num + region[a : a + n_rows, b : b + n_cols] * d[a, b]
    windows = np.lib.stride_tricks.sliding_window_view(roi.astype(np.int64), tpl.shape)
    w1 = windows.sum(axis=(2, 3)).astype(np.float64)
    w2 = (windows**2).sum(axis=(2, 3)).astype(np.float64)
    out = np.empty((n_rows, n_cols))
    t_norm = math.sqrt(t_norm2)
    for i in range(n_rows):
        for j in range(n_cols):
            denom = math.sqrt(max(w2[i, j] - w1[i, j] * w1[i, j] / n_px, 0.0)) * t_norm
            v = num[i, j]
            out[i, j] = v / denom if abs(v) < denom else ((1.0 if v > 0 else -1.0) if abs(v) < denom * 1.125 else 0.0)
    return out


def _compiled(roi: np.ndarray, tpl: np.ndarray) -> np.ndarray:
    n_rows, n_cols = roi.shape[0] - tpl.shape[0] + 1, roi.shape[1] - tpl.shape[1] + 1
    out = np.empty(n_rows * n_cols)
    ncc_grid(np.ascontiguousarray(roi), 0, 0, n_rows, n_cols, np.ascontiguousarray(tpl, dtype=np.float32), out)
    return out.reshape(n_rows, n_cols)


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_the_vector_correlation_equals_the_sums_formed_one_pixel_at_a_time(seed):
    """Grids of every size class the blocks meet (one candidate; fewer, exactly and more than a
    block's rows and lanes; the largest search), templates of 3, 9 and 15 pixels, textured, coarse
    (few grey levels: ties and flat windows) and flat: every score equal to the reference's."""
    rng = np.random.default_rng(seed)
    image = rng.integers(0, 256, (120, 140)).astype(np.uint8)
    coarse = (image // 85 * 85).astype(np.uint8)
    shapes = [(1, 1), (BLOCK_ROWS - 1, BLOCK_LANES - 1), (BLOCK_ROWS, BLOCK_LANES), (BLOCK_ROWS + 1, BLOCK_LANES + 1), (11, 9), (83, 83)]
    for n_rows, n_cols in shapes:
        for t in (3, 9, 15):
            for src in (image, coarse):
                r0, c0 = rng.integers(0, 120 - n_rows - t + 2), rng.integers(0, 140 - n_cols - t + 2)
                roi = src[r0 : r0 + n_rows + t - 1, c0 : c0 + n_cols + t - 1]
                tpl = (src[:t, :t] + rng.normal(0.0, 2.0, (t, t))).astype(np.float32)
                np.testing.assert_array_equal(_compiled(roi, tpl), _ncc_one_pixel_at_a_time(roi, tpl))
            flat = np.full((t, t), 42.0, dtype=np.float32)
            np.testing.assert_array_equal(_compiled(roi, flat), np.ones((n_rows, n_cols)))


def test_one_block_of_sums():
    """``correlate_block`` alone: a block of BLOCK_ROWS x BLOCK_LANES sums at an offset into a
    padded region, written with a row stride into a larger array, equal to the sequential sums; the
    entries around the block untouched."""
    rng = np.random.default_rng(7)
    t_rows, t_cols, stride = 5, 4, 30
    region = rng.integers(0, 256, (20 * stride,)).astype(np.float64)
    weights = rng.normal(0.0, 40.0, t_rows * t_cols)
    out = np.full(10 * 16, -1.0)
    row0, col0 = 3, 6

    @__import__("numba").njit
    def call(region, weights, out):
        correlate_block(region, stride, weights, t_rows, t_cols, row0, col0, out[2 * 16 + 4 :], 16)

    call(region, weights, out)
    grid = region.reshape(20, stride)
    expected = np.zeros((BLOCK_ROWS, BLOCK_LANES))
    for a in range(t_rows):
        for b in range(t_cols):
            expected = expected + grid[row0 + a : row0 + a + BLOCK_ROWS, col0 + b : col0 + b + BLOCK_LANES] * weights[a * t_cols + b]
    got = out.reshape(10, 16)
    np.testing.assert_array_equal(got[2 : 2 + BLOCK_ROWS, 4 : 4 + BLOCK_LANES], expected)
    untouched = np.ones((10, 16), dtype=bool)
    untouched[2 : 2 + BLOCK_ROWS, 4 : 4 + BLOCK_LANES] = False
    assert np.all(got[untouched] == -1.0)


def test_the_patch_store_keeps_each_points_patch_in_its_slot():
    """Patches put, replaced and removed, past the first capacity: each live point's slot holds its
    latest patch's region, centre and source pose; freed slots are used again; the templates warped
    from the store equal the ones warped from the patches themselves."""
    tracker = PatchTracker()
    rng = np.random.default_rng(3)
    image = rng.integers(0, 256, (200, 240)).astype(np.uint8)
    side = 2 * (tracker.config.patch_half_size_px + tracker.config.warp_margin_px) + 1
    store = PatchStore(side, capacity=4)
    live = {}
    for step in range(40):
        point_id = int(rng.integers(0, 12))
        if point_id in live and rng.random() < 0.4:
            store.remove(point_id)
            del live[point_id]
            continue
        uv = rng.uniform(30, 170, 2)
        patch = tracker.make_patch(image, uv, float(step))
        T = np.eye(4)
        T[:3, 3] = rng.normal(size=3)
        store.put(point_id, patch, T)
        live[point_id] = (patch, T)
    ids = np.array(sorted(live))
    slots = store.slots(ids)
    assert len(store) == len(live) and len(set(slots.tolist())) == len(ids) and slots.max() < len(store.regions)
    for point_id, slot in zip(ids.tolist(), slots.tolist()):
        patch, T = live[point_id]
        np.testing.assert_array_equal(store.regions[slot], patch.region_f32)
        np.testing.assert_array_equal(store.centers_px[slot], patch.center_px)
        np.testing.assert_array_equal(store.T_world_cam_source[slot], T)
    patches = [live[p][0] for p in ids.tolist()]
    M = tracker.template_warps(np.array([p.center_px for p in patches]), side // 2, np.tile(np.array([[1.02, 0.05, -1.0], [0.0, 0.97, 2.0], [1e-4, 0.0, 1.0]]), (len(ids), 1, 1)))
    np.testing.assert_array_equal(tracker.warp_regions(store.regions, slots, M), tracker.warp_templates(patches, M))


def test_a_patchs_spread_is_decided_as_numpys_std_decides_it():
    """Patches whose spread is far from the minimum, and ones built to sit on it within rounding
    (two grey levels in proportions that put numpy's std at the minimum or a hair either side): the
    decision is the one numpy's ``std`` gives, every time."""
    from dem_graph.frontend.tracker import _spread_below

    rng = np.random.default_rng(5)
    cases = [rng.integers(0, 256, (15, 15)).astype(np.uint8) for _ in range(50)]
    cases += [np.full((15, 15), 9, dtype=np.uint8)]
    for n_high in range(1, 225):  # two levels 0 and g: std = g * sqrt(p (1 - p)), p = n_high / 225
        for g in (6, 7, 8):
            patch = np.zeros(225, dtype=np.uint8)
            patch[:n_high] = g
            cases.append(patch.reshape(15, 15))
    for patch in cases:
        std = float(patch.std())
        for min_std in (std, np.nextafter(std, 0.0), np.nextafter(std, 9.0), 3.0, 0.0):
            assert _spread_below(patch, min_std) == (std < min_std)


def test_new_points_keep_their_distance_as_one_candidate_at_a_time(smoke_log):
    """``FrontEnd._seed`` over 300 candidates (several chunks of distances), with 200 live points
    and a budget that ends it part way: the candidates seeded, in order, are the ones a check of
    one candidate at a time against the live and already seeded points picks."""
    from dem_graph.frontend.frontend import _SEED_CHUNK, FrontEnd, FrontendConfig, PointKind

    fe = FrontEnd(FrontendConfig(min_separation_px=9.0), smoke_log.rig)
    rng = np.random.default_rng(8)
    image = rng.integers(0, 256, (240, 320)).astype(np.uint8)
    live = rng.uniform(30, [290, 210], (200, 2))
    uv = rng.uniform(30, [290, 210], (300, 2))
    uv[::7] = live[: len(uv[::7])] + 0.5  # some candidates right on live points
    for budget in (0, 5, 40, 300):
        got = [k for k, _ in fe._seed(PointKind.CAMERA, range(len(uv)), uv, budget, live, image, 0.0, np.eye(4))]
        expected, occupied = [], live.copy()
        for k in range(len(uv)):
            if len(expected) >= budget:
                break
            if np.min(np.sum((occupied - uv[k]) ** 2, axis=1)) >= 81.0:
                expected.append(k)
                occupied = np.vstack([occupied, uv[k]])
        assert got == expected
    assert max(got) >= _SEED_CHUNK  # the unbudgeted run seeded from past the first chunk of distances
