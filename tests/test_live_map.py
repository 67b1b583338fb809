"""Incremental fusion and the live map.

Truths: the batch fusion (:func:`fuse`, gate off) of the same measurements is the weighted mean the
incremental grid must hold after any sequence of additions, removals and revisions; laser returns
placed in batch with the current poses (:func:`laser_returns_world`) are what the live map must hold
after revisions; the gate's decisions are set by hand-made cells.
"""

from __future__ import annotations

import numpy as np
import pytest

from dem_graph.dem.fusion import FusionConfig, fuse
from dem_graph.dem.incremental import IncrementalDem
from dem_graph.dem.live_map import LiveMap
from dem_graph.dem.returns import GroundReturns, PoseTrack, laser_returns_world
from dem_graph.dem.views import local_dem
from dem_graph.errors import DemGraphError
from dem_graph.geometry.lie import retract
from dem_graph.geometry.rig import default_rig
from dem_graph.geometry.se3 import make_pose, rotation_from_rpy

NO_GATE = FusionConfig(gate_sigma=1e12, min_variance_m2=1e-8)
TOL = 1e-9


def _random_batch(rng, n, t, spread_m=2.0):
    xyz = np.column_stack([rng.uniform(-spread_m, spread_m, n), rng.uniform(-spread_m, spread_m, n), rng.normal(0.3, 0.05, n)])
    return GroundReturns(xyz, rng.uniform(1e-4, 4e-3, n), np.full(n, float(t)), rng.integers(0, 2, n).astype(np.uint8))


def _assert_same_map(grid: IncrementalDem, batch: GroundReturns, config: FusionConfig):
    """The grid's global map equals the batch fusion of ``batch`` (gate off) on the same cells."""
    geometry = grid.covering_geometry()
    expected = fuse(batch, geometry, config)
    got = grid.sample(*geometry.cell_centers_xy())
    np.testing.assert_array_equal(np.isfinite(got["elevation"]), expected.covered)
    has = expected.covered
    # the batch's layers are float32: compare with the float64 sums computed from the same measurements
    cell_row, cell_col, _ = geometry.cell_index(batch.xyz_m[:, 0], batch.xyz_m[:, 1])
    cell = cell_row * geometry.n_cols + cell_col
    w = 1.0 / np.maximum(batch.var_z_m2, config.min_variance_m2)
    W = np.bincount(cell, weights=w, minlength=geometry.n_rows * geometry.n_cols).reshape(geometry.shape)
    WZ = np.bincount(cell, weights=w * batch.xyz_m[:, 2], minlength=geometry.n_rows * geometry.n_cols).reshape(geometry.shape)
    with np.errstate(invalid="ignore", divide="ignore"):
        np.testing.assert_allclose(got["elevation"][has], (WZ / W)[has], rtol=0, atol=TOL)
        np.testing.assert_allclose(got["variance"][has], (1.0 / W)[has], rtol=TOL, atol=0)
    np.testing.assert_array_equal(got["count"], expected.layers["count"])
    np.testing.assert_array_equal(got["laser_count"], expected.layers["laser_count"])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_after_random_additions_removals_and_revisions_the_grid_equals_the_batch_fusion(seed):
    rng = np.random.default_rng(seed)
    grid = IncrementalDem(NO_GATE, tile_cells=8)  # small tiles: batches span several
    held: dict[int, tuple[GroundReturns, object]] = {}
    next_id = 0
    for step in range(300):
        op = rng.uniform()
        if op < 0.5 or not held:
            batch = _random_batch(rng, int(rng.integers(1, 60)), step)
            held[next_id] = (batch, grid.add(batch))
            next_id += 1
        elif op < 0.75:
            key = list(held)[int(rng.integers(len(held)))]
            grid.remove(held.pop(key)[1])
        else:  # a revision: the batch moves (a new pose) and is placed again
            key = list(held)[int(rng.integers(len(held)))]
            batch, placed = held[key]
            grid.remove(placed)
            shift = rng.normal(0, 0.05, 3)
            moved = GroundReturns(batch.xyz_m + shift, batch.var_z_m2 * rng.uniform(0.5, 2.0), batch.t_s, batch.source)
            held[key] = (moved, grid.add(moved))
    everything = GroundReturns.concatenate([b for b, _ in held.values()])
    assert grid.n_kept == len(everything)
    _assert_same_map(grid, everything, NO_GATE)


def test_batches_far_apart_and_cells_never_measured():
    """Batches whose points lie 100 m apart (their tiles looked up one by one, not as a box)
    and batches around the origin (negative cells) give the batch fusion; a cell of a tile never
    made samples as unknown, with zero counts and no time."""
    rng = np.random.default_rng(11)
    grid = IncrementalDem(NO_GATE, tile_cells=8)
    held = []
    for step in range(60):
        batch = _random_batch(rng, 30, step)
        if step % 3 == 0:  # a third of each such batch 100 m east and 60 m south
            far = np.zeros_like(batch.xyz_m)
            far[:10] = [100.0, -60.0, 0.0]
            batch = GroundReturns(batch.xyz_m + far, batch.var_z_m2, batch.t_s, batch.source)
        held.append((batch, grid.add(batch)))
        if step % 4 == 3:
            grid.remove(held.pop(int(rng.integers(len(held))))[1])
    everything = GroundReturns.concatenate([b for b, _ in held])
    rows, cols, _ = grid.covering_geometry().cell_index(everything.xyz_m[:, 0], everything.xyz_m[:, 1])
    assert np.ptp(cols) > 950  # the map does span both places
    _assert_same_map(grid, everything, NO_GATE)
    unknown = grid.sample(np.array([50.0, -0.05]), np.array([-30.0, 1e4]))
    assert np.all(np.isnan(unknown["elevation"])) and np.all(unknown["count"] == 0) and np.all(np.isnan(unknown["last_update_s"]))


def test_the_whole_map_made_tile_by_tile_is_the_map_sampled_cell_by_cell():
    """to_dem()'s tiles placed whole (the global map's fast path) against sampling every cell of the
    same grid: the same numbers, bit for bit, with batches far apart (empty tiles between) and removals."""
    rng = np.random.default_rng(5)
    grid = IncrementalDem(NO_GATE, tile_cells=8)
    held = []
    for step in range(40):
        batch = _random_batch(rng, 25, step)
        if step % 5 == 0:
            batch = GroundReturns(batch.xyz_m + [30.0, -20.0, 0.0], batch.var_z_m2, batch.t_s, batch.source)
        held.append(grid.add(batch))
        if step % 6 == 5:
            grid.remove(held.pop(0))
    fast, sampled = grid.to_dem(), grid.to_dem(grid.covering_geometry())
    assert fast.geometry == sampled.geometry and np.isfinite(fast.layers["elevation"]).sum() > 100
    for name, layer in sampled.layers.items():
        np.testing.assert_array_equal(fast.layers[name], layer, err_msg=name)


def test_removing_everything_leaves_exact_zeros():
    rng = np.random.default_rng(5)
    grid = IncrementalDem(NO_GATE)
    placed = [grid.add(_random_batch(rng, 40, i)) for i in range(20)]
    for p in placed[::-1]:
        grid.remove(p)
    sums, counts = grid._blocks()  # w, wz; n, n_laser, n_out (and the times, which stay)
    assert grid.n_tiles > 0
    assert np.all(sums == 0.0) and np.all(counts[:3] == 0.0)


def test_the_gate_tests_a_batch_against_the_cell_as_it_stood_before_it():
    cell = (0.05, 0.05)
    config = FusionConfig(gate_sigma=3.0, gate_floor_m=0.0)
    grid = IncrementalDem(config, gate_min_count=3)

    def batch(z, var=1e-4):
        z = np.atleast_1d(np.asarray(z, float))
        return GroundReturns(np.column_stack([np.full(len(z), cell[0]), np.full(len(z), cell[1]), z]), np.full(len(z), var), np.zeros(len(z)), np.zeros(len(z), np.uint8))

    # a cell with fewer than gate_min_count measurements takes the whole batch, outlier included
    first = grid.add(batch([0.20, 0.21, 0.90]))
    assert first.kept.tolist() == [True, True, True]
    grid.remove(first)
    grid.add(batch([0.20, 0.21, 0.19]))
    # now h = 0.20, var_cell = 1e-4 / 3: 0.5 m is 43 sigma away, 0.22 m is 1.7 sigma
    second = grid.add(batch([0.70, 0.22]))
    assert second.kept.tolist() == [False, True]
    s = grid.sample(np.array([cell[0]]), np.array([cell[1]]))
    assert s["count"][0] == 4 and s["outliers"][0] == 1
    assert s["elevation"][0] == pytest.approx(np.mean([0.20, 0.21, 0.19, 0.22]), abs=TOL)
    # taking the batch back takes back its outlier count and its kept measurement only
    grid.remove(second)
    s = grid.sample(np.array([cell[0]]), np.array([cell[1]]))
    assert s["count"][0] == 3 and s["outliers"][0] == 0
    assert s["elevation"][0] == pytest.approx(0.20, abs=TOL)


def test_with_the_gate_the_grid_holds_the_weighted_mean_of_what_it_kept():
    rng = np.random.default_rng(7)
    grid = IncrementalDem(FusionConfig(gate_sigma=2.0), tile_cells=8)
    batches = []
    for i in range(80):
        b = _random_batch(rng, 50, i, spread_m=0.5)  # 100 cells: many measurements each, some gated out
        batches.append((b, grid.add(b)))
    assert grid.n_rejected > 0
    kept = GroundReturns.concatenate([b.select(p.kept) for b, p in batches])
    _assert_same_map(grid, kept, NO_GATE)


def test_map_memory_grows_with_the_area_mapped_not_with_the_measurements():
    rng = np.random.default_rng(3)
    grid = IncrementalDem(NO_GATE, tile_cells=32)
    for i in range(50):
        grid.add(_random_batch(rng, 200, i, spread_m=1.5))
    tiles = grid.n_tiles
    for i in range(500):
        grid.add(_random_batch(rng, 200, i, spread_m=1.5))
    assert grid.n_tiles == tiles  # 25 000 more measurements on the same 3 m x 3 m: no new memory


# --- the live map ----------------------------------------------------------------------------


def _track(n=40, dt=0.1, seed=0):
    """A pose track driving +x at 1.5 m/s over flat ground with a little roll and pitch."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * dt
    T = np.array([make_pose(rotation_from_rpy(rng.normal(0, 0.01), rng.normal(0, 0.01), 0.02 * k), [1.5 * tk, 0.05 * k, 0.0]) for k, tk in enumerate(t)])
    P = np.array([np.diag([1e-5] * 3 + [1e-4] * 3) * (1 + k) for k in range(n)])
    return PoseTrack(t, T, P)


def _scans(rig, track, per_frame=2, seed=1):
    rng = np.random.default_rng(seed)
    t = np.arange(track.t_s[0], track.t_s[-1], (track.t_s[1] - track.t_s[0]) / per_frame)
    ranges = rng.uniform(2.5, 4.0, (len(t), len(rig.laser.beam_directions())))
    ranges[:, ::17] = np.nan  # some beams without a return
    return t, ranges


def _mapped():
    """The default rig's scans over :func:`_track`, each placed in a live map (no gate, nothing frozen) with the track's pose."""
    rig = default_rig()
    track = _track()
    t_scan, ranges = _scans(rig, track)
    live = LiveMap(rig, NO_GATE, window_s=1e9)
    for t, r in zip(t_scan, ranges, strict=True):
        T, P = track.at(np.array([t]))
        live.add_scan(t, r, T[0], P[0])
    return rig, track, t_scan, ranges, live


def test_live_map_after_revisions_equals_the_batch_placement_with_the_current_poses():
    rig, track, t_scan, ranges, live = _mapped()
    # revise: frames 10..19 move (a smoother's correction), the rest stay
    rng = np.random.default_rng(4)
    T_new = track.T_world_body.copy()
    for k in range(10, 20):
        T_new[k] = retract(T_new[k], rng.normal(0, [0.01, 0.01, 0.01, 0.05, 0.05, 0.05]))
    revised = PoseTrack(track.t_s, T_new, track.covariance)
    T_before = np.array([s.T_world_body for s in live._log])
    moved_returns = live.revise(revised.at)
    T_after = np.array([s.T_world_body for s in live._log])
    changed = np.any(np.abs(T_after - T_before) > 0, axis=(1, 2))
    # exactly the scans between frame 9 and frame 20 moved (their interpolation uses a moved frame)
    expected = (t_scan > track.t_s[9]) & (t_scan < track.t_s[20])
    np.testing.assert_array_equal(changed, expected)
    assert moved_returns == sum(len(s.placed) for s, c in zip(live._log, changed, strict=True) if c)
    batch = laser_returns_world(t_scan, ranges, rig, revised)
    _assert_same_map(live.grid, batch, NO_GATE)


def test_frozen_scans_stay_where_they_were_placed():
    rig, track, t_scan, ranges, live = _mapped()
    live.freeze_before(2.0)
    assert np.all(live.logged_times_s >= 2.0)
    shifted = PoseTrack(track.t_s, track.T_world_body @ make_pose(np.eye(3), [0.0, 0.0, 0.1]), track.covariance)
    live.revise(shifted.at)
    old = t_scan < 2.0
    batch = GroundReturns.concatenate([laser_returns_world(t_scan[old], ranges[old], rig, track), laser_returns_world(t_scan[~old], ranges[~old], rig, shifted)])
    _assert_same_map(live.grid, batch, NO_GATE)


def test_live_local_map_matches_the_hindsight_local_dem_where_cells_line_up():
    """On a heading along +x with no yaw, local cells are world cells: the two local maps agree."""
    rig = default_rig()
    t = np.arange(30) * 0.1
    T = np.array([make_pose(np.eye(3), [1.5 * tk, 0.0, 0.0]) for tk in t])
    track = PoseTrack(t, T, np.repeat(np.diag([1e-6] * 6)[None], len(t), axis=0))
    t_scan, ranges = _scans(rig, track)
    live = LiveMap(rig, NO_GATE)
    for ts, r in zip(t_scan, ranges, strict=True):
        Tq, Pq = track.at(np.array([ts]))
        live.add_scan(ts, r, Tq[0], Pq[0])
    t_now = float(t_scan[-1])
    T_now = track.at(np.array([t_now]))[0][0]
    # the body origin on a cell edge (x = 4.35 is not): shift the query so cells align
    T_now[0, 3] = np.round(T_now[0, 3] / 0.1) * 0.1
    got = live.local(T_now, (1.0, 6.0), 2.5, t_now)
    poses = PoseTrack(np.r_[track.t_s, t_now + 1e-3], np.concatenate([track.T_world_body, T_now[None]]), np.concatenate([track.covariance, track.covariance[-1:]]))
    want = local_dem(laser_returns_world(t_scan, ranges, rig, track), poses, t_now + 1e-3, (1.0, 6.0), 2.5, NO_GATE, history_s=100.0)
    # the centre beam lands on y = 0, a cell edge, where rounding puts it on either side: rows 24, 25 left out
    rows = np.r_[0:24, 26:50]
    np.testing.assert_array_equal(got.covered[rows], want.covered[rows])
    has = np.zeros_like(want.covered)
    has[rows] = want.covered[rows]
    assert has.sum() > 100
    np.testing.assert_allclose(got.elevation[has], want.elevation[has], atol=1e-5)  # float32 layers
    assert np.all(got.layers["age_s"][has] >= 0)
    assert "slope_deg" in got.layers


def test_a_scan_of_the_wrong_length_is_refused_in_one_line():
    rig = default_rig()
    live = LiveMap(rig)
    with pytest.raises(DemGraphError, match="beams"):
        live.add_scan(0.0, np.ones(5), np.eye(4), np.eye(6) * 1e-6)


def test_the_traversability_kernel_is_compiled_before_the_first_local_map(monkeypatch):
    """Making a live map runs the traversability kernel once, with the signature a local map then
    uses: nothing is compiled in the first frame. A fresh dispatcher of the same kernel, so that no
    other test's call counts. The local map's slope is that of its own elevation."""
    import numba

    from dem_graph.dem import traversability as trav

    fresh = numba.njit(nogil=True)(trav._layers.py_func)
    monkeypatch.setattr(trav, "_layers", fresh)
    rig, track, t_scan, ranges, _ = _mapped()
    live = LiveMap(rig, NO_GATE)
    assert len(fresh.signatures) == 1
    for t, r in zip(t_scan, ranges, strict=True):
        T, P = track.at(np.array([t]))
        live.add_scan(t, r, T[0], P[0])
    local = live.local(track.T_world_body[-1], (1.0, 6.0), 2.5, float(t_scan[-1]))
    assert len(fresh.signatures) == 1
    slope = local.layers["slope_deg"]
    assert np.isfinite(slope).sum() > 50
    np.testing.assert_array_equal(slope, trav.traversability(local.elevation, 0.1)["slope_deg"])
