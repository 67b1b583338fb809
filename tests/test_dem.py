"""The dense DEM: returns placed with their poses, per-cell fusion, traversability, views and files.

Truths: analytic terrains ray-cast by the simulator's laser with ground-truth poses, hand-made
measurements whose fused value is known in closed form, and Monte Carlo for the propagated variance.
"""

from __future__ import annotations

import numpy as np
import pytest

from dem_graph.dem.fusion import FusionConfig, fuse
from dem_graph.dem.returns import GroundReturns, PoseTrack, ReturnSource, laser_returns_world
from dem_graph.dem.traversability import traversability
from dem_graph.dem.views import global_dem, local_dem, local_frame
from dem_graph.errors import DatasetError, DemGraphError
from dem_graph.geometry.grid import ElevationGrid, GridGeometry
from dem_graph.geometry.lie import retract
from dem_graph.geometry.rig import default_rig
from dem_graph.geometry.se3 import make_pose, rotation_from_rpy
from dem_graph.io.dem_files import read_dem_npz

RANGE_SIGMA_M = 0.02  # the default rig's laser


def _returns(z, var, xy=(0.05, 0.05), t=None) -> GroundReturns:
    z = np.asarray(z, dtype=float)
    n = len(z)
    xyz = np.column_stack([np.full(n, xy[0]), np.full(n, xy[1]), z])
    return GroundReturns(xyz, np.broadcast_to(np.asarray(var, dtype=float), (n,)).copy(), np.arange(n, dtype=float) if t is None else np.asarray(t, float), np.zeros(n, np.uint8))


ONE_CELL = GridGeometry(0.0, 0.1, 0.1, 1, 1)


# --- fusion ----------------------------------------------------------------------------------


def test_a_cell_fuses_to_the_inverse_variance_mean_and_its_variance_falls_as_hits_accumulate():
    rng = np.random.default_rng(0)
    z = 0.3 + rng.normal(0, 0.02, 64)
    var = rng.uniform(1e-4, 9e-4, 64)
    variances = []
    for n in (1, 4, 16, 64):
        dem = fuse(_returns(z[:n], var[:n]), ONE_CELL, FusionConfig(gate_sigma=100.0))
        w = 1.0 / var[:n]
        assert dem.elevation[0, 0] == pytest.approx(np.sum(w * z[:n]) / w.sum(), abs=1e-6)
        assert dem.variance[0, 0] == pytest.approx(1.0 / w.sum(), rel=1e-5)
        assert dem.layers["count"][0, 0] == n
        variances.append(float(dem.variance[0, 0]))
    assert all(a > b for a, b in zip(variances, variances[1:]))


def test_outliers_fail_the_gate_even_when_they_come_first():
    """Three returns 0.5 m too high, the first three in time, against 20 good ones (sigma 1 cm)."""
    rng = np.random.default_rng(1)
    good = 0.2 + rng.normal(0, 0.01, 20)
    z = np.r_[[0.7, 0.71, 0.69], good]
    dem = fuse(_returns(z, 1e-4), ONE_CELL, FusionConfig(gate_floor_m=0.0))
    assert dem.layers["outliers"][0, 0] == 3
    assert dem.layers["count"][0, 0] == 20
    assert dem.elevation[0, 0] == pytest.approx(good.mean(), abs=1e-6)  # equal variances: the plain mean
    assert dem.layers["max"][0, 0] == pytest.approx(good.max(), abs=1e-6)
    assert dem.layers["min"][0, 0] == pytest.approx(good.min(), abs=1e-6)
    assert dem.layers["last_update_s"][0, 0] == 22.0


def test_nan_measurements_are_left_out_and_never_reach_a_valid_cell():
    geometry = GridGeometry(0.0, 1.0, 0.1, 10, 10)
    rng = np.random.default_rng(2)
    n = 500
    xyz = np.column_stack([rng.uniform(0, 1, n), rng.uniform(0, 1, n), rng.normal(0, 0.01, n)])
    clean = GroundReturns(xyz, np.full(n, 1e-4), np.arange(n, dtype=float), np.zeros(n, np.uint8))
    dirty_xyz = np.vstack([xyz, [[0.55, 0.55, np.nan], [np.nan, 0.5, 0.0], [0.25, 0.25, 1.0]]])
    dirty_var = np.r_[np.full(n, 1e-4), 1e-4, 1e-4, np.nan]
    dirty = GroundReturns(dirty_xyz, dirty_var, np.arange(n + 3, dtype=float), np.zeros(n + 3, np.uint8))
    a, b = fuse(clean, geometry), fuse(dirty, geometry)
    for name in ("elevation", "variance", "count"):
        np.testing.assert_array_equal(a.layers[name], b.layers[name])


def test_empty_input_gives_an_empty_map_not_an_error():
    geometry = GridGeometry(0.0, 1.0, 0.1, 10, 10)
    dem = fuse(GroundReturns.empty(), geometry)
    assert not dem.covered.any() and np.all(dem.layers["count"] == 0)
    with pytest.raises(DemGraphError, match="no ground measurement"):
        global_dem(GroundReturns.empty())


def test_fusion_puts_each_measurement_in_the_cell_the_grid_says():
    geometry = GridGeometry(-3.0, 2.0, 0.25, 16, 24)
    rng = np.random.default_rng(3)
    n = 2000
    xyz = np.column_stack([rng.uniform(-3.5, 3.5, n), rng.uniform(-2.5, 2.5, n), np.zeros(n)])
    xyz[:, 2] = rng.integers(0, 1000, n)  # a distinct height per measurement: cells with one hit reveal which
    dem = fuse(GroundReturns(xyz, np.full(n, 1e-4), np.zeros(n), np.zeros(n, np.uint8)), geometry, FusionConfig(gate_sigma=1e6))
    row, col, inside = geometry.cell_index(xyz[:, 0], xyz[:, 1])
    counts = np.zeros(geometry.shape)
    np.add.at(counts, (row[inside], col[inside]), 1)
    np.testing.assert_array_equal(dem.layers["count"], counts)
    single = np.flatnonzero(counts[row[inside], col[inside]] == 1)
    np.testing.assert_allclose(dem.elevation[row[inside][single], col[inside][single]], xyz[inside][single, 2], rtol=1e-6)


# --- returns ---------------------------------------------------------------------------------


def test_a_returns_height_variance_matches_monte_carlo_through_pose_and_range_noise():
    rig = default_rig()
    T = make_pose(rotation_from_rpy(0.05, -0.03, 0.8), [3.0, -2.0, 0.4])
    rng = np.random.default_rng(4)
    A = rng.normal(size=(6, 6)) * np.r_[0.01, 0.01, 0.01, 0.05, 0.05, 0.05][:, None]
    P = A @ A.T
    ranges = np.full((1, rig.laser.beams.count), np.nan)
    beams = [30, 180, 330]
    ranges[0, beams] = [4.0, 3.2, 5.0]
    track = PoseTrack(np.array([0.0, 1.0]), np.stack([T, T]), np.stack([P, P]))
    ret = laser_returns_world(np.array([0.5]), ranges, rig, track)
    assert len(ret) == 3
    # Monte Carlo: perturb the pose on the right and the ranges
    n = 40000
    L = np.linalg.cholesky(P)
    xi = rng.normal(size=(n, 6)) @ L.T
    d = rig.laser.beam_directions()[beams]
    z = np.empty((n, 3))
    for i in range(n):
        Ti = retract(T, xi[i])
        r = ranges[0, beams] + rng.normal(0, RANGE_SIGMA_M, 3)
        p = (rig.T_body_laser[:3, :3] @ (r[:, None] * d).T).T + rig.T_body_laser[:3, 3]
        z[i] = (Ti[:3, :3] @ p.T).T[:, 2] + Ti[2, 3]
    np.testing.assert_allclose(ret.var_z_m2, z.var(axis=0), rtol=0.05)  # 40000 samples: ~0.7 % sampling error
    np.testing.assert_allclose(ret.xyz_m[:, 2], z.mean(axis=0), atol=0.01)


def test_placing_returns_with_a_pose_each_one_for_all_or_by_index_is_the_array_formula():
    """The compiled placement against the module's equations written with numpy (position R p + t;
    variance J P J^T + (a . d)^2 sigma_r^2, J = [p x a, a], a = R^T e_z), to 1e-12 relative, in its
    three call forms; indices that point past the poses are refused."""
    from dem_graph.dem.returns import place_returns

    rng = np.random.default_rng(8)
    n, m = 50, 4
    poses = np.array([retract(make_pose(rotation_from_rpy(*rng.normal(0, 0.2, 3)), rng.normal(0, 5, 3)), np.zeros(6)) for _ in range(m)])
    L = rng.normal(0, 0.05, (m, 6, 6))
    P = L @ np.swapaxes(L, 1, 2) + 1e-6 * np.eye(6)
    p_body = rng.uniform(-3, 3, (n, 3))
    d_body = rng.normal(size=(n, 3))
    d_body /= np.linalg.norm(d_body, axis=1, keepdims=True)
    pose_of = rng.integers(0, m, n)

    def formula(T, C):
        R = T[:, :3, :3]
        a = R[:, 2, :]
        J = np.concatenate([np.cross(p_body, a), a], axis=1)
        return np.einsum("nij,nj->ni", R, p_body) + T[:, :3, 3], np.einsum("ni,nij,nj->n", J, C, J) + (np.einsum("ni,ni->n", a, d_body) * RANGE_SIGMA_M) ** 2

    for got, want in (
        (place_returns(p_body, d_body, poses[pose_of], P[pose_of], RANGE_SIGMA_M), formula(poses[pose_of], P[pose_of])),
        (place_returns(p_body, d_body, poses[:1], P[:1], RANGE_SIGMA_M), formula(np.repeat(poses[:1], n, 0), np.repeat(P[:1], n, 0))),
        (place_returns(p_body, d_body, poses, P, RANGE_SIGMA_M, pose_of=pose_of), formula(poses[pose_of], P[pose_of])),
    ):
        np.testing.assert_allclose(got[0], want[0], rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(got[1], want[1], rtol=1e-12)
    with pytest.raises(DemGraphError, match="disagree"):
        place_returns(p_body, d_body, poses, P, RANGE_SIGMA_M, pose_of=pose_of + m)


def test_returns_outside_the_track_and_without_a_return_are_left_out():
    rig = default_rig()
    track = PoseTrack(np.array([0.0, 1.0]), np.stack([np.eye(4)] * 2), np.zeros((2, 6, 6)))
    ranges = np.full((3, rig.laser.beams.count), 3.0)
    ranges[0, :10] = np.nan
    ranges[0, 10:20] = 1e6  # beyond range_max_m
    ret = laser_returns_world(np.array([0.5, 0.9, 1.5]), ranges, rig, track)
    assert len(ret) == 2 * rig.laser.beams.count - 20
    with pytest.raises(DemGraphError, match="shape"):
        laser_returns_world(np.array([0.5]), ranges, rig, track)


# --- terrains recovered with ground-truth poses ------------------------------------------------


def _terrain(kind: str) -> ElevationGrid:
    g = GridGeometry.covering(-2.0, -6.0, 12.0, 6.0, 0.02)
    x, y = g.cell_centers_xy()
    z = {
        "plane": np.full(x.shape, 0.1),
        "slope": 0.15 * x,
        "sinusoid": 0.15 * np.sin(2 * np.pi * x / 3.0) * np.cos(2 * np.pi * y / 4.0),
    }[kind]
    return ElevationGrid(g, z.astype(np.float32))


@pytest.mark.parametrize("kind", ["plane", "slope", "sinusoid"])
def test_terrains_are_recovered_within_the_range_noise_with_ground_truth_poses(kind):
    from dem_graph.sim.laser import cast_scan
    from dem_graph.sim.raycast import TerrainScene

    rig = default_rig()
    truth = _terrain(kind)
    scene = TerrainScene(truth)
    rng = np.random.default_rng(5)
    t = np.arange(0.0, 4.0, 0.08)  # 12.5 Hz at 1.5 m/s: 6 m
    x_body = 1.5 * t
    T = np.stack([make_pose(np.eye(3), [x, 0.0, float(truth.height_at(x, 0.0))]) for x in x_body])
    # the same drive twice (the second pass 4 s later), with fresh range noise
    t2, T2 = np.r_[t, t + 4.0], np.concatenate([T, T])
    ranges = np.stack([cast_scan(scene, T2[i] @ rig.T_body_laser, rig.laser, rng) for i in range(len(t2))])
    track = PoseTrack(t2, T2, np.zeros((len(t2), 6, 6)))
    returns = laser_returns_world(t2, ranges, rig, track)
    dem = global_dem(returns, FusionConfig(resolution_m=0.1))
    x, y = dem.geometry.cell_centers_xy()
    z_truth = truth.height_at(x, y)
    err = dem.elevation - z_truth
    ok = np.isfinite(err)
    assert ok.sum() > 1000
    rmse = float(np.sqrt(np.mean(err[ok] ** 2)))
    # measured: 3.5 mm (plane), 6.6 mm (slope), 6.5 mm (sinusoid); half the noise of one return
    assert rmse < 0.5 * RANGE_SIGMA_M, f"{kind}: height RMSE {rmse:.4f} m"
    assert abs(float(err[ok].mean())) < 0.003
    # the reported variance falls as hits accumulate: the first pass alone against both
    first = global_dem(returns.until(3.99), FusionConfig(resolution_m=0.1), geometry=dem.geometry)
    both = first.covered & dem.covered
    ratio = dem.variance[both] / first.variance[both]
    assert np.all(ratio <= 1.0 + 1e-6)
    assert np.median(ratio) == pytest.approx(0.5, abs=0.1)


# --- traversability --------------------------------------------------------------------------


def test_traversability_of_a_plane_a_step_and_noise():
    res = 0.1
    rows, cols = np.indices((30, 40), dtype=float)
    slope = np.tan(np.radians(10.0)) * cols * res  # rising eastwards by 10 degrees
    t = traversability(slope, res)
    inner = (slice(1, -1), slice(1, -1))
    np.testing.assert_allclose(t["slope_deg"][inner], 10.0, atol=1e-3)
    np.testing.assert_allclose(t["roughness_m"][inner], 0.0, atol=1e-6)
    np.testing.assert_allclose(t["step_height_m"][inner], 2 * res * np.tan(np.radians(10.0)), atol=1e-6)
    step = np.where(cols >= 20, 0.2, 0.0)
    s = traversability(step, res)["step_height_m"]
    assert s[10, 19] == pytest.approx(0.2) and s[10, 20] == pytest.approx(0.2) and s[10, 10] == 0.0
    noisy = np.random.default_rng(6).normal(0, 0.01, (200, 200))
    r = traversability(noisy, res, window=5)["roughness_m"][2:-2, 2:-2]
    assert float(np.mean(r)) == pytest.approx(0.01, rel=0.05)
    holes = slope.copy()
    holes[5, 5] = np.nan
    th = traversability(holes, res)
    assert np.isnan(th["slope_deg"][5, 5]) and th["slope_deg"][5, 6] == pytest.approx(10.0, abs=1e-3)


def _traversability_by_least_squares(z, res, window):
    """The layers' definition, one cell at a time: numpy's least-squares plane through the known
    heights of each window (x east, y north, metres), the step from their range."""
    h = window // 2
    out = {k: np.full(z.shape, np.nan) for k in ("slope_deg", "step_height_m", "roughness_m")}
    for r, c in np.argwhere(np.isfinite(z)):
        rr, cc = np.mgrid[max(r - h, 0) : r + h + 1, max(c - h, 0) : c + h + 1].reshape(2, -1)
        keep = (rr < z.shape[0]) & (cc < z.shape[1])
        rr, cc = rr[keep], cc[keep]
        known = np.isfinite(z[rr, cc])
        rr, cc, zz = rr[known], cc[known], z[rr[known], cc[known]]
        if len(zz) >= 3:
            out["step_height_m"][r, c] = zz.max() - zz.min()
        A = np.column_stack([np.ones(len(zz)), cc * res, -rr * res])
        if len(zz) >= 4 and np.linalg.matrix_rank(A) == 3:
            g, *_ = np.linalg.lstsq(A, zz, rcond=None)
            out["slope_deg"][r, c] = np.degrees(np.arctan(np.hypot(g[1], g[2])))
            out["roughness_m"][r, c] = np.sqrt(np.sum((zz - A @ g) ** 2) / (len(zz) - 3))
    return out


@pytest.mark.parametrize("window", [3, 5])
def test_traversability_is_the_least_squares_plane_of_every_window_with_holes(window):
    """Every cell of a rough tilted grid with half its heights missing, against the per-cell
    least-squares definition: the same cells known (exactly 4 heights give a slope, exactly 3 a
    step: the box filters this replaced lost some of those to rounding), values to 1e-6 in the
    float32 layers."""
    rng = np.random.default_rng(window)
    z = rng.normal(0.0, 0.05, (24, 30)) + 3.0 + 0.01 * np.indices((24, 30))[1]
    z[rng.random(z.shape) < 0.5] = np.nan
    got = traversability(z, 0.1, window)
    want = _traversability_by_least_squares(z, 0.1, window)
    for key, expected in want.items():
        assert np.array_equal(np.isnan(got[key]), np.isnan(expected)), key
        np.testing.assert_allclose(got[key], expected, atol=1e-4 if key == "slope_deg" else 1e-6, rtol=1e-6, err_msg=key)
    assert np.isfinite(got["slope_deg"]).sum() > 100


# --- views -----------------------------------------------------------------------------------


def test_the_local_map_is_in_the_heading_frame_and_only_holds_what_was_known_then():
    yaw = np.radians(90.0)
    T_body = make_pose(rotation_from_rpy(0.1, 0.05, yaw), [10.0, 5.0, 2.0])  # rolled and pitched
    track = PoseTrack(np.array([0.0, 10.0]), np.stack([T_body, T_body]), np.zeros((2, 6, 6)))
    # a measurement 3.1 m ahead (world +y), 0.2 m above the body origin, and one from the future
    xyz = np.array([[9.9, 8.1, 2.2], [9.9, 8.1, 5.0]])  # local (3.1, 0.1)
    ret = GroundReturns(xyz, np.full(2, 1e-4), np.array([1.0, 6.0]), np.array([ReturnSource.LASER_RETURN, ReturnSource.MAP_POINT], np.uint8))
    dem = local_dem(ret, track, 5.0, (2.0, 4.0), 1.0, FusionConfig(resolution_m=0.5))
    assert dem.frame == "local"
    row, col, _ = dem.geometry.cell_index(3.1, 0.1)
    assert dem.elevation[row, col] == pytest.approx(0.2)
    assert dem.covered.sum() == 1  # the future one is not there
    np.testing.assert_allclose(local_frame(T_body)[:3, 2], [0, 0, 1], atol=1e-12)


# --- files -----------------------------------------------------------------------------------


def test_a_cell_centre_in_the_geotiff_maps_to_its_world_xy(tmp_path):
    import rasterio

    from dem_graph.pipeline.run_folder import write_dem_outputs

    geometry = GridGeometry(100.0, 50.0, 0.2, 20, 30)
    x, y, z = 103.33, 47.71, 1.25
    dem = fuse(GroundReturns(np.array([[x, y, z]]), np.array([1e-4]), np.zeros(1), np.zeros(1, np.uint8)), geometry)
    paths = write_dem_outputs(tmp_path, dem, GroundReturns(np.array([[x, y, z]]), np.array([1e-4]), np.zeros(1), np.zeros(1, np.uint8)))
    with rasterio.open(paths["dem_tif"]) as src:
        names = list(src.descriptions)
        assert names[:3] == ["elevation", "variance", "count"]
        row, col = src.index(x, y)
        assert src.read(1)[row, col] == pytest.approx(z)
        assert src.read(3)[row, col] == 1
        cx, cy = src.xy(row, col)  # the cell's centre
        assert abs(cx - x) <= 0.1 and abs(cy - y) <= 0.1
        assert (cx, cy) == pytest.approx((100.0 + (col + 0.5) * 0.2, 50.0 - (row + 0.5) * 0.2))
        assert np.isnan(src.nodata) and np.isnan(src.read(1)[0, 0])
    assert paths["dem_png"].stat().st_size > 1000
    back = read_dem_npz(paths["dem_npz"])
    assert back.geometry == geometry
    for k, v in dem.layers.items():
        np.testing.assert_array_equal(back.layers[k], v)


def test_a_corrupt_dem_file_gives_a_clear_error(tmp_path):
    bad = tmp_path / "dem.npz"
    bad.write_bytes(b"not a zip")
    with pytest.raises(DatasetError, match="dem.npz"):
        read_dem_npz(bad)
    with pytest.raises(DatasetError, match="not found"):
        read_dem_npz(tmp_path / "missing.npz")
