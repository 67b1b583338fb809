"""The live pipeline on the `smoke` log: one update per frame with the map as it stands, the same
map a batch fusion makes from the same poses, and bad input logged and skipped or bridged while the
map goes on.

Truths: the estimator's own frame records (the update's pose), the batch fusion of the laser
returns placed with the run's per-frame poses, the simulator's ground truth, and the events taken
out or put in by hand.
"""

from __future__ import annotations

import logging

import numpy as np
import pytest

from dem_graph.datasets.events import CameraFrame, LaserScan, Odometry
from dem_graph.dem.fusion import FusionConfig, fuse
from dem_graph.dem.returns import PoseTrack, laser_returns_world
from dem_graph.pipeline.config import RunConfig
from dem_graph.pipeline.live import LivePipeline, PoseWindow
from dem_graph.pipeline.run import run_estimator

NO_GATE = FusionConfig(gate_sigma=1e12)


def _live(log, estimator="ptpm", **config) -> tuple[LivePipeline, list]:
    c = RunConfig(estimator=estimator, **config)
    pipeline = LivePipeline.for_sequence(log, c)
    updates = [u for u in (pipeline.on_event(e) for e in log.events()) if u is not None]
    last = pipeline.finish()
    return pipeline, updates + ([last] if last is not None else [])


def _frames(log):
    return [e for e in log.events() if isinstance(e, CameraFrame)]


@pytest.fixture(scope="module")
def clean_live(smoke_log) -> tuple[LivePipeline, list]:
    """`_live(smoke_log)`, made once: the run the tests below check, and hold the runs on edited logs to
    (they read it and leave it as it is)."""
    return _live(smoke_log)


def test_one_update_per_frame_with_the_estimators_pose_and_a_local_map(smoke_log, clean_live):
    pipeline, updates = clean_live
    frames = pipeline.result().frames
    assert len(updates) == len(frames) == len(_frames(smoke_log))
    for u, f in zip(updates, frames, strict=True):
        assert u.t_s == f.t_s
        np.testing.assert_array_equal(u.T_world_body, f.T_world_body)
    last = updates[-1]
    assert last.local.frame == "local"
    assert {"elevation", "variance", "count", "age_s", "slope_deg", "step_height_m", "roughness_m"} <= set(last.local.layers)
    # the local map ahead has heights, against the true terrain under the estimated cells to 5 cm
    truth = smoke_log.ground_truth
    covered = last.local.covered
    assert covered.sum() > 50
    xl, yl = last.local.geometry.cell_centers_xy()
    T = last.local.meta["T_world_local"]
    z_true = truth.elevation.height_at(T[0, 3] + T[0, 0] * xl + T[0, 1] * yl, T[1, 3] + T[1, 0] * xl + T[1, 1] * yl) - T[2, 3]
    err = (last.local.elevation - z_true)[covered & np.isfinite(z_true)]
    assert np.sqrt(np.mean(err**2)) < 0.05
    # an age is the time since the cell's latest measurement: never negative, and the map is not older than the log
    age = last.local.layers["age_s"][covered]
    assert np.all(age >= 0) and np.all(age <= last.t_s - smoke_log.t_start_s)


def test_the_live_map_equals_the_batch_fusion_of_the_scans_placed_with_the_final_frame_poses(smoke_log):
    """PTPM never revises a frame once made: after the log, every scan sits at the pose between
    the frames around it, as a batch placement with the same poses puts it."""
    events = list(smoke_log.events())
    last_frame = max(i for i, e in enumerate(events) if isinstance(e, CameraFrame))
    log = smoke_log.replace_events(events[: last_frame + 1])
    pipeline, _ = _live(log, dem={"fusion": NO_GATE.model_dump(), "map_points": False})
    res = pipeline.result()
    c = RunConfig()
    P0 = np.eye(6) * c.motion.initial_sigma_pose**2
    t = np.r_[log.t_start_s, [f.t_s for f in res.frames]]
    T = np.concatenate([log.T_world_body_initial[None], [f.T_world_body for f in res.frames]])
    P = np.concatenate([P0[None], res.pose_covariances()])
    first = 1 if t[1] <= t[0] else 0  # a first frame at the start time: its pose, not the start's
    poses = PoseTrack(t[first:], T[first:], P[first:])
    t_scan, ranges = log.laser_scans()
    batch = laser_returns_world(t_scan, ranges, log.rig, poses)
    grid = pipeline.map.grid
    geometry = grid.covering_geometry()
    expected = fuse(batch, geometry, NO_GATE)
    got = grid.sample(*geometry.cell_centers_xy())
    laser_only = got["count"] == got["laser_count"]  # map points (seeded from the same scans) join some cells
    np.testing.assert_array_equal(got["laser_count"], expected.layers["laser_count"])
    has = laser_only & expected.covered
    assert has.sum() > 1000
    np.testing.assert_allclose(got["elevation"][has], expected.elevation[has], atol=1e-6)  # float32 batch layers
    np.testing.assert_allclose(got["variance"][has], expected.variance[has], rtol=1e-5)


def test_pose_window_interpolates_as_the_trajectory_does_and_extrapolates_at_constant_velocity():
    from dem_graph.geometry.lie import retract
    from dem_graph.geometry.trajectory import Trajectory

    rng = np.random.default_rng(2)
    t = np.array([0.0, 0.1, 0.2, 0.3])
    T = np.array([retract(np.eye(4), rng.normal(0, 0.1, 6)) for _ in t])
    P = np.array([np.eye(6) * (k + 1) for k in range(4)])
    w = PoseWindow(t, T, P)
    q = np.array([0.05, 0.17, 0.3])
    T_w, P_w = w.at(q)
    np.testing.assert_allclose(T_w, Trajectory.from_poses(t, T).at(q), atol=1e-12)
    np.testing.assert_allclose(P_w[0], 1.5 * np.eye(6))
    # 0.1 s past the newest: the last step once more (the rotation's in the body, the translation's in the world, as interpolated)
    T_next, P_next = w.at(np.array([0.4]))
    np.testing.assert_allclose(T_next[0, :3, :3], T[3, :3, :3] @ T[2, :3, :3].T @ T[3, :3, :3], atol=1e-12)
    np.testing.assert_allclose(T_next[0, :3, 3], 2 * T[3, :3, 3] - T[2, :3, 3], atol=1e-12)
    np.testing.assert_array_equal(P_next[0], P[3])


# --- bad input while live --------------------------------------------------------------------


def _scan_counts(pipeline):
    return pipeline.map.counters["scans"], pipeline.map.counters["returns"]


def test_a_scan_with_infinite_or_nan_ranges_is_thinned_with_a_warning_and_the_map_goes_on(smoke_log, clean_live, caplog):
    events = list(smoke_log.events())
    scans = [i for i, e in enumerate(events) if isinstance(e, LaserScan)]
    k = scans[len(scans) // 2]
    bad = events[k]
    r = np.array(bad.ranges_m, dtype=float)
    r[::2] = np.inf
    r[1::4] = np.nan
    events[k] = LaserScan(bad.t_s, r, bad.index)
    log = smoke_log.replace_events(events)
    with caplog.at_level(logging.WARNING):
        pipeline, updates = _live(log)
    assert len(updates) == len(_frames(log))
    assert any(f"laser scan {bad.index}" in m and "infinite" in m for m in caplog.messages)
    assert pipeline.counters["scans_nonfinite"] == 1
    # the finite beams of the scan went in, the others did not
    valid = np.isfinite(r) & (r >= log.rig.laser.range_min_m) & (r <= log.rig.laser.range_max_m)
    clean, _ = clean_live
    valid_clean = np.isfinite(bad.ranges_m) & (bad.ranges_m >= log.rig.laser.range_min_m) & (bad.ranges_m <= log.rig.laser.range_max_m)
    assert _scan_counts(pipeline)[1] == _scan_counts(clean)[1] - int(valid_clean.sum()) + int(valid.sum())


def test_events_older_than_the_last_of_their_kind_are_skipped_with_a_warning(smoke_log, clean_live, caplog):
    events = list(smoke_log.events())
    frames = [i for i, e in enumerate(events) if isinstance(e, CameraFrame)]
    scans = [i for i, e in enumerate(events) if isinstance(e, LaserScan)]
    odometry = [i for i, e in enumerate(events) if isinstance(e, Odometry)]
    at = frames[30]
    old = [events[frames[10]], events[scans[3]], events[odometry[5]]]
    log = smoke_log.replace_events([*events[:at], *old, *events[at:]])
    with caplog.at_level(logging.WARNING):
        pipeline, updates = _live(log)
    clean, clean_updates = clean_live
    assert pipeline.counters["events_out_of_order"] == 3
    assert sum("is not after the last one" in m for m in caplog.messages) == 3
    # skipped, not used: the same frames, the same poses and the same map as without them
    assert [u.t_s for u in updates] == [u.t_s for u in clean_updates]
    np.testing.assert_array_equal(updates[-1].T_world_body, clean_updates[-1].T_world_body)
    assert _scan_counts(pipeline) == _scan_counts(clean)


def test_a_camera_silent_for_a_second_is_bridged_and_the_map_grows_meanwhile(smoke_log, caplog):
    events = list(smoke_log.events())
    t0 = smoke_log.t_start_s
    gap = (t0 + 0.8, t0 + 2.0)
    kept = [e for e in events if not (isinstance(e, CameraFrame) and gap[0] < e.t_s < gap[1])]
    log = smoke_log.replace_events(kept)
    seen = []
    c = RunConfig(estimator="ptpm")
    pipeline = LivePipeline.for_sequence(log, c)
    with caplog.at_level(logging.WARNING):
        for e in log.events():
            update = pipeline.on_event(e)
            if update is not None:
                seen.append(update)
            if isinstance(e, LaserScan) and gap[0] < e.t_s < gap[1]:
                seen.append(("scan", pipeline.map.counters["returns"]))
        pipeline.finish()
    assert any("no camera frame for" in m for m in caplog.messages)
    grown = [n for x, n in (s for s in seen if isinstance(s, tuple))]
    assert len(grown) >= 5 and grown[-1] > grown[0]  # scans went into the map while no frame came
    frames_after = [u for u in seen if not isinstance(u, tuple) and u.t_s > gap[1]]
    assert frames_after, "updates resume after the silence"
    # bridged: the first pose after the gap within 10 cm of the truth
    u = frames_after[0]
    truth = log.ground_truth.trajectory.at(u.t_s)
    assert np.linalg.norm(u.T_world_body[:3, 3] - truth[:3, 3]) < 0.10


def test_no_laser_for_two_seconds_is_warned_once_and_the_map_ages(smoke_log, caplog):
    events = list(smoke_log.events())
    t0 = smoke_log.t_start_s
    gap_start = t0 + 0.3
    kept = [e for e in events if not (isinstance(e, LaserScan) and e.t_s > gap_start)]  # the laser stops at 0.3 s
    log = smoke_log.replace_events(kept)
    with caplog.at_level(logging.WARNING):
        pipeline, updates = _live(log, dem={"map_points": False})  # laser returns only: nothing else refreshes a cell
    assert len(updates) == len(_frames(log))
    assert sum("no laser scan with a return for" in m for m in caplog.messages) == 1
    assert pipeline.counters["laser_silences"] == 1
    last = updates[-1]
    assert last.t_s - gap_start > 2.0
    # 3 m further on, nothing was measured ahead: the guidance sees unknown cells, not invented ones
    assert not np.isfinite(last.local.elevation).any()
    # the map kept what it had, every cell last measured before the laser stopped
    dem = pipeline.map.global_dem()
    assert dem.covered.sum() > 100
    assert np.nanmax(dem.layers["last_update_s"]) <= gap_start


def test_a_run_reports_the_live_fig8_next_to_the_hindsight_one(smoke_run):
    run = smoke_run({"estimator": "ptpm"})  # run_estimator(smoke_log, RunConfig(estimator="ptpm")), made once in the session
    live, hindsight = run.metrics.live_map.local_window, run.metrics.dem.local_window
    assert live.frames == hindsight.frames and live.frames_with_data > 0
    # both measure the same kind of map over the same window: within 2 cm of each other on smoke
    assert abs(live.mean_of_mean_m - hindsight.mean_of_mean_m) < 0.02
    assert live.mean_of_std_m == pytest.approx(hindsight.mean_of_std_m, abs=0.02)


def test_a_recorded_run_loads_back_with_one_image_and_one_local_map_per_frame(smoke_log, tmp_path):
    pytest.importorskip("rerun")
    from dem_graph.pipeline.live_view import ViewerOptions
    from dem_graph.viz.rerun_viewer import recording_rows

    path = tmp_path / "smoke.rrd"
    run = run_estimator(smoke_log, RunConfig(estimator="ptpm", max_frames=30), with_dem=False, viewer=ViewerOptions(record_path=path))
    frames = len(run.estimator.frames)
    assert frames == 30
    rows = recording_rows(path)
    assert rows["/camera/image"] == frames
    assert rows["/local_map/height"] == frames
    assert rows["/world/vehicle"] == frames
    assert rows["/world/truth"] == 1
    # the laser and camera points searched, in two entities, on the frames that tracked any
    assert 0 < rows["/camera/image/laser_points"] <= frames and rows["/camera/image/camera_points"] == rows["/camera/image/laser_points"]


def test_the_height_image_puts_ahead_up_and_left_on_the_left():
    from dem_graph.viz.rerun_viewer import height_image

    z = np.full((4, 6), np.nan)  # rows: left to right across the heading (y from +), columns: near to far
    z[0, 5] = 0.3  # far left
    rgb = height_image(z, (-0.3, 0.3))
    assert rgb.shape == (6, 4, 3)
    assert np.all(rgb[0, 0] > 0) and np.all(rgb[1:, :] == 0) and np.all(rgb[0, 1:] == 0)


def test_driver_callbacks_and_a_guidance_reading_at_its_own_rate(smoke_log):
    """The README's "On a vehicle": callbacks build the events; the guidance reads the map between frames."""
    from dem_graph.pipeline.live import LivePipeline

    live = LivePipeline(smoke_log.rig, smoke_log.T_world_body_initial, smoke_log.t_start_s, has_odometry=True, config=RunConfig(estimator="ptpm"))
    with pytest.raises(Exception, match="no frame yet"):
        live.local_map((1.0, 4.0), 1.5)
    reads = []
    for e in smoke_log.events():
        if isinstance(e, CameraFrame):
            update = live.on_frame(CameraFrame(e.t_s, e.image))
        elif isinstance(e, LaserScan):
            update = live.on_scan(LaserScan(e.t_s, e.ranges_m))
        elif isinstance(e, Odometry):
            update = live.on_odometry(Odometry(e.t_s, e.t_prev_s, e.T_prev_curr, e.covariance))
        else:
            update = live.on_event(e)
        if update is not None and update.frame % 4 == 0:  # the guidance at a quarter of the camera's rate
            g = update.local.geometry
            x0, x1 = g.x_min_m, g.x_min_m + (g.n_cols - 0.5) * g.resolution_m  # the update's window (half a cell in: no rounding up)
            reads.append((live.local_map((x0, x1), g.y_max_m), update.local))
    assert len(reads) >= 10
    for got, want in reads:
        np.testing.assert_array_equal(got.elevation, want.elevation)  # read at once: the map the update gave


def test_the_map_is_saved_at_any_time_and_reads_back(smoke_log, tmp_path):
    from dem_graph.io.geotiff import read_elevation_geotiff

    live = LivePipeline.for_sequence(smoke_log, RunConfig(estimator="gm"))
    saved = []
    for e in smoke_log.events():
        update = live.on_event(e)
        if update is not None and update.frame in (20, 40):
            saved.append((live.save_map(tmp_path / f"map_{update.frame}.tif"), live.map.global_dem()))
    for path, dem in saved:
        geometry, bands = read_elevation_geotiff(path)
        assert geometry == dem.geometry
        z = bands["elevation"]
        np.testing.assert_array_equal(np.isfinite(z), dem.covered)
        np.testing.assert_allclose(z[dem.covered], dem.elevation[dem.covered])
        np.testing.assert_array_equal(bands["count"], dem.layers["count"])
    assert saved[1][1].covered.sum() > saved[0][1].covered.sum()  # the map grew between the two saves


def test_a_failing_listener_is_dropped_with_an_error_and_the_map_goes_on(smoke_log, caplog):
    live = LivePipeline.for_sequence(smoke_log, RunConfig(estimator="gm"))
    calls = []

    def broken(update):
        calls.append(update.frame)
        raise RuntimeError("the display went away")

    live.listeners.append(broken)
    with caplog.at_level(logging.ERROR):
        updates = [u for u in (live.on_event(e) for e in smoke_log.events()) if u is not None]
    assert calls == [1]
    assert len(updates) == len(_frames(smoke_log))
    assert sum("the display went away" in m and "the map goes on" in m for m in caplog.messages) == 1


def _silences(caplog) -> list[str]:
    return [m for m in caplog.messages if " for " in m and " s (since " in m]


def test_a_camera_that_stops_for_good_is_warned_once_by_the_other_streams(smoke_log, caplog):
    t_stop = smoke_log.t_start_s + 0.5
    log = smoke_log.replace_events([e for e in smoke_log.events() if not (isinstance(e, CameraFrame) and e.t_s > t_stop)])
    last_frame = max(e.t_s for e in _frames(log))
    with caplog.at_level(logging.WARNING):
        pipeline, _ = _live(log, estimator="gm")
    camera = [m for m in _silences(caplog) if m.startswith("no camera frame for")]
    assert len(camera) == 1 and f"(since {last_frame:.3f} s)" in camera[0]
    assert pipeline.counters["camera_silences"] == 1


def test_scans_without_a_return_count_as_a_silent_laser(smoke_log, caplog):
    t_nan = smoke_log.t_start_s + 0.3
    events = [LaserScan(e.t_s, np.full_like(e.ranges_m, np.nan), e.index) if isinstance(e, LaserScan) and e.t_s > t_nan else e for e in smoke_log.events()]
    log = smoke_log.replace_events(events)
    n_empty = sum(isinstance(e, LaserScan) and e.t_s > t_nan for e in events)
    with caplog.at_level(logging.WARNING):
        pipeline, _ = _live(log, estimator="gm")
    assert sum(m.startswith("no laser scan with a return for") for m in _silences(caplog)) == 1
    assert pipeline.counters["scans_without_return"] == n_empty and pipeline.counters["laser_silences"] == 1


def test_an_odometry_gap_is_warned_when_found_and_when_it_ends(smoke_log, caplog):
    t0 = smoke_log.t_start_s
    gap = (t0 + 0.5, t0 + 1.5)
    log = smoke_log.replace_events([e for e in smoke_log.events() if not (isinstance(e, Odometry) and gap[0] <= e.t_s < gap[1])])
    last_before = max(e.t_s for e in log.events() if isinstance(e, Odometry) and e.t_s < gap[0])
    first_after = min(e.t_s for e in log.events() if isinstance(e, Odometry) and e.t_s >= gap[1])
    with caplog.at_level(logging.WARNING):
        pipeline, _ = _live(log, estimator="gm")
    found = [m for m in _silences(caplog) if m.startswith("no odometry for")]
    assert len(found) == 1 and f"(since {last_before:.3f} s)" in found[0]
    assert any(m.startswith(f"odometry again at {first_after:.3f} s, after {first_after - last_before:.2f} s") for m in caplog.messages)
    assert pipeline.counters["odometry_silences"] == 1
