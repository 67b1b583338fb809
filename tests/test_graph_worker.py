"""The graph's side of the graph estimator: the same messages give the same smoothing in this
process and in a second one, failures and restarts, a whole run with the graph in a second
process against the simulator's truth, and that process's quiet end with a `dem-graph run`
interrupted (Ctrl-C, SIGTERM) or killed."""

from __future__ import annotations

import dataclasses
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from dem_graph.errors import DemGraphError
from dem_graph.estimators import keyframe_graph
from dem_graph.estimators.graph_worker import (
    DelayedProcessGraph,
    GraphWorker,
    InProcessGraph,
    KeyframeMessage,
    ProcessGraph,
    RestartMessage,
)
from dem_graph.estimators.isam2_config import Isam2Config
from dem_graph.geometry.se3 import make_pose, rotation_from_rpy, transform_points
from dem_graph.pipeline import RunConfig, run_estimator


@pytest.fixture(scope="module")
def recorded(smoke_log):
    """The setup and the first 40 messages an in-process run of `smoke` sends to its graph, with
    the results it got back."""
    setups, messages, results = [], [], []
    real_init, real_send = InProcessGraph.__init__, InProcessGraph.send

    def init(self, setup, delay=0):
        setups.append(setup)
        real_init(self, setup, delay)

    def send(self, message):
        real_send(self, message)
        if len(messages) < 40:
            messages.append(message)
            results.append(self._results[-1])

    mp = pytest.MonkeyPatch()
    mp.setattr(InProcessGraph, "__init__", init)
    mp.setattr(InProcessGraph, "send", send)
    try:
        run_estimator(smoke_log, RunConfig.model_validate({"estimator": "isam2", "max_frames": 45}))
    finally:
        mp.undo()
    return setups[0], messages, results


def _wait(graph: ProcessGraph, timeout_s: float = 60.0):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        got = graph.results()
        if got:
            return got
        time.sleep(0.002)
    raise AssertionError("no result from the graph process")


def test_the_second_process_smooths_exactly_as_this_one(recorded):
    """Message by message (each result awaited), the second process's results equal the
    in-process ones to the last bit: the same gtsam computation, only elsewhere."""
    setup, messages, expected = recorded
    graph = ProcessGraph(setup)
    try:
        for message, want in zip(messages, expected):
            graph.send(message)
            (got,) = _wait(graph)
            assert got.k == want.k and got.failure is None
            assert sorted(got.poses) == sorted(want.poses) and sorted(got.points) == sorted(want.points)
            for k in want.poses:
                np.testing.assert_array_equal(got.poses[k], want.poses[k])
            for j in want.points:
                np.testing.assert_array_equal(got.points[j], want.points[j])
        pending, (poses, points) = graph.finish()
        assert pending == []
        assert len(poses) == messages[-1].k + 1  # every keyframe numbered
    finally:
        graph.close()


@pytest.mark.skipif(not hasattr(os, "getpriority"), reason="Unix scheduling priorities")
def test_the_second_process_runs_at_the_priority_it_was_given(recorded):
    """``graph_process_nice``: the graph process's nice value is the estimator's plus the setting
    (read back from the kernel), and 0 leaves it at the estimator's; the process still answers."""
    setup, messages, _ = recorded
    own = os.getpriority(os.PRIO_PROCESS, 0)
    for nice in (0, 7):
        graph = ProcessGraph(setup, nice=nice)
        try:
            graph.send(messages[0])
            (got,) = _wait(graph)
            assert got.k == messages[0].k and got.failure is None
            assert os.getpriority(os.PRIO_PROCESS, graph._process.pid) == min(own + nice, 19)
        finally:
            graph.close()


def test_an_indeterminate_window_is_eliminated_again_with_the_same_estimate(recorded):
    """The recovery from an update iSAM2 finds indeterminate (the IMU's stiff factors): a new iSAM2
    over the same factors from the kept estimates, velocities and biases last. Forced after 20
    keyframes of `smoke` (with its IMU), the window after the next 20 is the one of the run without
    it: each pose within a tenth of its own marginal sigma (Mahalanobis distance of the position),
    and the count says so."""
    setup, messages, _ = recorded
    assert setup.imu is not None
    plain, recovered = GraphWorker(setup), GraphWorker(setup)
    for i, message in enumerate(messages):
        for worker in (plain, recovered):
            worker.apply([message])
            worker.cut_if_due()
        if i == 19:
            recovered.graph._recover("Indeterminate linear system (forced by the test)")
    assert recovered.graph.recoveries == 1 and plain.graph.recoveries == 0
    (poses_a, points_a), (poses_b, points_b) = plain.graph.window_estimates(), recovered.graph.window_estimates()
    assert sorted(poses_a) == sorted(poses_b) and sorted(points_a) == sorted(points_b)
    from gtsam.symbol_shorthand import X

    # the two differ as iSAM2's relinearisation left them: the new iSAM2 linearised every factor anew
    ratio = []
    for k in poses_a:
        P_translation = np.asarray(plain.graph.isam.marginalCovariance(X(k)))[3:, 3:]
        d = poses_a[k][:3, :3].T @ (poses_b[k][:3, 3] - poses_a[k][:3, 3])  # in the body frame, as gtsam's covariance
        ratio.append(float(np.sqrt(d @ np.linalg.solve(P_translation, d))))
    assert max(ratio) < 0.1


def _as_sent_without_basis(messages):
    """The recorded messages as a front end that does not say which estimate of the keyframe before
    its guesses were measured from: the replays below change only how the keyframes arrive, and the
    recording's bases are those of results that came on time."""
    return [dataclasses.replace(m, T_world_prev=None) for m in messages]


def test_a_late_front_ends_guesses_are_carried_onto_the_graphs_estimate(recorded):
    """A front end whose results are late guesses keyframe k and its new points from an older
    estimate of keyframe k - 1. Sent with its guesses and that estimate all moved by the same rigid
    motion D (1 degree and 3 cm: what a late correction is), the graph starts from its own estimate
    and smooths exactly as with the guesses of a front end on time: every estimate of the window
    equal to 1e-9. Without the basis the same moved message starts D away and ends elsewhere."""
    setup, messages, _ = recorded
    n = 30
    k_new = next(i for i in range(n, len(messages)) if messages[i].new_points)
    on_time, late, blind = GraphWorker(setup), GraphWorker(setup), GraphWorker(setup)
    for m in messages[:k_new]:
        for worker in (on_time, late, blind):
            worker.apply([m])
            worker.cut_if_due()
    m = messages[k_new]
    T_prev = on_time.graph.poses[m.k - 1]
    D = make_pose(rotation_from_rpy(0.0, 0.0, np.radians(1.0)), [0.03, -0.02, 0.01])
    moved_points = [dataclasses.replace(p, X_world=transform_points(D, p.X_world)) for p in m.new_points]
    moved = dataclasses.replace(m, T_world_body=D @ m.T_world_body, T_world_prev=D @ T_prev, new_points=moved_points)
    want = on_time.apply([dataclasses.replace(m, T_world_prev=T_prev.copy())])
    got = late.apply([moved])
    off = blind.apply([dataclasses.replace(moved, T_world_prev=None)])
    assert sorted(got.poses) == sorted(want.poses) and sorted(got.points) == sorted(want.points)
    for k in want.poses:
        np.testing.assert_allclose(got.poses[k], want.poses[k], atol=1e-9)
    for j in want.points:
        np.testing.assert_allclose(got.points[j], want.points[j], atol=1e-9)
    assert max(np.abs(off.poses[k][:3, 3] - want.poses[k][:3, 3]).max() for k in want.poses) > 1e-4


def _smooth_in_batches(setup, messages, size: int):
    worker = GraphWorker(setup)
    for start in range(0, len(messages), size):
        result = worker.apply(messages[start : start + size])
        worker.cut_if_due()  # (as the second process does after each result)
    return result


def _largest_difference(result, want) -> tuple[float, float]:
    """Largest position difference over the window's keyframes and over its landmarks, metres."""
    pose = max(np.abs(result.poses[k][:3, 3] - want.poses[k][:3, 3]).max() for k in want.poses)
    point = max(np.abs(result.points[j] - want.points[j]).max() for j in want.points)
    return pose, point


def test_keyframes_sent_together_are_smoothed_like_one_at_a_time(recorded, monkeypatch):
    """iSAM2 takes one step per update, so keyframes that reach the graph 8 at a time get 8 steps:
    after 40 keyframes the estimates are within half a millimetre (poses) and a centimetre (points,
    camera points with up to 0.5 m of seed uncertainty among them) of the one-at-a-time smoothing,
    and closer than with one step per update. Measured: 0.09 mm and 3.7 mm with the steps,
    0.46 mm and 28 mm without."""
    setup, messages, expected = recorded
    messages = _as_sent_without_basis(messages)
    want = expected[-1]
    stepped = _largest_difference(_smooth_in_batches(setup, messages, 8), want)
    real = keyframe_graph.KeyframeGraph.update
    monkeypatch.setattr(keyframe_graph.KeyframeGraph, "update", lambda self, iterations=1: real(self, 1))
    single = _largest_difference(_smooth_in_batches(setup, messages, 8), want)
    print(f"batches of 8, pose/point difference: with a step per keyframe {stepped}, one step per update {single}")
    assert stepped[0] < 5e-4 and stepped[1] < 0.01
    assert stepped[0] < single[0] and stepped[1] < single[1]


def test_a_failed_update_waits_for_a_restart(recorded, monkeypatch):
    """A failed update is reported; keyframes sent before the restart keep their numbers; the
    restart starts a new smoother at the newest keyframe with the given priors."""
    setup, messages, expected = recorded
    worker = GraphWorker(setup)
    for m in messages[:10]:
        assert worker.apply([m]).failure is None

    def fail(self, iterations=1):
        self._clear_pending()
        raise keyframe_graph.GraphUpdateError("the graph update failed: Indeterminant linear system")

    monkeypatch.setattr(keyframe_graph.KeyframeGraph, "update", fail)
    failed = worker.apply([messages[10]])
    assert failed.failure is not None and "Indeterminant" in failed.failure and failed.poses == {}
    monkeypatch.undo()
    waiting = worker.apply([messages[11]])
    assert waiting.waiting and waiting.failure is None
    k = messages[11].k
    T = messages[11].T_world_body
    X = {7: np.array([3.0, 0.1, -0.05])}
    restarted = worker.apply([RestartMessage(k, T, np.eye(6) * 1e-4, {7: (X[7], np.eye(3) * 1e-4)})])
    assert restarted.failure is None and not restarted.waiting
    assert sorted(restarted.poses) == [k] and sorted(restarted.points) == [7]
    np.testing.assert_allclose(restarted.poses[k], T, atol=1e-9)  # priors only: the estimate is the prior
    np.testing.assert_allclose(restarted.points[7], X[7], atol=1e-9)


def _stopped_graph(setup, max_lag: int) -> ProcessGraph:
    """A graph process that does not read (stopped, as during a long update), behind a socket buffer
    far smaller than the messages."""
    graph = ProcessGraph(setup, max_lag=max_lag)
    sock = socket.socket(fileno=os.dup(graph._conn.fileno()))
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 4096)
    sock.close()
    os.kill(graph._process.pid, signal.SIGSTOP)
    return graph


def _send_all(graph: ProcessGraph, messages) -> tuple[threading.Thread, list]:
    sent = []
    thread = threading.Thread(target=lambda: [(graph.send(m), sent.append(m.k)) for m in messages], daemon=True)
    thread.start()
    return thread, sent


@pytest.mark.parametrize("max_lag", [64, 8])
def test_a_busy_graph_process_holds_up_the_frame_only_past_its_lag(recorded, max_lag):
    """While the second process does not read, keyframes are sent without waiting as long as they
    are at most ``max_lag`` after the graph's newest result (none here), then the send waits for the
    graph. Once it reads again every keyframe is smoothed, in order, and the final estimates are
    those of one-at-a-time smoothing to 0.5 mm (the keyframes arrive together: the bound of the test
    above). Before the sending thread, the first send past the socket's buffer waited here for
    ever: the process, answering, waited for the frame to read."""
    setup, messages, expected = recorded
    messages = _as_sent_without_basis(messages)
    assert [m.k for m in messages] == list(range(len(messages)))
    graph = _stopped_graph(setup, max_lag)
    try:
        thread, sent = _send_all(graph, messages)
        thread.join(2.0 if max_lag < len(messages) else 10.0)
        if max_lag >= len(messages):
            assert not thread.is_alive(), "send waited for the stopped graph process"
        else:
            assert thread.is_alive() and sent == list(range(max_lag))
        os.kill(graph._process.pid, signal.SIGCONT)
        thread.join(30.0)
        assert not thread.is_alive() and len(sent) == len(messages)
        pending, (poses, points) = graph.finish()
        assert [r.failure for r in pending if r.failure] == []
        assert pending[-1].k == messages[-1].k
        assert sorted(poses) == list(range(messages[-1].k + 1))
        want = expected[-1]
        for k in want.poses:
            np.testing.assert_allclose(poses[k][:3, 3], want.poses[k][:3, 3], atol=5e-4)
    finally:
        os.kill(graph._process.pid, signal.SIGCONT)
        graph._process.kill()  # (a send still waiting, as before the fix, would wait for ever)
        graph.close()


def test_a_frame_waits_for_a_busy_graph_process_only_as_long_as_it_is_told(recorded):
    """With the graph process stopped (a long update) after answering keyframe 0 and
    ``max_lag`` 2: keyframes 1 and 2 may go at once, keyframe 3 may not. Asked with no time to
    spare (a frame behind the sensors' clock) the answer is no at once; with 0.3 s to spare it waits
    those 0.3 s and no longer; once the process runs again it answers within that time."""
    setup, messages, _ = recorded
    graph = ProcessGraph(setup, max_lag=2)
    try:
        graph.send(messages[0])
        deadline = time.monotonic() + 60.0
        while not graph.started and time.monotonic() < deadline:
            time.sleep(0.002)
        assert graph.started
        os.kill(graph._process.pid, signal.SIGSTOP)
        assert graph.wait_for(1, 0.0) and graph.wait_for(2, 0.0)
        t0 = time.monotonic()
        assert not graph.wait_for(3, 0.0)
        assert time.monotonic() - t0 < 0.05
        t0 = time.monotonic()
        assert not graph.wait_for(3, 0.3)
        assert 0.3 <= time.monotonic() - t0 < 0.5
        for m in messages[1:3]:
            graph.send(m)
        os.kill(graph._process.pid, signal.SIGCONT)
        assert graph.wait_for(3, 30.0)
        assert max(r.k for r in graph.results()) >= 1
    finally:
        os.kill(graph._process.pid, signal.SIGCONT)
        graph.close()


def test_a_replay_as_fast_as_possible_waits_for_the_graph_and_one_at_the_sensors_rate_does_not(smoke_log):
    """``graph_when_behind`` unset: a run replaying its log as fast as possible waits for a graph
    that is behind (the replay goes at its pace); at the sensors' rate (``realtime``) frames merge
    instead. Set, it is kept."""
    from dem_graph.pipeline.live import make_estimator

    def policy(**settings):
        config = RunConfig.model_validate({"estimator": "isam2", **settings})
        return make_estimator(smoke_log.rig, smoke_log.T_world_body_initial, smoke_log.t_start_s, True, config).config.graph_when_behind

    assert policy() == "wait"
    assert policy(realtime=True) == "merge"
    assert policy(realtime=True, isam2={"graph_when_behind": "wait"}) == "wait"


def test_the_graph_in_a_second_process_takes_each_landmark_every_second_keyframe(smoke_log, monkeypatch):
    """``observation_every`` unset: with the graph in a second process each landmark's observation
    goes at every second keyframe, the landmarks taking turns (landmark + keyframe even), carrying
    the two frames since its last (sigma_px / sqrt(2) for a point tracked throughout); in this
    process, at every keyframe with sigma_px; set, it is kept either way."""
    messages = []
    real_send = ProcessGraph.send
    monkeypatch.setattr(ProcessGraph, "send", lambda self, m: (messages.append(m), real_send(self, m))[1])
    run = run_estimator(smoke_log, RunConfig.model_validate({"estimator": "isam2", "isam2": {"graph_process": True}}))
    assert run.error is None
    keyframes = [m for m in messages if isinstance(m, KeyframeMessage) and len(m.landmarks)]
    assert len(keyframes) > 30 and all(np.all((m.landmarks + m.k) % 2 == 0) for m in keyframes)
    sigma_px = run.config.frontend.sigma_px
    assert np.median(np.concatenate([m.sigma_px for m in keyframes[3:]])) == pytest.approx(sigma_px / np.sqrt(2))
    spacing = {(process, every): Isam2Config(graph_process=process, observation_every=every).observation_spacing for process in (False, True) for every in (None, 1, 3)}
    assert spacing == {(False, None): 1, (False, 1): 1, (False, 3): 3, (True, None): 2, (True, 1): 1, (True, 3): 3}
    assert Isam2Config(graph_process=True, batch=True).observation_spacing == 1  # (the batch's online pass)


def test_frames_merged_while_the_graph_is_behind(smoke_log, monkeypatch):
    """A graph that cannot take every other keyframe (here told so, reproducibly, in this
    process): those frames are not keyframes, their observations go with the next one, and the run
    counts them. Every other frame of `smoke` merged: 32 of 65, 33 keyframes; the trajectory stays
    within 3 cm of the truth (ATE; measured 7.4 mm against 6.6 mm with every frame a keyframe)."""
    from dem_graph.estimators.graph_client import GraphClient

    turns = iter([True, False] * 100)
    monkeypatch.setattr(GraphClient, "ready_for_keyframe", lambda self: next(turns))
    run = run_estimator(smoke_log, RunConfig.model_validate({"estimator": "isam2"}))
    m = run.metrics
    assert run.error is None and m.frames == 65
    assert m.events["keyframes_merged"] == 32 and m.events["keyframes"] == 33
    assert m.trajectory.ate_rmse_m < 0.03


def test_a_bad_message_in_the_second_process_is_a_clear_error(recorded):
    setup, messages, _ = recorded
    graph = ProcessGraph(setup)
    try:
        m = messages[3]
        bad = KeyframeMessage(m.k + 5, m.t_s, m.T_world_body, m.U, m.Q, m.landmarks, m.uv_px, m.sigma_px)
        graph.send(bad)
        with pytest.raises(DemGraphError, match=f"keyframe {m.k + 5} sent to the graph, which expected keyframe 1"):
            _wait(graph)
    finally:
        graph.close()


def test_a_run_with_the_graph_in_a_second_process(smoke_log):
    """`smoke` with the graph on another core: its results come back keyframes late, and the run
    meets the same goals as in-process (drift under 1 %, ATE under 3 cm)."""
    run = run_estimator(smoke_log, RunConfig.model_validate({"estimator": "isam2", "isam2": {"graph_process": True}}))
    m = run.metrics
    assert run.error is None and m.frames == 65
    assert m.trajectory.drift_percent < 1.0
    assert m.trajectory.ate_rmse_m < 0.03
    assert m.trajectory_smoothed.ate_rmse_m < 0.03
    assert "graph_lag_keyframes_median" in m.events


def test_an_in_process_graph_can_hand_its_results_back_late(recorded):
    """``delay`` keyframes late, in order, the same results; the rest at the end."""
    setup, messages, expected = recorded
    graph = InProcessGraph(setup, delay=3)
    got = []
    for i, message in enumerate(messages[:10]):
        graph.send(message)
        back = graph.results()
        assert [r.k for r in back] == ([] if i < 3 else [expected[i - 3].k])
        got += back
    pending, _ = graph.finish()
    got += pending
    assert [r.k for r in got] == [r.k for r in expected[:10]]
    for r, want in zip(got, expected):
        for k in want.poses:
            np.testing.assert_array_equal(r.poses[k], want.poses[k])


def test_a_delayed_second_process_hands_back_what_this_one_would(recorded):
    """``graph_delay_keyframes`` with ``graph_process``: the second process takes one message at a
    time and each result is handed back exactly ``delay`` messages late, waited for when not back:
    the keyframes at the calls the in-process graph with that delay gives them, the numbers to the bit."""
    setup, messages, expected = recorded
    assert Isam2Config(graph_process=True, graph_delay_keyframes=3).graph_placement == (True, 3)
    graph = DelayedProcessGraph(setup, delay=3)
    try:
        got = []
        for i, message in enumerate(messages[:12]):
            graph.send(message)
            back = graph.results()
            assert [r.k for r in back] == ([] if i < 3 else [expected[i - 3].k])
            got += back
        assert graph.results() == []  # nothing more is due until the next message
        pending, _ = graph.finish()
        got += pending
        assert graph.results() == []
    finally:
        graph.close()
    assert [r.k for r in got] == [r.k for r in expected[:12]]
    for r, want in zip(got, expected):
        assert sorted(r.points) == sorted(want.points)
        for k in want.poses:
            np.testing.assert_array_equal(r.poses[k], want.poses[k])
        for j in want.points:
            np.testing.assert_array_equal(r.points[j], want.points[j])


def test_a_delayed_graph_needs_a_delay():
    with pytest.raises(ValueError, match="at least one keyframe"):
        DelayedProcessGraph(None, delay=0)


@pytest.fixture(scope="module")
def paper_5m():
    """The first 5 m of `paper` (800x600, 83 frames), every event in memory; without the IMU, whose
    1 mm ATE in-process on this log is below the spread of what late results change (1.0 in-process;
    2.1, 1.2, 1.2 and 2.3 mm 1, 2, 3 and 6 keyframes late: docs/imu.md)."""
    from dem_graph.datasets.memory import InMemorySequence
    from dem_graph.sim.scenarios import scenario
    from dem_graph.sim.simulator import SimulatedSequence

    return InMemorySequence.record(SimulatedSequence.from_config(scenario("paper", seed=1, length_m=5.0, with_imu=False)))


def _late(sequence, delay: int):
    """isam2's metrics on ``sequence`` with its graph's results handed back ``delay`` keyframes late."""
    r = run_estimator(sequence, RunConfig.model_validate({"estimator": "isam2", "isam2": {"graph_delay_keyframes": delay}}))
    assert r.error is None
    return r.metrics


@pytest.fixture(scope="module")
def paper_5m_in_process(paper_5m):
    """isam2's metrics on the first 5 m of `paper`, each result within its frame."""
    return _late(paper_5m, 0)


def test_late_results_do_not_turn_good_matches_into_outliers(paper_5m, paper_5m_in_process):
    """The graph's results 6 keyframes late (as from a second process, but reproducibly): the live
    points keep the steps of the observations sent since, so the pose update rejects no more matches
    as outliers than in-process (the simulation injects none; the tracker's own tails are 0.11 % of
    the matches in-process). Bound: 0.5 %. Measured: 0.24 % with the steps kept, 2.25 % when a late
    result set the points back to the graph's older estimate (the code before; 1.7-2.2 % on the
    whole of `paper` with the second process). The trajectory stays within 25 % of the in-process
    ATE (measured 3.30 mm against 3.19 mm; 4.5 mm before)."""

    now, late = paper_5m_in_process, _late(paper_5m, 6)
    assert late.events["graph_lag_keyframes_median"] == 6
    assert now.tracking.outlier_fraction_of_matched < 0.005
    assert late.tracking.outlier_fraction_of_matched < 0.005
    assert late.trajectory.ate_rmse_m < 1.25 * now.trajectory.ate_rmse_m


@pytest.mark.parametrize("delay", [1, 3])
def test_a_graph_one_or_three_keyframes_late_keeps_the_in_process_accuracy(paper_5m, paper_5m_in_process, delay):
    """Results 1 and 3 keyframes late (as a second process that keeps up hands them back; here
    reproducibly, in this process): the online trajectory, what was known at each frame, stays within
    15 % of the in-process graph's ATE. Measured on this log: 3.19 mm in-process, 3.16 mm one
    keyframe late, 3.49 mm three late (12 m of seeds 1 and 2: 4.43 / 4.27 / 4.80 mm and
    4.12 / 4.22 / 4.06 mm)."""

    now, late = paper_5m_in_process, _late(paper_5m, delay)
    assert late.events["graph_lag_keyframes_median"] == delay
    assert late.trajectory.ate_rmse_m <= 1.15 * now.trajectory.ate_rmse_m


# --- the graph process ends with its run ------------------------------------------------------
# `dem-graph run` in a process group of its own; the processes are seen through /proc (Linux).

signals_on_linux = pytest.mark.skipif(sys.platform != "linux", reason="reads /proc")


def _stat(pid: int) -> list[str] | None:
    """The fields of /proc/<pid>/stat after the name (state, ppid, ...); None when it has gone."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rpartition(")")[2].split()
    except OSError:
        return None


def _children(pid: int) -> list[int]:
    return [int(d) for d in os.listdir("/proc") if d.isdigit() and (s := _stat(int(d))) is not None and int(s[1]) == pid]


def _ignores_sigint(pid: int) -> bool:
    try:
        status = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return False
    ignored = int(status.split("SigIgn:")[1].split()[0], 16)
    return bool(ignored & (1 << (signal.SIGINT - 1)))


def _gone(pid: int, timeout_s: float) -> bool:
    """Whether process ``pid`` has ended (a zombie waiting for its new parent counts) within ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while (s := _stat(pid)) is not None and s[0] != "Z":
        if time.monotonic() > deadline:
            return False
        time.sleep(0.01)
    return True


def _start_run(folder, out) -> tuple[subprocess.Popen, int]:
    """`dem-graph run` with the graph in a second process, in real time (the run lasts the log's
    2.5 s at least), and the pid of the graph process once it serves: it ignores SIGINT from then.
    The run is processing frames by then (it waits for the graph past 10 keyframes)."""
    command = [
        sys.executable,
        "-m",
        "dem_graph.cli",
        "run",
        str(folder),
        "--estimator",
        "isam2",
        "--graph-process",
        "--realtime",
        "--out",
        str(out / "run"),
    ]
    with open(out / "stderr.txt", "w") as stderr:
        run = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=stderr, start_new_session=True)
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline and run.poll() is None:
        graph = _children(run.pid)  # (its only child)
        if graph and _ignores_sigint(graph[0]):
            time.sleep(0.2)  # the graph at work on the keyframes queued meanwhile
            return run, graph[0]
        time.sleep(0.02)
    run.kill()
    raise AssertionError(f"no graph process ignoring SIGINT before the run's end: {(out / 'stderr.txt').read_text()}")


def _stop(run: subprocess.Popen, graph_pid: int) -> None:
    """Whatever the test left running."""
    if run.poll() is None:
        run.kill()
        run.wait()
    if not _gone(graph_pid, 0.0):
        os.kill(graph_pid, signal.SIGKILL)


@signals_on_linux
@pytest.mark.parametrize("how", ["SIGINT to the group", "SIGTERM to the run"])
def test_the_graph_process_ends_quietly_with_an_interrupted_run(smoke_folder, tmp_path, how):
    """Ctrl-C (SIGINT to the whole group, as a terminal sends it) or SIGTERM to the run mid-way: the
    run ends (within 15 s: it may keep what it has), the graph process with it (within 3 s more),
    and no one prints a traceback (before, the graph process printed its KeyboardInterrupt)."""
    run, graph_pid = _start_run(smoke_folder, tmp_path)
    try:
        if how == "SIGINT to the group":
            os.killpg(run.pid, signal.SIGINT)
        else:
            os.kill(run.pid, signal.SIGTERM)
        run.wait(timeout=15)
        assert _gone(graph_pid, 3.0), "the graph process outlived its run"
    finally:
        _stop(run, graph_pid)
    stderr = (tmp_path / "stderr.txt").read_text()
    assert "Traceback" not in stderr, stderr


@signals_on_linux
def test_the_graph_process_ends_with_a_killed_run(smoke_folder, tmp_path):
    """SIGKILL to the run mid-way: the graph process ends within 3 s (Linux tells it at once), quietly."""
    run, graph_pid = _start_run(smoke_folder, tmp_path)
    try:
        run.kill()
        assert _gone(graph_pid, 3.0), "the graph process outlived its killed run"
    finally:
        _stop(run, graph_pid)
    stderr = (tmp_path / "stderr.txt").read_text()
    assert "Traceback" not in stderr, stderr


def test_the_second_process_is_ready_when_made(recorded):
    """``ProcessGraph`` returns once the process has imported and built its graph: a setup it cannot
    build one from is refused there, with the process's reason, before any keyframe is sent; with a
    good one nothing is left unread, and the first keyframes' results are the in-process ones."""
    setup, messages, results = recorded
    with pytest.raises(DemGraphError, match="the graph process could not start"):
        ProcessGraph(dataclasses.replace(setup, P0=np.eye(3)))
    graph = ProcessGraph(setup)
    try:
        assert not graph._conn.poll() and graph._process.poll() is None
        graph.send(messages[0])
        got = _wait(graph)
        assert got[0].k == results[0].k
        for k, T in results[0].poses.items():
            np.testing.assert_array_equal(got[0].poses[k], T)
    finally:
        graph.close()
