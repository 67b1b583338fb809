"""The graph's side of the graph estimator: what it is sent at each keyframe, what it answers, and
where it runs.

The front end (tracking, the per-frame pose) and the graph (iSAM2 updates, marginalisation,
marginal covariances) talk only through plain messages:

- :class:`KeyframeMessage`: a keyframe's pose guess, the motion since the keyframe before, its
  observations, the landmarks it starts (seeds and patch-refresh links);
- :class:`RestartMessage`: start a new smoother from the front end's estimates after a failure;
- :class:`GraphResult`: the smoothed window after the update, and a marginal when one was asked for.

:class:`GraphWorker` turns messages into factors and runs the update. It runs either in the
estimator's own process (:class:`InProcessGraph`: each keyframe's result is back before the frame
ends, and a run is reproducible) or in a second process (:class:`ProcessGraph`: the frame's time is
the front end's alone, the graph works on another core and its results come back one or more
keyframes later; a run then depends on the timing).

The second process ends with the estimator's, quietly, however that one ends. A terminal's Ctrl-C
reaches every process of its group, the graph's too: the graph ignores it, and the estimator
decides (it may still ask for the final estimates). It ends, without a traceback, when the
connection breaks (the estimator has gone) or at SIGTERM (its default action, which the estimator's
close sends, and which Linux sends when the estimator's process dies, even by SIGKILL).
"""

from __future__ import annotations

import atexit
import ctypes
import os
import queue
import signal
import socket
import subprocess
import sys
import threading
import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from multiprocessing.connection import Connection

import gtsam
import numpy as np
from gtsam.symbol_shorthand import L, X

from dem_graph.errors import DemGraphError
from dem_graph.estimators.graph_factors import (
    ProjectionFactors,
    calibration,
    level_factor,
    link_factor,
    odometry_factor,
    points_in_frame_factors,
    seeds_factors,
)
from dem_graph.estimators.imu_preintegration import bias_sigmas, preintegrate, preintegration_params
from dem_graph.estimators.keyframe_graph import GraphUpdateError, KeyframeGraph
from dem_graph.estimators.laser_ties import NO_TIES, LaserTies
from dem_graph.frontend.frontend import PointKind
from dem_graph.geometry.camera import PinholeCamera
from dem_graph.geometry.rig import ImuSpec
from dem_graph.geometry.se3 import invert, nearest_pose, transform_points


@dataclass(frozen=True)
class GraphSetup:
    """Everything the graph needs to start: the first keyframe and the factors' settings."""

    T_world_body_0: np.ndarray
    P0: np.ndarray  # 6x6, [rotation, translation]
    t0_s: float
    lag_s: float
    relinearize_threshold: float
    relinearize_skip: int
    marginalize_every_s: float
    optimizer: str  # "dogleg" or "gauss_newton"
    camera: PinholeCamera
    T_body_cam: np.ndarray
    camera_point_sigma_px: float  # the seed pixel of a camera point
    split_link_sigma_m: float
    robust: bool
    imu: ImuSpec | None = None  # the rig's IMU, when its samples are sent (KeyframeMessage.imu)
    imu_sigma_v0_mps: float = 1.0  # the prior on a keyframe's velocity where the IMU's factors start (the first, or after a restart or a gap)


@dataclass(frozen=True)
class NewLandmark:
    landmark: int
    X_world: np.ndarray  # initial guess, metres
    kind: PointKind
    p_body: np.ndarray  # the seed in the keyframe's body frame
    Sigma_body: np.ndarray  # 3x3


@dataclass(frozen=True)
class KeyframeMessage:
    """Keyframe ``k`` at ``t_s``. When ``k`` is a new keyframe, ``U``/``Q`` are the motion and its
    covariance since keyframe ``k - 1``; when it is the graph's last one (the first frame, at the
    start pose's time) the observations attach to it."""

    k: int
    t_s: float
    T_world_body: np.ndarray  # the front end's estimate: the initial guess
    U: np.ndarray
    Q: np.ndarray
    landmarks: np.ndarray  # observed landmark per observation (m,)
    uv_px: np.ndarray  # (m,2)
    sigma_px: np.ndarray  # (m,)
    links: list[tuple[int, int, np.ndarray]] = field(default_factory=list)  # (old, new landmark, old covariance) of refreshed patches
    new_points: list[NewLandmark] = field(default_factory=list)
    want_marginal: bool = False  # answer with keyframe k's marginal pose covariance
    imu: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None  # the IMU samples since keyframe k - 1: times (n,), rates, forces (n,3)
    T_world_prev: np.ndarray | None = None  # keyframe k - 1 as the front end had it when it sent k: what its guesses of k and of the new points were measured from
    ties: LaserTies = NO_TIES  # landmarks tied to the scans of their ground, each measured in a keyframe of the window (laser_ties)


@dataclass(frozen=True)
class RestartMessage:
    """A new smoother at keyframe ``k`` (the newest one sent): its pose and the live landmarks
    (landmark -> (X_world, 3x3 covariance)) enter with priors at the front end's estimates."""

    k: int
    T_world_body: np.ndarray
    P: np.ndarray
    point_priors: dict[int, tuple[np.ndarray, np.ndarray]]


@dataclass
class GraphResult:
    k: int  # the newest keyframe in the update
    poses: dict[int, np.ndarray]  # every keyframe in the window: T_world_body
    points: dict[int, np.ndarray]  # every landmark in the window: X_world
    marginal: np.ndarray | None = None  # keyframe k's marginal pose covariance, when asked for
    imu_bias: np.ndarray | None = None  # keyframe k's IMU biases [accel m/s^2 (3), gyro rad/s (3)], with an IMU
    recoveries: int = 0  # the graph's indeterminate windows eliminated again so far (KeyframeGraph.recoveries)
    failure: str | None = None  # the update failed: the graph waits for a RestartMessage
    waiting: bool = False  # keyframes that arrived while the graph waited for its restart
    worker_s: float = 0.0  # the graph's time on these messages, seconds
    phases: dict[str, float] = field(default_factory=dict)  # seconds per phase: factors, solve, estimate, marginal; cut, rebuild (the window's, since the last result)

    # Sent between processes with each window's estimates as one array per dict: pickling a dict of
    # some 500 small arrays cost the graph 0.9 ms to write and the estimator 0.6 ms to read per result
    # (packed: 0.2 and 0.3 ms; the same numbers arrive)
    def __getstate__(self) -> dict:
        return {**self.__dict__, "poses": _packed(self.poses), "points": _packed(self.points)}

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state, poses=_unpacked(state["poses"]), points=_unpacked(state["points"]))


def _packed(arrays: dict[int, np.ndarray]) -> tuple[np.ndarray, np.ndarray | None]:
    """Keys and stacked values of a dict of equal-shaped arrays."""
    keys = np.fromiter(arrays.keys(), dtype=np.int64, count=len(arrays))
    return keys, (np.stack(list(arrays.values())) if arrays else None)


def _unpacked(packed: tuple[np.ndarray, np.ndarray | None]) -> dict[int, np.ndarray]:
    """:func:`_packed`'s dict again, each value a row of the packed array (a view: 0.1 against 0.5 ms
    for a window of 660 points and 40 keyframes, copied row by row). The estimator keeps the last
    estimate of every landmark and keyframe for the whole run; it copies a row to an array of its own
    once the row has left the window (:func:`~dem_graph.estimators.graph_client._take_window`), so no
    result's array stays alive for it."""
    keys, values = packed
    return {} if values is None else dict(zip(keys.tolist(), values))


class GraphWorker:
    """Turns messages into factors and updates a :class:`KeyframeGraph` with them."""

    def __init__(self, setup: GraphSetup):
        self.setup = setup
        self._K = calibration(setup.camera)
        self._projection = ProjectionFactors(self._K, setup.T_body_cam, robust=setup.robust)
        self._imu_params = preintegration_params(setup.imu) if setup.imu is not None else None
        self.graph = KeyframeGraph(setup.T_world_body_0, setup.P0, setup.t0_s, setup.lag_s, setup.relinearize_threshold, setup.relinearize_skip, setup.marginalize_every_s, setup.optimizer)
        self.failed = False
        self._cut_failure: str | None = None  # the last cut failed and no result has said so yet
        self._phases_since: dict[str, float] = {}  # the cut's time since the last result, seconds

    def apply(self, messages: list) -> GraphResult:
        """Add the messages' factors in order, then one update and the marginal when asked for. The
        window's cut is not made here but after the result has gone (:meth:`cut_if_due`): its time
        is not the result's wait (it is reported with the next result's phases)."""
        t0 = time.perf_counter()
        g = self.graph
        phases, self._phases_since = {**self._phases_since, **g.take_phases()}, {}
        want_marginal, pending = False, 0
        for m in messages:
            if isinstance(m, RestartMessage):
                self._restart(m)  # updates the new smoother
                pending = 0
            elif self.failed:
                g.skip_keyframe(m.t_s, m.T_world_body)  # waiting for the restart
            else:
                self._add_keyframe(m)
                want_marginal |= m.want_marginal
                pending += 1
        result = GraphResult(g.last_keyframe, {}, {}, phases=phases)
        result.phases["factors"] = time.perf_counter() - t0 - sum(g.phase_s.values())  # (a restart's update is its own phases')
        if self._cut_failure is not None:  # the cut after the last result failed: the estimator restarts the graph
            result.failure, self._cut_failure = self._cut_failure, None
            return result
        if self.failed:
            result.waiting = True
            return result
        try:
            if pending:
                # iSAM2 takes one step per update: keyframes that arrive together get as many steps
                # as they would have had one at a time
                g.update(iterations=pending)
            if want_marginal:
                result.marginal = g.pose_covariance(g.last_keyframe)
        except GraphUpdateError as exc:
            self.failed = True
            result.failure = str(exc)
            result.worker_s = time.perf_counter() - t0
            return result
        result.poses, result.points = g.window_estimates()
        result.imu_bias = g.biases.get(g.last_keyframe)
        result.recoveries = g.recoveries
        result.phases.update(g.take_phases())
        result.worker_s = time.perf_counter() - t0
        return result

    def cut_if_due(self) -> bool:
        """The window's cut, when due (:meth:`KeyframeGraph.marginalize`): made between results, so
        that no result waits for it. Its time goes with the next result's phases (``cut``: the
        marginal of what leaves, ``rebuild``: the new iSAM2); a failure is that result's, and the
        graph waits for a restart. Returns whether it was due."""
        g = self.graph
        if self.failed or not g.marginalization_due:
            return False
        try:
            g.marginalize()
        except GraphUpdateError as exc:
            self.failed = True
            self._cut_failure = str(exc)
        self._phases_since.update(g.take_phases())
        return True

    def _add_keyframe(self, m: KeyframeMessage) -> None:
        g, s = self.graph, self.setup
        k = g.last_keyframe
        C = None  # the attached first frame brings no guess of its own
        if m.k > k:
            C = self._stale_guess_correction(m)
            k = g.add_keyframe(m.t_s, m.T_world_body if C is None else C @ m.T_world_body)
            if k != m.k:
                raise DemGraphError(f"keyframe {m.k} sent to the graph, which expected keyframe {k}")
            g.add_factor(odometry_factor(X(k - 1), X(k), m.U, m.Q))
            if m.imu is not None and self._imu_params is not None:
                self._add_imu(k, m)
        for old, new, Sigma_old in m.links:
            X_old = g.points[old]
            g.add_point(new, X_old)
            if g.in_window(old):
                g.add_factor(link_factor(L(old), L(new), s.split_link_sigma_m))
            else:  # the old one has left the window: its last estimate, as a prior
                Sigma = np.asarray(Sigma_old) + s.split_link_sigma_m**2 * np.eye(3)
                g.add_factor(gtsam.PriorFactorPoint3(L(new), gtsam.Point3(*X_old), gtsam.noiseModel.Gaussian.Covariance(Sigma)))
        for lm, z, sigma in zip(m.landmarks, m.uv_px, m.sigma_px):
            lm = int(lm)
            if not g.in_window(lm):  # marginalised since the front end last heard
                continue
            g.add_factor(self._projection(X(k), L(lm), z, sigma))
            g.observed(lm)
        self._add_ties(m.ties)
        for p in m.new_points:
            g.add_point(p.landmark, p.X_world if C is None else transform_points(C, p.X_world))
        if m.new_points:
            new = m.new_points
            for f in seeds_factors(
                [X(k)] * len(new), [L(p.landmark) for p in new], [p.kind for p in new], np.array([p.p_body for p in new]), np.array([p.Sigma_body for p in new]),
                s.camera, self._K, s.T_body_cam, s.camera_point_sigma_px,
            ):  # fmt: skip
                g.add_factor(f)

    def _add_ties(self, ties: LaserTies) -> None:
        """The laser's ties whose landmark and keyframe are both still in the window (the others came too
        late), and the start pose's own prior put back when the ties say the rig's mount agrees."""
        g = self.graph
        if ties.pin_start is not None and g.pose_in_window(0):
            g.add_factor(gtsam.PriorFactorPose3(X(0), gtsam.Pose3(self.setup.T_world_body_0), gtsam.noiseModel.Gaussian.Covariance(ties.pin_start)))
        for lm, mean, Sigma in zip(ties.level_landmarks.tolist(), ties.level_mean, ties.level_Sigma):  # the start's ground: the world's level
            if g.in_window(lm):
                g.add_factor(level_factor(L(lm), mean, Sigma))
        if not len(ties):
            return
        ok = np.array([g.in_window(lm) and g.pose_in_window(k) for k, lm in zip(ties.keyframes.tolist(), ties.landmarks.tolist())], dtype=bool)
        if ok.any():
            pose_keys, point_keys = [X(int(k)) for k in ties.keyframes[ok]], [L(int(lm)) for lm in ties.landmarks[ok]]
            for f in points_in_frame_factors(pose_keys, point_keys, ties.p_frame[ok], ties.Sigma_frame[ok]):
                g.add_factor(f)

    def _stale_guess_correction(self, m: KeyframeMessage) -> np.ndarray | None:
        """Where the front end guessed the new keyframe ``m.k`` and its new points from a keyframe ``m.k - 1``
        older than the graph's (its results late), the world-frame correction that carries its guess
        onto the graph's estimate of ``m.k - 1``; None when the two agree to the bit (in-process, or
        the results on time) or the graph has no estimate of ``m.k - 1``. A late front end then costs
        the graph no step away from its own estimates."""
        T_graph = self.graph.poses.get(m.k - 1)
        if m.T_world_prev is None or T_graph is None or np.array_equal(T_graph, m.T_world_prev):
            return None
        return nearest_pose(T_graph @ invert(m.T_world_prev))

    def _add_imu(self, k: int, m: KeyframeMessage) -> None:
        """The IMU's factor between keyframes ``k - 1`` and ``k``. Where the IMU's factors start (the
        first span, or after a restart or a span without samples), keyframe ``k - 1`` gets its
        velocity and bias with priors: the velocity of the motion to ``k``, within ``imu_sigma_v0_mps``;
        the latest bias estimate (zero at first), within the rig's bias sigmas at the start."""
        g, spec = self.graph, self.setup.imu
        if not g.has_nav(k - 1):
            dt = g.keyframe_t_s[k] - g.keyframe_t_s[k - 1]
            v_world = g.poses[k - 1][:3, :3] @ np.asarray(m.U)[:3, 3] / dt
            latest = g.biases[max(g.biases)] if g.biases else np.zeros(6)
            g.add_nav(k - 1, v_world, gtsam.imuBias.ConstantBias(latest[:3], latest[3:]), self.setup.imu_sigma_v0_mps, bias_sigmas(spec))
        b = g.biases[k - 1]
        t, gyro, accel = m.imu
        pim = preintegrate(self._imu_params, t, gyro, accel, g.keyframe_t_s[k - 1], g.keyframe_t_s[k], gtsam.imuBias.ConstantBias(b[:3], b[3:]))
        g.add_imu(k - 1, k, pim)

    def _restart(self, m: RestartMessage) -> None:
        g = self.graph
        if m.k != g.last_keyframe:
            raise DemGraphError(f"restart at keyframe {m.k} sent to the graph, whose last keyframe is {g.last_keyframe}")
        self.failed = False
        g.restart(m.T_world_body, m.P, m.point_priors)

    def final_estimates(self) -> tuple[dict[int, np.ndarray], dict[int, np.ndarray]]:
        """The latest estimate of every keyframe and landmark ever in the window."""
        return dict(self.graph.poses), dict(self.graph.points)


class InProcessGraph:
    """The graph in the estimator's process: each message is applied when sent, and its result is
    handed back at once, or ``delay`` keyframes later (a second process's lag, reproducibly)."""

    def __init__(self, setup: GraphSetup, delay: int = 0):
        self.worker = GraphWorker(setup)
        self.delay = delay
        self._results: list[GraphResult] = []
        self._held: list[GraphResult] = []  # results not yet handed back, oldest first

    def send(self, message) -> None:
        self._held.append(self.worker.apply([message]))
        self.worker.cut_if_due()
        while len(self._held) > self.delay:
            self._results.append(self._held.pop(0))

    def results(self) -> list[GraphResult]:
        out, self._results = self._results, []
        return out

    started = True  # (the graph is there from the first message)

    def wait_for(self, k: int, timeout_s: float | None) -> bool:
        """The graph can take keyframe ``k`` (here: always, its results are never missing, only held)."""
        return True

    def finish(self) -> tuple[list[GraphResult], tuple[dict[int, np.ndarray], dict[int, np.ndarray]]]:
        self._results.extend(self._held)
        self._held = []
        return self.results(), self.worker.final_estimates()

    def close(self) -> None:
        pass


def _serve(conn, one_at_a_time: bool = False) -> None:
    """The second process: apply whatever has arrived as one update (``one_at_a_time``: each message
    as its own, as :class:`InProcessGraph` does), answer, repeat. A broken connection (EOFError,
    OSError) is left to :func:`main`."""
    setup = conn.recv()
    try:
        worker = GraphWorker(setup)
    except Exception as exc:  # noqa: BLE001 - reported to the estimator, which raises it
        conn.send(("error", f"the graph process could not start: {exc}"))
        return
    conn.send(("ready", None))
    while True:
        messages = [conn.recv()]
        while not one_at_a_time and conn.poll():
            messages.append(conn.recv())
        finish = any(isinstance(m, str) and m == "finish" for m in messages)
        messages = [m for m in messages if not isinstance(m, str)]
        try:
            if messages:
                conn.send(("result", worker.apply(messages)))
                worker.cut_if_due()
            if finish:
                conn.send(("final", worker.final_estimates()))
                return
        except OSError:  # the connection, not the graph
            raise
        except Exception as exc:  # noqa: BLE001 - a bug in the graph: reported, the estimator ends the run with what it has
            conn.send(("error", f"the graph process failed: {type(exc).__name__}: {exc}"))
            return


_STOP = object()  # tells the sending thread to end
_READY_CHECK_S = 1.0  # how often the wait for the second process to start checks it is still there, seconds
_PR_SET_PDEATHSIG = 1  # linux/prctl.h


@contextmanager
def _sigint_held():
    """SIGINT held back from this thread meanwhile (it waits, or another thread takes it); a process
    started meanwhile starts with it held back, until it chooses what to do with it."""
    if not hasattr(signal, "pthread_sigmask"):
        yield
        return
    before = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, before)


def _follow_the_estimator(estimator_pid: int) -> bool:
    """The second process's signals: Ctrl-C ignored (a Ctrl-C held back since the start is dropped
    with it), SIGTERM ends the process at once and without a word (its default action), and on
    Linux the estimator's death sends it. False when the estimator has died already."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if hasattr(signal, "pthread_sigmask"):
        signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
    signal.signal(signal.SIGTERM, signal.SIG_DFL)  # (an ignored SIGTERM would be inherited)
    if sys.platform.startswith("linux"):
        try:
            ctypes.CDLL(None).prctl(_PR_SET_PDEATHSIG, ctypes.c_ulong(signal.SIGTERM))
        except (OSError, AttributeError):  # no prctl: the broken connection tells instead
            pass
    return os.getppid() == estimator_pid


class ProcessGraph:
    """The graph in a second process (another core); results come back when they are ready.

    The process is a fresh interpreter running this module (not a fork of the estimator's, and not
    ``multiprocessing``'s spawn, which would re-run the user's script), talking over a socket pair;
    its first message is the setup, and it answers once it has built its graph: this object is
    ready when made. It starts with Ctrl-C held back, so that one during its imports
    (a second or more) does not interrupt it either. On Linux it gets SIGTERM when the thread that
    made this object ends: make it in a thread that lasts the run.

    Messages leave through a thread of their own: the second process reads only between updates, so
    during a long one (the window's cut, a relinearisation) the socket's buffer fills after a few
    keyframes, and a send from the frame's own thread would wait there, perhaps while the process,
    answering with a result larger than the buffer, waits for the frame to read. :meth:`send` waits
    only to keep the front end within ``max_lag`` keyframes of the graph's newest result, and takes
    the results that arrive meanwhile."""

    def __init__(self, setup: GraphSetup, max_lag: int = 10, nice: int = 0, one_at_a_time: bool = False):
        ours, theirs = socket.socketpair()
        try:
            command = [sys.executable, "-m", __name__, str(theirs.fileno()), str(os.getpid()), str(int(nice)), str(int(one_at_a_time))]
            with _sigint_held():
                self._process = subprocess.Popen(command, pass_fds=(theirs.fileno(),))
        except OSError as exc:
            ours.close()
            raise DemGraphError(f"the graph process could not start: {exc}") from None
        finally:
            theirs.close()
        self._conn = Connection(ours.detach())
        self._conn.send(setup)
        self._wait_ready()
        self.max_lag = max_lag
        self._answered_k = -1  # the newest keyframe a result has answered (keyframes count from 0)
        self._outbox: queue.SimpleQueue = queue.SimpleQueue()
        self._early: list[GraphResult] = []  # results taken while send waited
        self._send_failed = threading.Event()
        self._sender = threading.Thread(target=self._send_loop, name="graph-sender", daemon=True)
        self._sender.start()
        atexit.register(self.close)  # an interrupted run does not leave the process behind

    def _wait_ready(self) -> None:
        """Until the process has imported and built its graph (a second or more): a run at the camera's
        rate then starts its clock with the graph able to take keyframes, rather than spending its
        first second waiting for it (0.9 s in the 150-frame bench at 500 points, 267feb5)."""
        while not self._conn.poll(_READY_CHECK_S):
            if self._process.poll() is not None:
                raise DemGraphError(f"the graph process ended while starting (exit code {self._process.returncode})")
        kind, _ = self._receive()  # (an error the process reports, or its end, raises here)
        if kind != "ready":
            raise DemGraphError(f"the graph process answered {kind!r} before it was ready")

    def _send_loop(self) -> None:
        while (message := self._outbox.get()) is not _STOP:
            try:
                self._conn.send(message)
            except OSError:  # the process has ended; the next send or receive says so
                self._send_failed.set()
                return

    def send(self, message) -> None:
        """Queue ``message`` for the second process; a keyframe more than ``max_lag`` after the one the
        graph last answered first waits for the graph's results."""
        k = message.k if isinstance(message, KeyframeMessage) else None
        while True:
            if self._send_failed.is_set():  # a broken pipe: the process has ended; its last words, if any, explain why
                while not self._conn.closed and self._conn.poll():
                    self._receive()
                raise DemGraphError("the graph process ended unexpectedly")
            if k is None or k - self._answered_k <= self.max_lag:
                break
            self._conn.poll(0.05)  # until a result comes (at most 50 ms: the sending thread may have failed meanwhile)
            self._early.extend(self._arrived())
        self._outbox.put(message)

    @property
    def started(self) -> bool:
        """The process has answered its first keyframe (until then it starts: imports, a second or more)."""
        self._early.extend(self._arrived())
        return self._answered_k >= 0

    def wait_for(self, k: int, timeout_s: float | None) -> bool:
        """Whether keyframe ``k`` is within ``max_lag`` keyframes of the newest the graph has answered,
        waiting at most ``timeout_s`` (None: as long as it takes) for its results to bring it there
        (they are kept for :meth:`results`)."""
        deadline = None if timeout_s is None else time.perf_counter() + timeout_s
        while True:
            self._early.extend(self._arrived())
            if k - self._answered_k <= self.max_lag:
                return True
            remaining = 0.05 if deadline is None else deadline - time.perf_counter()
            if remaining <= 0:
                return False
            if self._send_failed.is_set():  # the process has ended: the next send says why
                return True
            self._conn.poll(min(remaining, 0.05))

    def _receive(self):
        try:
            kind, payload = self._conn.recv()
        except (EOFError, OSError):  # (a connection reset: the process died with our messages unread)
            raise DemGraphError("the graph process ended unexpectedly") from None
        if kind == "error":
            raise DemGraphError(payload)
        return kind, payload

    def _arrived(self) -> list[GraphResult]:
        out = []
        while not self._conn.closed and self._conn.poll():
            out.append(self._receive()[1])
            self._answered_k = max(self._answered_k, out[-1].k)
        return out

    def results(self) -> list[GraphResult]:
        """The results that have arrived (none after :meth:`finish`, which takes them all)."""
        out, self._early = self._early + self._arrived(), []
        return out

    def finish(self) -> tuple[list[GraphResult], tuple[dict[int, np.ndarray], dict[int, np.ndarray]]]:
        """The results not yet taken, and the final estimates once every message sent has been
        applied. Whatever stops it (the process's end, Ctrl-C) stops the process too, and is raised."""
        try:
            self.send("finish")
            pending, self._early = self._early, []
            while True:
                kind, payload = self._receive()
                if kind == "final":
                    self._stop_sender()
                    self._conn.close()  # the process has ended
                    return pending, payload
                pending.append(payload)
        except BaseException:
            self.close()
            raise

    def _stop_sender(self, timeout_s: float = 5.0) -> None:
        self._outbox.put(_STOP)
        self._sender.join(timeout_s)

    def close(self) -> None:
        """Stop the process: after :meth:`finish` it ends by itself; before, it is terminated (the
        run stopped early: an error, Ctrl-C). At the interpreter's exit, when no one has called it."""
        if not self._conn.closed:  # (after finish the thread has ended already)
            self._process.terminate()  # first: a send waiting for the process then fails at once
            self._stop_sender()
            self._conn.close()
        try:
            self._process.wait(timeout=5)
        except subprocess.TimeoutExpired:
            self._process.kill()
            self._process.wait()
        atexit.unregister(self.close)


class DelayedProcessGraph(ProcessGraph):
    """The graph in a second process that takes one message at a time, its results handed back exactly
    ``delay`` messages after their own, waiting for one that is not back when due: what
    :class:`InProcessGraph` with that delay gives, number for number, while the graph's updates run
    beside the frames between. For offline runs: a frame may wait, so the process keeps the front
    end's priority."""

    def __init__(self, setup: GraphSetup, delay: int):
        if delay < 1:
            raise ValueError(f"a delayed graph needs a delay of at least one keyframe, got {delay}")
        super().__init__(setup, max_lag=sys.maxsize, one_at_a_time=True)
        self.delay = delay
        self._sent = 0  # messages sent, each of which has one result
        self._handed = 0  # results handed back

    def send(self, message) -> None:
        super().send(message)
        self._sent += 1

    @property
    def started(self) -> bool:
        return True  # (nothing waits for the start: a result due before the process answers is waited for)

    def wait_for(self, k: int, timeout_s: float | None) -> bool:
        return True  # (the wait is for a result when due, in results())

    def results(self) -> list[GraphResult]:
        """The results due: every message's but the last ``delay``'s, in order, waiting for them."""
        due = self._sent - self.delay
        self._early.extend(self._arrived())
        while self._handed + len(self._early) < due:
            self._early.append(self._receive()[1])
            self._answered_k = max(self._answered_k, self._early[-1].k)
        n = max(due - self._handed, 0)
        out, self._early = self._early[:n], self._early[n:]
        self._handed += n
        return out

    def finish(self) -> tuple[list[GraphResult], tuple[dict[int, np.ndarray], dict[int, np.ndarray]]]:
        pending, final = super().finish()
        self._handed = self._sent  # every result is handed back now
        return pending, final


def _lower_priority(nice: int) -> None:
    """This process's scheduling priority lowered by ``nice`` (where the system has ``os.nice``), so
    that where the cores are short, the front end's frames go first and the graph falls behind."""
    if nice > 0 and hasattr(os, "nice"):
        try:
            os.nice(nice)
        except OSError:  # not allowed here: the graph runs at the front end's priority
            pass


def main(fd: int, estimator_pid: int, nice: int = 0, one_at_a_time: bool = False) -> None:
    """The second process, connected on ``fd`` to the estimator's process ``estimator_pid``, its
    priority lowered by ``nice``; ``one_at_a_time``: see :func:`_serve`."""
    if not _follow_the_estimator(estimator_pid):
        return
    _lower_priority(nice)
    try:
        _serve(Connection(fd), one_at_a_time)
    except (EOFError, OSError):  # the estimator has gone (ended early, interrupted, killed): no one to answer
        pass


if __name__ == "__main__":
    # through the package, so the messages unpickle to the classes the worker checks against
    from dem_graph.estimators.graph_worker import main as package_main

    package_main(int(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3]), bool(int(sys.argv[4])))


__all__ = [
    "DelayedProcessGraph",
    "GraphResult",
    "GraphSetup",
    "GraphWorker",
    "InProcessGraph",
    "KeyframeMessage",
    "NewLandmark",
    "ProcessGraph",
    "RestartMessage",
]
