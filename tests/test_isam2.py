"""The graph estimator (isam2, isam2-batch) end to end on simulated logs, against the simulator's truth."""

from __future__ import annotations

import numpy as np
import pytest

from dem_graph.datasets.events import CameraFrame, LaserScan, Odometry
from dem_graph.datasets.memory import InMemorySequence
from dem_graph.estimators.base import ONLINE_TRAJECTORY
from dem_graph.estimators.isam2 import Isam2Config, Isam2Slam
from dem_graph.frontend.frontend import FrontEnd
from dem_graph.frontend.tracker import TrackBatch
from dem_graph.geometry.lie import so3_log
from dem_graph.geometry.se3 import invert, transform_points
from dem_graph.pipeline import RunConfig, RunOverrides, run_config, run_estimator
from dem_graph.sim.scenarios import scenario
from dem_graph.sim.simulator import SimulatedSequence


def _run(log, estimator="isam2", **overrides):
    return run_estimator(log, RunConfig.model_validate({"estimator": estimator, **overrides}))


@pytest.fixture(scope="module")
def isam2_run(smoke_run):
    """``_run(smoke_log)``, made once in the session (other files check the same run)."""
    return smoke_run({"estimator": "isam2"})


# --- exactness ---------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def noiseless_flat_log() -> InMemorySequence:
    """`smoke` on flat ground (the flat-ground prior is true) with every sensor noiseless, and no IMU."""
    cfg = scenario("smoke", seed=3)
    rig = cfg.rig
    odo = rig.odometry.model_copy(
        update=dict(sigma_scale=0.0, sigma_forward_m_per_sqrt_m=0.0, sigma_lateral_m_per_sqrt_m=0.0, sigma_vertical_m_per_sqrt_m=0.0, sigma_yaw_rad_per_sqrt_m=0.0, sigma_roll_pitch_rad_per_sqrt_m=0.0)
    )
    rig = rig.model_copy(update=dict(camera=rig.camera.model_copy(update=dict(noise_sigma_dn=0.0)), laser=rig.laser.model_copy(update=dict(range_sigma_m=0.0)), odometry=odo))
    cfg = cfg.model_copy(update=dict(rig=rig, terrain=cfg.terrain.model_copy(update=dict(kind="flat")), with_imu=False))
    return InMemorySequence.record(SimulatedSequence.from_config(cfg))


class OracleTracker:
    """Replaces patch matching by the true projection: a point is the ground (z = 0) under the pixel
    its patch was cut at, seen from the true camera pose of that moment."""

    def __init__(self, log: InMemorySequence):
        self.gt = log.ground_truth.trajectory
        self.camera = log.rig.camera_model
        self.T_body_cam = log.rig.T_body_cam
        self.truth: dict[int, np.ndarray] = {}
        self._T_world_cam: dict[float, np.ndarray] = {}

    def T_world_cam(self, t_s: float) -> np.ndarray:
        """The true camera pose at ``t_s`` (interpolated once per time: a frame asks for it for every point)."""
        if t_s not in self._T_world_cam:
            self._T_world_cam[t_s] = self.gt.at(np.array([t_s]))[0] @ self.T_body_cam
        return self._T_world_cam[t_s]

    def __call__(self, frontend, image, point_ids, templates, uv_pred, S_px2=None, half_size_px=None, t_s=0.0, T_world_cam=None):
        """In place of ``FrontEnd.track_many``: every point found at its true pixel."""
        ids = np.asarray(point_ids).tolist()
        for point_id in ids:
            track = frontend.tracks[point_id]
            if point_id not in self.truth:
                T_wc = self.T_world_cam(track.created_t_s)
                d = T_wc[:3, :3] @ self.camera.bearings_from_pixels(np.asarray(track.patch.center_px, dtype=float)[None])[0]
                o = T_wc[:3, 3]
                self.truth[point_id] = o - d * o[2] / d[2]
            track.misses = 0
            track.n_tracked += 1
        n = len(ids)
        uv_all = np.zeros((n, 2))
        if n:
            T_cam_world = invert(self.T_world_cam(t_s))
            uv_all[:] = self.camera.project(transform_points(T_cam_world, np.array([self.truth[p] for p in ids])))[0]
        return TrackBatch(np.zeros(n, dtype=np.int8), uv_all, np.ones(n), np.full(n, np.nan), np.full((n, 2), 3, dtype=np.int64))


@pytest.mark.parametrize("estimator", ["isam2", "isam2-batch"])
def test_noiseless_flat_ground_recovers_poses_and_points_to_1mm(noiseless_flat_log, monkeypatch, estimator):
    """Noiseless sensors, exact pixels, flat ground: every frame's pose and every point to 1 mm.
    Measured (isam2): poses within 0.2 mm and 0.005 deg, points within 0.4 mm."""
    oracle = OracleTracker(noiseless_flat_log)
    monkeypatch.setattr(FrontEnd, "track_many", lambda self, *a, **k: oracle(self, *a, **k))
    run = _run(noiseless_flat_log, estimator)
    res = run.estimator
    assert run.error is None and len(res.frames) == 65
    t = np.array([f.t_s for f in res.frames])
    est = np.array([f.T_world_body for f in res.frames])
    truth = oracle.gt.at(t)
    assert np.max(np.linalg.norm(est[:, :3, 3] - truth[:, :3, 3], axis=1)) < 1e-3
    assert np.degrees(max(np.linalg.norm(so3_log(a[:3, :3].T @ b[:3, :3])) for a, b in zip(est, truth))) < 0.02  # 1 mm at 3 m
    pts = res.points.arrays()
    errors = [np.linalg.norm(x - oracle.truth[p]) for p, x in zip(pts["point_id"], pts["xyz"]) if p in oracle.truth]
    assert len(errors) > 200
    assert max(errors) < 1e-3


# --- accuracy and outputs ----------------------------------------------------------------------


def test_accuracy_with_odometry(isam2_run):
    m = isam2_run.metrics
    assert isam2_run.error is None and m.frames == 65
    # the EKF's goals on the same log (test_ekf_run): drift below 1 %, ATE below 3 cm
    assert m.trajectory.drift_percent < 1.0
    assert m.trajectory.ate_rmse_m < 0.03
    assert m.points_per_frame.tracked_median > 80
    # the trajectory smoothed at the end is written next to the per-frame one, as accurate
    assert m.trajectory_smoothed.ate_rmse_m < 0.03


def test_keyframes_and_window_stay_bounded(smoke_log):
    """Keyframes every `keyframe_every` frames (or sooner when the map runs short), and the smoother
    holds no variable older than the lag: its size does not grow with the run."""
    config = Isam2Config(lag_s=0.5, keyframe_every=4, keyframe_min_live_fraction=0.0)
    est = Isam2Slam(smoke_log.rig, smoke_log.T_world_body_initial, smoke_log.t_start_s, True, config)
    window = []
    for e in smoke_log.events():
        if isinstance(e, CameraFrame):
            est.on_frame(e)
            stamps = est.graph.timestamps()
            window.append(len(stamps))
            newest = max(stamps.values())
            # cut back to the lag at the first frame after it spans lag + marginalize_every
            assert min(stamps.values()) >= newest - config.lag_s - config.marginalize_every_s - config.keyframe_every / 25.0 - 1e-9
        elif isinstance(e, LaserScan):
            est.on_scan(e)
        elif isinstance(e, Odometry):
            est.on_odometry(e)
    est.finish()
    # 65 frames, a keyframe every 4 (the first frame is keyframe 0 itself)
    assert len(est.graph.keyframe_t_s) == 1 + 64 // 4
    # at most lag / keyframe period + 1 poses and the points seen in that time
    assert max(window[32:]) <= max(window[:32]) * 1.5


@pytest.mark.parametrize("every", [2, 3])
def test_landmarks_take_turns_in_the_graph(smoke_log, monkeypatch, every):
    """``observation_every`` n: a landmark's observation reaches the graph at every n-th keyframe
    only (landmark + keyframe divisible by n), and stands for the frames since its last one
    (``sigma_px / sqrt(frames)``, so a landmark tracked throughout carries sigma_px / sqrt(n)). The
    graph then holds about 1/n of the projection factors, and the run stays within the goals of
    every observation (drift under 1 %, ATE under 3 cm on `smoke`). (A new point's first turn may
    come after fewer frames: it carries those, sigma_px at most.)"""
    from dem_graph.estimators.graph_worker import InProcessGraph, KeyframeMessage

    messages = []
    real_send = InProcessGraph.send
    monkeypatch.setattr(InProcessGraph, "send", lambda self, m: (messages.append(m), real_send(self, m))[1])
    run = _run(smoke_log, isam2={"observation_every": every})
    keyframes = [m for m in messages if isinstance(m, KeyframeMessage) and len(m.landmarks)]
    assert keyframes and all(np.all((m.landmarks + m.k) % every == 0) for m in keyframes)
    sigma = np.concatenate([m.sigma_px for m in keyframes[3:]])
    sigma_px = run.config.frontend.sigma_px
    assert np.all(sigma <= sigma_px + 1e-12)
    assert np.median(sigma) == pytest.approx(sigma_px / np.sqrt(every))
    m = run.metrics
    assert m.trajectory.drift_percent < 1.0 and m.trajectory.ate_rmse_m < 0.03


def test_constant_velocity_without_odometry(smoke_log):
    run = _run(smoke_log, motion={"model": "constant_velocity", "initial_speed_mps": 1.5})
    assert run.error is None and run.metrics.frames == 65
    # the EKF's goal without odometry: drift below 3 %
    assert run.metrics.trajectory.drift_percent < 3.0


def test_wrong_matches_barely_move_the_estimate(smoke_log, smoke_run):
    """10 % of matches replaced by ones 12 px away: the gate and the outlier test drop them, the
    Huber kernel bounds what gets through; the ATE grows by less than 20 % (the issue's bound;
    measured 5.73 against 6.66 mm). Both runs ignore the IMU: with it the ATE is 2 mm, where 20 % is
    below the spread the choice of tracked points alone gives (2.68 against 2.07 mm)."""
    clean = smoke_run({"estimator": "isam2", "motion": {"use_imu": False}})  # _run(smoke_log, motion=...), made once in the session
    run = _run(smoke_log, false_matches={"fraction": 0.1, "offset_px": 12.0}, motion={"use_imu": False})
    ev = run.metrics.events
    assert ev["injected"] > 300
    assert run.metrics.trajectory.ate_rmse_m < 1.2 * clean.metrics.trajectory.ate_rmse_m


# --- degenerate input --------------------------------------------------------------------------


def _edit(log, frame=None, scan=None):
    events = []
    for e in log.events():
        if isinstance(e, CameraFrame) and frame is not None:
            e = frame(e)
        elif isinstance(e, LaserScan) and scan is not None:
            e = scan(e)
        if e is not None:
            events.append(e)
    return log.replace_events(events)


def test_frames_with_nothing_trackable(smoke_log):
    """Five uniform frames: no point can be matched; the pose rides on odometry and the run goes on."""
    log = _edit(smoke_log, frame=lambda e: CameraFrame(e.t_s, np.full_like(e.image, 40), e.index) if 20 <= e.index < 25 else e)
    run = _run(log)
    frames = run.estimator.frames
    assert run.error is None and len(frames) == 65
    assert all(f.n_tracked == 0 for f in frames[20:25])
    assert run.metrics.trajectory.drift_percent < 2.0


def test_camera_blackout_of_a_second(smoke_log):
    """No frame for 1 s (25 frames), longer than the lag: the pose rides on odometry across the gap,
    the points marginalised meanwhile are dropped, tracking resumes, and the error the gap left is
    within the uncertainty the estimator reports for it."""
    log = _edit(smoke_log, frame=lambda e: None if 20 <= e.index < 45 else e)
    run = _run(log, isam2={"lag_s": 0.8})
    frames = run.estimator.frames
    assert run.error is None and len(frames) == 40
    assert frames[22].n_tracked > 50 and frames[-1].n_tracked > 50
    after = frames[20]
    error = after.T_world_body[:3, 3] - smoke_log.ground_truth.trajectory.at(np.array([after.t_s]))[0, :3, 3]
    P_xyz = after.T_world_body[:3, :3] @ after.pose_covariance[3:, 3:] @ after.T_world_body[:3, :3].T  # body -> world axes
    assert error @ np.linalg.solve(P_xyz, error) < 14.2  # chi-square(3) at 99.7 %


def test_laser_gap(smoke_log):
    """No scan for 1 s: only camera points enter; the run goes on with its accuracy."""
    log = _edit(smoke_log, scan=lambda e: None if 0.6 <= e.t_s < 1.6 else e)
    run = _run(log)
    assert run.error is None and run.metrics.frames == 65
    assert run.metrics.trajectory.drift_percent < 1.0


# --- batch -------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def batch_run(smoke_log):
    """isam2-batch on `smoke`, and the arguments its batch smoothing was called with (the real
    smoothing runs: the run is the one without the spy)."""
    from dem_graph.estimators import batch, batch_log

    seen = {}

    def keep_inputs(*args, **kwargs):
        seen.update(args=args, kwargs=kwargs)
        return batch.smooth_batch(*args, **kwargs)

    mp = pytest.MonkeyPatch()
    mp.setattr(batch_log, "smooth_batch", keep_inputs)
    try:
        run = _run(smoke_log, "isam2-batch")
    finally:
        mp.undo()
    return run, seen


def test_batch_smooths_every_observation(batch_run):
    run, _ = batch_run
    m = run.metrics
    assert run.error is None and m.frames == 65
    ev = m.events
    # the online pass makes a keyframe every 5 frames, or sooner when the map runs short of points: on
    # this short log points leave the view fast and it made 46 keyframes of 65 frames (isam2: 65)
    assert Isam2Config(batch=True).keyframe_spacing == 5 and Isam2Config().keyframe_spacing == 1
    assert ev["keyframes"] < 65
    # yet the batch has one projection factor per inlier observation of every frame, not only the keyframes'
    assert ev["batch_factors"] > ev["track_ok"] - ev.get("outlier_rejected", 0)
    # the EKF's goals on this log (test_ekf_run), as for isam2
    assert m.trajectory.drift_percent < 1.0
    assert m.trajectory.ate_rmse_m < 0.03


def test_batch_online_pass_beside_its_graph_is_reproducible(smoke_log):
    """``batch_graph_delay_keyframes: 1``: the batch's online pass has its graph in a second
    process, each result handed back one keyframe late; the run is the one with the graph in this
    process and that delay, to the last bit, online pass and batch alike."""
    assert Isam2Config(batch=True).graph_placement == (False, 0)
    assert Isam2Config(batch=True, batch_graph_delay_keyframes=1).graph_placement == (True, 1)
    assert Isam2Config(batch=True, batch_graph_delay_keyframes=1, graph_process=True).graph_placement == (True, 0)
    run = _run(smoke_log, "isam2-batch", isam2={"batch_graph_delay_keyframes": 1})
    here = _run(smoke_log, "isam2-batch", isam2={"graph_delay_keyframes": 1})
    assert run.error is None and here.error is None
    np.testing.assert_array_equal(run.estimator.extra_poses[ONLINE_TRAJECTORY], here.estimator.extra_poses[ONLINE_TRAJECTORY])
    np.testing.assert_array_equal([f.T_world_body for f in run.estimator.frames], [f.T_world_body for f in here.estimator.frames])
    assert run.metrics.events["graph_lag_keyframes_median"] == 1 == run.metrics.events["graph_lag_keyframes_max"]


def test_batch_fits_the_landmarks_to_the_poses_before_smoothing(smoke_log, batch_run):
    """The online pass's landmarks need not agree with its final poses: each is the graph's estimate
    from when it was last updated. Started with every landmark 1 m off (random directions), the
    first pass (the landmarks fitted with the poses held) removes most of the start's error, and
    the batch ends on the truth. On this short log Levenberg-Marquardt also gets there without that
    pass (measured: the same 6.7 mm ATE); on `paper` seed 6 (100 m, 244 000 factors) it did not:
    it stopped after one iteration at an error of 4.2e6, 3 m low at the end, and with the first
    pass it reaches 3.0e4, 0.38 m high (docs/isam2_design.md)."""
    from dem_graph.estimators import batch

    run, seen = batch_run
    assert run.error is None
    mlog, rig, T0, P0, poses, points, *rest = seen["args"]
    rng = np.random.default_rng(0)
    off = rng.normal(size=(len(points), 3))
    off *= 1.0 / np.linalg.norm(off, axis=1, keepdims=True)
    moved = {lm: np.asarray(x) + d for (lm, x), d in zip(points.items(), off)}
    t = np.array([f.t_s for f in run.estimator.frames])
    truth = smoke_log.ground_truth.trajectory.at(t)[:, :3, 3]

    def ate_m(result) -> float:
        return float(np.sqrt(np.mean(np.sum((result.poses[:, :3, 3] - truth) ** 2, axis=1))))

    fitted = batch.smooth_batch(mlog, rig, T0, P0, poses, moved, *rest, **seen["kwargs"])
    assert fitted.refit_iterations > 0 and fitted.error_refit < 0.01 * fitted.error_initial
    assert ate_m(fitted) < 0.03  # the goal of test_batch_smooths_every_observation


def test_batch_online_pass_is_the_online_estimator_at_its_spacing(smoke_log, isam2_run):
    # with the online estimator's keyframe spacing, the batch's online pass is that estimator, to the bit
    run = _run(smoke_log, "isam2-batch", isam2={"batch_keyframe_every": 1})
    assert run.metrics.trajectory_online.ate_rmse_m == pytest.approx(isam2_run.metrics.trajectory.ate_rmse_m, rel=1e-9)
    # --keyframe-every sets the spacing of the run's own estimator only
    assert run_config(overrides=RunOverrides(estimator="isam2-batch", keyframe_every=3)).isam2.batch_keyframe_every == 3
    assert run_config(overrides=RunOverrides(estimator="isam2-batch", keyframe_every=3)).isam2.keyframe_every is None
    assert run_config(overrides=RunOverrides(estimator="isam2", keyframe_every=3)).isam2.keyframe_every == 3


def test_a_failed_graph_update_restarts_the_smoother(smoke_log, monkeypatch):
    """gtsam refusing an update (as for an indeterminate system) at one keyframe: the estimator
    logs it, starts a new smoother from its current estimates and goes on to the goals above."""
    from dem_graph.estimators import keyframe_graph

    real = keyframe_graph.KeyframeGraph.update
    calls = {"n": 0}

    def failing_once(self, iterations=1):
        calls["n"] += 1
        if calls["n"] == 8:
            self._new_factors = keyframe_graph.gtsam.NonlinearFactorGraph()
            raise keyframe_graph.GraphUpdateError("the graph update at keyframe 7 failed: Indeterminant linear system")
        return real(self, iterations)

    monkeypatch.setattr(keyframe_graph.KeyframeGraph, "update", failing_once)
    run = _run(smoke_log)
    assert run.error is None and run.metrics.frames == 65
    assert run.metrics.events["graph_restarts"] == 1
    assert run.metrics.trajectory.drift_percent < 1.0


def test_search_regions_match_the_smoothers_marginals(smoke_log):
    """The approximate search regions (pose relative to the map + each point's own covariance)
    against the exact ones from the smoother's joint marginal of the keyframe pose and the point.
    Measured on this log (every frame a keyframe, 640 points): 66 % contained outright, the exact
    region sticking out by 0.5 % in sigma at the 95th percentile (1.010 in variance), 0.9 % at
    worst; area ratio median 1.006."""
    from dem_graph.studies.search_regions import search_region_study

    s = search_region_study(smoke_log, every_keyframes=2).summary()
    assert s["points"] > 200
    assert s["containment_p95"] < 1.05**2  # at most 5 % of sigma outside, for 95 % of points
    assert 0.9 < s["area_ratio_median"] < 1.2  # and not searching much more than needed


def test_effective_sample_size_of_correlated_frames():
    """n consecutive AR(1) errors with lag-1 correlation rho: the variance of their mean is
    sigma^2 (1 + 2 sum_k (1 - k/n) rho^k) / n; without correlation n frames are n samples, and for
    long runs the ratio tends to (1 - rho) / (1 + rho)."""
    from dem_graph.estimators.online_filter import effective_sample_size

    np.testing.assert_allclose(effective_sample_size(np.array([1, 3, 7]), 0.0), [1, 3, 7])
    np.testing.assert_allclose(effective_sample_size(np.array([1]), 0.6), [1.0])
    np.testing.assert_allclose(effective_sample_size(np.array([3]), 0.6), [3 / (1 + 2 * (2 / 3 * 0.6 + 1 / 3 * 0.36))])
    n = 2000
    assert effective_sample_size(np.array([n]), 0.6)[0] / n == pytest.approx(0.4 / 1.6, rel=2e-3)
    # and the same from simulated AR(1) errors: the variance of the mean of 5 frames
    rng = np.random.default_rng(0)
    e = np.zeros((20000, 5))
    e[:, 0] = rng.standard_normal(20000)
    for k in range(1, 5):
        e[:, k] = 0.6 * e[:, k - 1] + np.sqrt(1 - 0.36) * rng.standard_normal(20000)
    assert 1.0 / np.var(e.mean(axis=1)) == pytest.approx(effective_sample_size(np.array([5]), 0.6)[0], rel=0.03)


def test_a_landmark_bound_keeps_the_graph_small_and_the_rest_in_the_front_end(smoke_log, monkeypatch):
    """``graph_max_landmarks`` n: no keyframe sends the graph observations of more than n landmarks,
    and the new points beyond the bound are the front end's own (each updated with the pose held
    fixed, moved with the graph's corrections, never a variable of the graph). The run keeps the
    goals of every estimator on `smoke` (drift under 1 %, ATE under 3 cm), and the front end's own
    points lie on the simulator's terrain as the graph's do: height RMSE under 3 cm, the DEM's goal."""
    from dem_graph.estimators.graph_worker import InProcessGraph, KeyframeMessage

    bound = 30
    messages, own_ids = [], []
    real_send, real_keep = InProcessGraph.send, Isam2Slam._keep_in_front_end
    monkeypatch.setattr(InProcessGraph, "send", lambda self, m: (messages.append(m), real_send(self, m))[1])
    monkeypatch.setattr(Isam2Slam, "_keep_in_front_end", lambda self, new: (own_ids.extend(p.point_id for p in new), real_keep(self, new))[1])
    run = _run(smoke_log, isam2={"graph_max_landmarks": bound})
    keyframes = [m for m in messages if isinstance(m, KeyframeMessage)]
    assert max(len(set(m.landmarks.tolist())) for m in keyframes) <= bound
    assert all(np.all(m.landmarks >= 0) for m in keyframes)
    assert run.metrics.events["points_front_end_only"] == len(own_ids) > 100
    m = run.metrics
    assert m.trajectory.drift_percent < 1.0 and m.trajectory.ate_rmse_m < 0.03
    terrain = smoke_log.ground_truth.elevation
    pts = run.estimator.points
    xyz = np.array(pts.xyz)
    dz = xyz[:, 2] - terrain.height_at(xyz[:, 0], xyz[:, 1])
    own = np.isin(pts.point_id, own_ids)
    assert own.sum() > 100 and (~own).sum() > 100
    assert np.sqrt(np.nanmean(dz[own] ** 2)) < 0.03
    assert np.sqrt(np.nanmean(dz[~own] ** 2)) < 0.03


def test_the_vehicles_graph_spaces_its_keyframes_by_its_landmarks():
    """On the vehicle (the graph in a second process, results when ready) every live point is a
    landmark and the keyframes are spaced so that the graph takes at most
    ``graph_landmarks_per_frame`` landmark observations a frame: ceil(live / per frame) frames, with
    room to run 3 keyframes ahead per frame of spacing. Everywhere else the spacing is the set one,
    or 1."""
    vehicle = Isam2Config(graph_process=True)
    assert vehicle.graph_landmark_budget is None
    assert [vehicle.keyframe_spacing_for(n) for n in (0, 150, 250, 251, 486, 500, 751)] == [1, 1, 1, 2, 2, 2, 4]
    assert [vehicle.graph_lag_limit(s) for s in (1, 2, 4)] == [3, 6, 12]
    assert vehicle.keyframe_spacing == 1  # the most at the default 150 live points: the default vehicle run keeps a keyframe every frame
    assert Isam2Config(graph_process=True, frontend={"max_points": 500}).keyframe_spacing == 2
    assert Isam2Config(graph_process=True, graph_landmarks_per_frame=100).keyframe_spacing_for(486) == 5
    assert Isam2Config(graph_process=True, graph_max_landmarks=200).keyframe_spacing_for(486) == 1  # the bound's landmarks only
    assert Isam2Config(graph_process=True, graph_max_lag=4).graph_lag_limit(2) == 4
    assert Isam2Config(graph_process=True, keyframe_every=3).keyframe_spacing_for(100) == 3
    # in this process, at a fixed delay, and in the batch's online pass the spacing does not follow the points
    assert Isam2Config().keyframe_spacing_for(486) == 1
    assert Isam2Config(graph_process=True, graph_delay_keyframes=1).keyframe_spacing_for(486) == 1
    assert Isam2Config(batch=True, graph_process=True).keyframe_spacing_for(486) == 5
