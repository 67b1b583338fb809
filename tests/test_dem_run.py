"""A run's DEM: made by `dem-graph run`, made again by `dem-graph dem RUN`, measured against the truth."""

from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner

from dem_graph.cli import main
from dem_graph.dem.returns import GroundReturns, PoseTrack
from dem_graph.errors import DemGraphError
from dem_graph.evaluation.dem_metrics import LocalErrorConfig
from dem_graph.io.dem_files import read_dem_npz
from dem_graph.io.live_maps import read_live_maps
from dem_graph.pipeline.run_dem import ground_returns, make_run_dem
from dem_graph.pipeline.run_folder import LOCAL_ERROR_COLUMNS, write_run_dem


def _truth_track(sequence, dt_s=0.04) -> PoseTrack:
    gt = sequence.ground_truth.trajectory
    t = np.arange(gt.t_s[0], gt.t_s[-1] + 1e-9, dt_s)
    return PoseTrack(t, gt.at(t), np.zeros((len(t), 6, 6)))


def test_with_ground_truth_poses_the_smoke_dem_and_its_local_window_are_within_the_range_noise(smoke_log, tmp_path):
    poses = _truth_track(smoke_log)
    returns = ground_returns(smoke_log, poses)
    run_dem = make_run_dem(returns, poses, smoke_log.ground_truth, local_error=LocalErrorConfig(every_n_frames=1))
    m = run_dem.metrics
    sigma = smoke_log.rig.laser.range_sigma_m
    assert m.height_error_laser_cells.cells > 500
    assert m.height_error_laser_cells.rmse_m < 0.5 * sigma
    lw = m.local_window
    assert lw.frames_with_data > 0.8 * lw.frames
    # exact poses: the paper's measure and the vehicle-relative one agree, and both are unbiased
    series = run_dem.local_series
    ok = np.isfinite(series.mean_m)
    np.testing.assert_allclose(series.mean_m[ok], series.relative_mean_m[ok], atol=1e-5)
    assert lw.mean_abs_mean_m < 0.25 * sigma
    assert lw.mean_of_std_m < sigma
    # the run folder keeps the series frame by frame (Fig. 8 for one run), to the digits written
    paths = write_run_dem(run_dem, tmp_path)
    table = np.genfromtxt(paths["local_dem_error"], delimiter=",", names=True)
    assert table.dtype.names == LOCAL_ERROR_COLUMNS and len(table) == len(series.t_s)
    for name in LOCAL_ERROR_COLUMNS:
        np.testing.assert_allclose(table[name], getattr(series, name), rtol=1e-8, atol=1e-12, equal_nan=True)


def test_no_measurement_at_all_is_a_clear_error():
    track = PoseTrack(np.array([0.0, 1.0]), np.stack([np.eye(4)] * 2), np.zeros((2, 6, 6)))
    with pytest.raises(DemGraphError, match="no ground measurement"):
        make_run_dem(GroundReturns.empty(), track)


@pytest.fixture(scope="module")
def run_folder(tmp_path_factory):
    root = tmp_path_factory.mktemp("dem_run")
    log = root / "smoke"
    r = CliRunner().invoke(
        main, ["--no-progress", "simulate", "--scenario", "smoke", "--seed", "7", "--length-m", "1.5", "--out", str(log)]
    )
    assert r.exit_code == 0, r.output
    out = root / "run"
    r = CliRunner().invoke(main, ["--no-progress", "run", str(log), "--estimator", "ptpm", "--out", str(out)])
    assert r.exit_code == 0, r.output
    assert "DEM:" in r.output
    return log, out


def test_dem_command_makes_the_runs_dem_again_from_its_saved_poses(run_folder, tmp_path):
    log, out = run_folder
    for name in ("dem.tif", "dem.npz", "dem.png", "cloud.ply", "poses.npz"):
        assert (out / name).is_file(), name
    again = tmp_path / "again"
    r = CliRunner().invoke(main, ["--no-progress", "dem", str(out), "--out", str(again)])  # the dataset from metrics.json
    assert r.exit_code == 0, r.output
    a, b = read_dem_npz(out / "dem.npz"), read_dem_npz(again / "dem.npz")
    assert a.geometry == b.geometry
    np.testing.assert_array_equal(a.layers["count"], b.layers["count"])
    # map points' variances are stored as float32 in points.ply: they weigh the heights again to
    # float32 rounding, so a cell's elevation may land on the neighbouring float32
    for name in ("elevation", "variance"):
        np.testing.assert_allclose(a.layers[name], b.layers[name], rtol=1e-6)
    dem_metrics = json.loads((out / "metrics.json").read_text())["dem"]
    assert dem_metrics["covered_cells"] == int(np.isfinite(a.elevation).sum())


@pytest.mark.parametrize("hindsight", [False, True])
def test_dem_command_local_map_at_a_time_holds_only_earlier_measurements(run_folder, tmp_path, hindsight):
    """The live map as saved at the last saved frame before T, or (--hindsight) one made from the final poses."""
    log, out = run_folder
    argv = ["--no-progress", "dem", str(out), "--dataset", str(log), "--at-s", "0.6", "--out", str(tmp_path / "local")]
    r = CliRunner().invoke(main, argv + (["--hindsight"] if hindsight else []))
    assert r.exit_code == 0, r.output
    local = read_dem_npz(tmp_path / "local" / "dem.npz")
    assert local.frame == "local"
    assert np.nanmax(local.layers["last_update_s"]) <= 0.6
    assert local.geometry.x_min_m > 0 if hindsight else local.geometry.x_min_m >= 0  # the focus area, or the saved window from the body on
    if not hindsight:
        saved = read_live_maps(out / "live_maps.nc")
        t = float(local.meta["t_s"]) if "t_s" in local.meta else float(r.output.split(" at ")[1].split(" s")[0])
        assert t == pytest.approx(saved["time"].values[saved["time"].values <= 0.6][-1], abs=1e-3)


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["dem", "{tmp}/nowhere"], "run folder not found"),
        (["dem", "{tmp}", "--dataset", "{log}"], "not a run folder written by `dem-graph run` (no poses.npz)"),
        (["dem", "{run}", "--dataset", "{log}", "--at-s", "99"], "outside the run's poses"),
        (["dem", "{run}", "--dataset", "{log}", "--at-s", "99", "--hindsight"], "outside the run's poses"),
    ],
)
def test_dem_command_bad_input_is_one_line(run_folder, tmp_path, args, message):
    log, out = run_folder
    argv = ["--no-progress", *[a.format(tmp=tmp_path, log=log, run=out) for a in args]]
    r = CliRunner().invoke(main, argv)
    assert r.exit_code == 2
    assert message in r.output and "Traceback" not in r.output
    assert len(r.output.strip().splitlines()) == 1


def test_a_run_without_any_laser_return_makes_its_dem_from_the_map_points_alone(smoke_log):
    from dataclasses import replace

    from dem_graph.datasets.events import LaserScan
    from dem_graph.pipeline import RunConfig, run_estimator

    blind = smoke_log.replace_events(
        [replace(e, ranges_m=e.ranges_m * np.nan) if isinstance(e, LaserScan) else e for e in smoke_log.events()]
    )
    run = run_estimator(blind, RunConfig(estimator="ptpm", max_frames=20))
    assert run.error is None
    d = run.metrics.dem
    assert d.laser_returns == 0
    assert d.measurements == run.metrics.map_points > 0
    dem = run.dem.dem
    assert np.all(dem.layers["laser_count"] == 0)
    assert np.all(np.isfinite(dem.variance[dem.covered]))


@pytest.mark.parametrize("resolution", ["0", "1e-6"])  # 1e-6 m once tried to allocate petabytes
def test_dem_command_with_a_resolution_below_a_centimetre_is_one_line(run_folder, tmp_path, resolution):
    log, out = run_folder
    r = CliRunner().invoke(
        main, ["--no-progress", "dem", str(out), "--dataset", str(log), "--resolution-m", resolution, "--out", str(tmp_path / "d")]
    )
    assert r.exit_code == 2 and r.stderr.count("\n") == 1
    assert "invalid DEM resolution: resolution_m: Input should be greater than or equal to 0.01" in r.stderr
