"""Work done between frames in a run at the camera's rate: when it is done, and that it changes
nothing but when.

Truths: a clock of the test's own (every event's due time and every piece of work's cost set by
hand); the same log run as fast as possible, whose map and trajectory the idle run must give bit
for bit.
"""

from __future__ import annotations

import numpy as np
import pytest

from dem_graph.datasets.events import CameraFrame, ImuSample
from dem_graph.pipeline import run as run_module
from dem_graph.pipeline.config import RunConfig
from dem_graph.pipeline.live import LivePipeline
from dem_graph.pipeline.run import IDLE_MIN_WAIT_S, feed

FRAME_PERIOD_S, IMU_PERIOD_S = 0.040, 0.005
FRAME_COST_S, IMU_COST_S, IDLE_COST_S = 0.015, 0.0002, 0.004


class _Clock:
    """perf_counter and sleep of a wall clock that moves only when told."""

    def __init__(self):
        self.now_s = 100.0

    def perf_counter(self) -> float:
        return self.now_s

    def sleep(self, seconds: float) -> None:
        self.now_s += max(seconds, 0.0)


class _Log:
    def __init__(self, duration_s: float):
        frames = [CameraFrame(k * FRAME_PERIOD_S, np.zeros((2, 2), np.uint8), k) for k in range(int(duration_s / FRAME_PERIOD_S))]
        imu = [ImuSample(k * IMU_PERIOD_S + 0.001, np.zeros(3), np.zeros(3), k) for k in range(int(duration_s / IMU_PERIOD_S))]
        self._events = sorted(frames + imu, key=lambda e: e.t_s)

    def events(self):
        return iter(self._events)

    def event_count(self) -> int:
        return len(self._events)


class _Estimator:
    """Records when each event was handed over and when its idle work ran, on the test's clock."""

    name = "fake"

    def __init__(self, clock: _Clock):
        self.clock = clock
        self.handed: list[tuple[float, float, bool]] = []  # (the event's time, the clock when handed, a camera frame)
        self.idle_at: list[float] = []

    def _take(self, event, cost_s: float, frame: bool) -> None:
        self.handed.append((event.t_s, self.clock.now_s, frame))
        self.clock.now_s += cost_s

    def on_frame(self, event):
        self._take(event, FRAME_COST_S, True)

    def on_imu(self, event):
        self._take(event, IMU_COST_S, False)

    def idle(self) -> bool:
        self.idle_at.append(self.clock.now_s)
        self.clock.now_s += IDLE_COST_S
        return True

    def finish(self):
        pass


@pytest.fixture
def clock(monkeypatch) -> _Clock:
    c = _Clock()
    monkeypatch.setattr(run_module, "time", c)
    return c


def test_idle_work_runs_only_with_the_next_frame_far_enough_and_no_event_is_handed_early_or_frame_late(clock):
    est = _Estimator(clock)
    list(feed(est, _Log(2.0), realtime=True))
    wall0 = est.handed[0][1]
    due = np.array([t for t, _, _ in est.handed]) + wall0
    handed = np.array([w for _, w, _ in est.handed])
    frame = np.array([f for _, _, f in est.handed])
    assert np.all(handed >= due - 1e-12)  # never before its time
    np.testing.assert_allclose(handed[frame], due[frame], atol=1e-12)  # no frame made late by idle work
    # idle work only while the next camera frame (one interval after the last) was at least IDLE_MIN_WAIT_S away
    frame_t = np.array([t for t, _, f in est.handed if f])
    for at in est.idle_at:
        t_log = at - wall0
        last = frame_t[frame_t <= t_log + 1e-12]
        assert len(last) >= 2  # (the interval is known from the second frame on)
        assert last[-1] + FRAME_PERIOD_S - t_log >= IDLE_MIN_WAIT_S - 1e-12
    # and it came in every interval after the second frame: the frames leave 25 ms of each 40 free
    intervals = np.floor((np.array(est.idle_at) - wall0) / FRAME_PERIOD_S + 1e-9).astype(int)
    assert set(range(1, len(frame_t) - 1)) <= set(intervals.tolist())


def test_a_run_replayed_as_fast_as_possible_does_no_idle_work(clock):
    est = _Estimator(clock)
    list(feed(est, _Log(0.5), realtime=False))
    assert est.idle_at == []


def _run(log, realtime: bool, idle_after_frames: bool, n_frames: int, graph=None, estimator: str = "isam2", **isam2):
    """The pipeline over the log's first ``n_frames`` frames, ``idle()`` called after each frame's update
    (``idle_after_frames``); ``graph(client)`` may wrap the estimator's graph first; ``isam2``: its settings."""
    pipeline = LivePipeline.for_sequence(log, RunConfig(estimator=estimator, realtime=realtime, isam2=isam2))
    held = graph(pipeline.estimator._client) if graph is not None else None
    est, pipeline.took = pipeline.estimator, []
    est_idle = est.idle
    est.idle = lambda: pipeline.took.append(est_idle()) or pipeline.took[-1]
    frames = 0
    for e in log.events():
        update = pipeline.on_event(e)
        if update is not None:
            frames += 1
            if held is not None:
                held.release()
            if idle_after_frames:
                pipeline.idle()
        if frames >= n_frames and isinstance(e, CameraFrame):
            break
    pipeline.finish()
    return pipeline


def _same_map(a: LivePipeline, b: LivePipeline) -> None:
    da, db = a.map.global_dem(None), b.map.global_dem(None)
    assert da.geometry == db.geometry
    for name in ("elevation", "variance", "count"):
        np.testing.assert_array_equal(da.layers[name], db.layers[name])


def test_the_map_caught_up_between_frames_is_the_map_of_a_run_as_fast_as_possible(smoke_log):
    fast = _run(smoke_log, realtime=False, idle_after_frames=False, n_frames=40)
    live = _run(smoke_log, realtime=True, idle_after_frames=True, n_frames=40)
    _same_map(fast, live)
    np.testing.assert_array_equal(fast.result().trajectory().positions_xyz, live.result().trajectory().positions_xyz)
    # every frame's catch-up was done between frames, but for the frame held at the end (done in finish)
    assert len(live.idle_timing_s) == live.updates - 1
    assert fast.idle_timing_s == []


class _HeldGraph:
    """The in-process graph, its results handed over only once released: as results that come back
    from a second process between frames."""

    def __init__(self, client):
        self.inner, self.released = client._graph, []
        client._graph = self
        client.results_when_ready = True  # (as a second process's without a fixed delay)

    def release(self) -> None:
        self.released += self.inner.results()

    def results(self):
        out, self.released = self.released, []
        return out

    def finish(self):
        pending, final = self.inner.finish()
        return self.released + pending, final

    def __getattr__(self, name):
        return getattr(self.inner, name)


def test_keyframe_work_and_results_done_between_frames_give_the_trajectory_of_the_same_work_at_the_next_frame(smoke_log):
    """With the graph in a second process (here: results held until the frame after they were made) a
    frame's keyframe work (drops, seeds, the keyframe's message) and the results that came back wait
    for idle time; without idle time the next frame does them first, in the same order."""
    at_next_frame = _run(smoke_log, realtime=True, idle_after_frames=False, n_frames=40, graph=_HeldGraph)
    between = _run(smoke_log, realtime=True, idle_after_frames=True, n_frames=40, graph=_HeldGraph)
    a, b = at_next_frame.result(), between.result()
    np.testing.assert_array_equal(a.trajectory().positions_xyz, b.trajectory().positions_xyz)
    np.testing.assert_array_equal(a.trajectory().orientations_quat_xyzw, b.trajectory().orientations_quat_xyzw)
    np.testing.assert_array_equal(a.pose_covariances(), b.pose_covariances())
    assert between.estimator._client.poses.keys() == at_next_frame.estimator._client.poses.keys()
    # every frame (each a keyframe) had its work done between frames, but for the frame held at the end
    assert len(between.took) == between.updates - 1 and all(between.took)
    # which the next frame did first where no idle time came: its time stays in the frame it belongs to
    frames = a.frames[1:-1]
    assert all(f.timing_s.get("after_frame", 0.0) > 0.0 for f in frames)


def test_the_batch_files_each_seed_under_the_frame_that_made_it_when_its_work_waited(smoke_log):
    """isam2-batch's log keeps the frame each new point was seeded in: with the keyframe work between
    frames (after the frame's record), still that frame, whose time is the point's creation time."""
    pipeline = _run(smoke_log, realtime=True, idle_after_frames=True, n_frames=20, graph=_HeldGraph, estimator="isam2-batch")
    est = pipeline.estimator
    result = est.result()
    points = result.points.arrays()
    created = dict(zip(points["point_id"].tolist(), points["created_t_s"].tolist()))
    frames_t = [f.t_s for f in result.frames]
    seeds = est.log.seeds
    assert len(seeds) > 50 and all(pipeline.took)
    for frame, seed in zip(est.log.seed_frame, seeds, strict=True):
        assert frames_t[frame] == created[seed.point_id]


def test_at_a_fixed_delay_a_run_at_the_camera_rate_is_still_the_in_process_run_with_that_delay(smoke_log):
    """With results handed back exactly one keyframe late nothing waits for idle time: the second
    process's run, idle calls and all, is number for number the in-process run with that delay."""
    in_process = _run(smoke_log, realtime=False, idle_after_frames=False, n_frames=25, graph_delay_keyframes=1)
    second = _run(smoke_log, realtime=True, idle_after_frames=True, n_frames=25, graph_process=True, graph_delay_keyframes=1)
    a, b = in_process.result(), second.result()
    np.testing.assert_array_equal(a.trajectory().positions_xyz, b.trajectory().positions_xyz)
    np.testing.assert_array_equal(a.trajectory().orientations_quat_xyzw, b.trajectory().orientations_quat_xyzw)
    assert not any(second.took)  # (the estimator had no idle work: every result was taken in its frame)
