"""The online graph: keyframe poses and map points in an iSAM2 whose window we marginalise ourselves.

Variables are ``X(k)``, the body pose ``T_world_body`` of keyframe k, and ``L(j)``, the world
position of landmark ``j`` (metres). Each variable carries a timestamp: a keyframe its time, a point
the time of the last keyframe that observed it. With an IMU (:meth:`KeyframeGraph.add_imu`), a
keyframe also has ``V(k)``, the body origin's world velocity (m/s), and ``B(k)``, the IMU's biases
(gtsam's ``imuBias.ConstantBias``: accelerometer m/s^2, gyroscope rad/s), with its time; between two
such keyframes a ``CombinedImuFactor`` holds the samples preintegrated.

Updates are incremental (``gtsam.ISAM2``), with the landmarks ordered before the keyframe poses
(iSAM2's constrained ordering): by default iSAM2 puts every variable a new factor touches last, so
the ~150 landmarks a keyframe observes formed one dense clique at the root of the Bayes tree; with the
poses last, each landmark is a small clique under the poses, and the newest pose sits in the root,
where its marginal is cheap (docs/isam2_design.md, "The graph keeps up").

The window is cut by :meth:`KeyframeGraph.marginalize`,
once it spans more than ``lag_s + marginalize_every_s``: the variables older than ``lag_s`` behind
the newest keyframe are eliminated from the factors that touch them, linearised at the current
estimate, and what they knew about the rest stays as linear factors (``LinearContainerFactor``);
a new iSAM2 starts from the remaining factors. So the cost of an update follows the window, not the
length of the run.

gtsam's ``IncrementalFixedLagSmoother``, which does this at every update inside the Bayes tree, is
not used: its marginalisation lost the window where the same graph without marginalisation did not
(docs/isam2_design.md).

The latest estimate of every variable ever in the window is kept (:attr:`poses`, :attr:`points`):
a marginalised variable keeps the value it had when it left.
"""

from __future__ import annotations

import time

import gtsam
import numpy as np
from gtsam.symbol_shorthand import B, L, V, X

from dem_graph.errors import DemGraphError, one_line


class GraphUpdateError(DemGraphError):
    """An iSAM2 update failed (an indeterminate system, say); the smoother's state is unusable."""


class KeyframeGraph:
    def __init__(
        self,
        T_world_body_0: np.ndarray,
        P0: np.ndarray,
        t0_s: float,
        lag_s: float,
        relinearize_threshold: float = 0.01,
        relinearize_skip: int = 1,
        marginalize_every_s: float = 0.5,
        optimizer: str = "gauss_newton",
    ):
        self._params = gtsam.ISAM2Params()
        self._params.setRelinearizeThreshold(relinearize_threshold)
        self._params.relinearizeSkip = relinearize_skip
        if optimizer == "dogleg":
            self._params.setOptimizationParams(gtsam.ISAM2DoglegParams())
        elif optimizer != "gauss_newton":
            raise DemGraphError(f"unknown graph optimizer {optimizer!r}: gauss_newton or dogleg")
        self.lag_s = float(lag_s)
        self.marginalize_every_s = float(marginalize_every_s)
        self.poses: dict[int, np.ndarray] = {}  # keyframe index -> T_world_body, latest estimate
        self.points: dict[int, np.ndarray] = {}  # landmark -> X_world, latest estimate
        self.velocities: dict[int, np.ndarray] = {}  # keyframe -> world velocity (m/s), latest estimate (IMU only)
        self.biases: dict[int, np.ndarray] = {}  # keyframe -> IMU biases [accel m/s^2 (3), gyro rad/s (3)], latest estimate
        self.keyframe_t_s: list[float] = []
        self.phase_s: dict[str, float] = {}  # seconds spent per phase since the last take_phases()
        self.recoveries = 0  # indeterminate windows eliminated again with the velocities and biases last (:meth:`_start_isam`)
        self._new_isam()
        self._clear_pending()
        k = self.add_keyframe(t0_s, T_world_body_0)
        self._prior_on_pose(k, T_world_body_0, P0)
        self.update()

    def _new_isam(self) -> None:
        self.isam = gtsam.ISAM2(self._params)
        self._factors = gtsam.NonlinearFactorGraph()  # every factor the current iSAM2 holds
        self._factor_keys: list[frozenset[int]] = []  # the keys of each of them, in the same order
        # the variables in the window with their times, seconds: keyframe -> t, landmark -> t
        self._pose_t: dict[int, float] = {}
        self._point_t: dict[int, float] = {}
        self._nav_t: dict[int, float] = {}  # keyframes with velocity and bias variables -> t

    # --- building the next update -----------------------------------------------------------
    @property
    def last_keyframe(self) -> int:
        return len(self.keyframe_t_s) - 1

    def add_keyframe(self, t_s: float, T_world_body_guess: np.ndarray) -> int:
        """A new keyframe pose variable at ``t_s``, starting from the guess; returns its index."""
        k = self.skip_keyframe(t_s, T_world_body_guess)
        self._insert_pose(k, T_world_body_guess)
        return k

    def skip_keyframe(self, t_s: float, T_world_body: np.ndarray) -> int:
        """Number keyframe ``t_s`` and keep ``T_world_body`` as its estimate, without a variable
        (a keyframe that arrives while the graph waits for a restart); returns its index."""
        if self.keyframe_t_s and t_s <= self.keyframe_t_s[-1]:
            raise DemGraphError(f"keyframe times must increase: {t_s} after {self.keyframe_t_s[-1]}")
        k = len(self.keyframe_t_s)
        self.keyframe_t_s.append(float(t_s))
        self.poses[k] = np.array(T_world_body, dtype=float)
        return k

    def _insert_pose(self, k: int, T_world_body: np.ndarray) -> None:
        self._new_values.insert(X(k), gtsam.Pose3(np.asarray(T_world_body, dtype=float)))
        self._new_pose_t[k] = self.keyframe_t_s[k]

    def add_point(self, landmark: int, X_world_guess: np.ndarray) -> None:
        """A new landmark variable, stamped with the newest keyframe's time."""
        self._new_values.insert(L(landmark), gtsam.Point3(*np.asarray(X_world_guess, dtype=float)))
        self._new_point_t[int(landmark)] = self.keyframe_t_s[-1]
        self.points[int(landmark)] = np.array(X_world_guess, dtype=float)

    def observed(self, landmark: int) -> None:
        """Stamp a landmark with the newest keyframe's time (it was measured there)."""
        self._new_point_t[int(landmark)] = self.keyframe_t_s[-1]

    def add_factor(self, factor: gtsam.NonlinearFactor) -> None:
        self._new_factors.add(factor)

    def in_window(self, landmark: int) -> bool:
        """The landmark is a variable of the smoother (or will be at the next update)."""
        return int(landmark) in self._point_t or int(landmark) in self._new_point_t

    def pose_in_window(self, k: int) -> bool:
        """Keyframe ``k`` is a variable of the smoother (or will be at the next update)."""
        return int(k) in self._pose_t or int(k) in self._new_pose_t

    def window_estimates(self) -> tuple[dict[int, np.ndarray], dict[int, np.ndarray]]:
        """The latest estimates of the keyframes and of the landmarks in the window."""
        return {k: self.poses[k] for k in self._pose_t}, {j: self.points[j] for j in self._point_t}

    def timestamps(self) -> dict[int, float]:
        """Every variable in the window (gtsam key) with its time, seconds."""
        nav = {key(k): t for k, t in self._nav_t.items() for key in (V, B)}
        return {**{X(k): t for k, t in self._pose_t.items()}, **{L(j): t for j, t in self._point_t.items()}, **nav}

    def has_nav(self, k: int) -> bool:
        """Keyframe ``k`` has velocity and bias variables in the window (or will at the next update)."""
        return k in self._nav_t or k in self._new_nav_t

    def add_nav(self, k: int, v_world: np.ndarray, bias: gtsam.imuBias.ConstantBias, sigma_v_mps: float | None = None, sigma_bias: np.ndarray | None = None) -> None:
        """Velocity and bias variables for keyframe ``k``, starting at ``v_world`` and ``bias``; with
        sigmas, a prior at those values (``sigma_bias``: 6, accelerometer then gyroscope)."""
        self._new_values.insert(V(k), np.asarray(v_world, dtype=float))
        self._new_values.insert(B(k), bias)
        self._new_nav_t[k] = self.keyframe_t_s[k]
        self.velocities[k] = np.array(v_world, dtype=float)
        self.biases[k] = np.asarray(bias.vector(), dtype=float).copy()
        if sigma_v_mps is not None:
            self.add_factor(gtsam.PriorFactorVector(V(k), np.asarray(v_world, dtype=float), gtsam.noiseModel.Isotropic.Sigma(3, float(sigma_v_mps))))
        if sigma_bias is not None:
            self.add_factor(gtsam.PriorFactorConstantBias(B(k), bias, gtsam.noiseModel.Diagonal.Sigmas(np.asarray(sigma_bias, dtype=float))))

    def add_imu(self, k_prev: int, k: int, pim: gtsam.PreintegratedCombinedMeasurements) -> None:
        """The IMU's preintegrated samples between keyframes ``k_prev`` and ``k`` (``k_prev`` must
        have velocity and bias variables; ``k``'s start from the prediction)."""
        bias = gtsam.imuBias.ConstantBias(self.biases[k_prev][:3], self.biases[k_prev][3:])
        if not self.has_nav(k):
            predicted = pim.predict(gtsam.NavState(gtsam.Pose3(self.poses[k_prev]), self.velocities[k_prev]), bias)
            self.add_nav(k, predicted.velocity(), bias)
        self.add_factor(gtsam.CombinedImuFactor(X(k_prev), V(k_prev), X(k), V(k), B(k_prev), B(k), pim))

    def _clear_pending(self) -> None:
        self._new_factors = gtsam.NonlinearFactorGraph()
        self._new_values = gtsam.Values()
        self._new_pose_t: dict[int, float] = {}
        self._new_point_t: dict[int, float] = {}
        self._new_nav_t: dict[int, float] = {}

    def _prior_on_pose(self, k: int, T_world_body: np.ndarray, P: np.ndarray) -> None:
        T = gtsam.Pose3(np.asarray(T_world_body, dtype=float))
        self.add_factor(gtsam.PriorFactorPose3(X(k), T, gtsam.noiseModel.Gaussian.Covariance(np.asarray(P, dtype=float))))

    # --- solving ----------------------------------------------------------------------------
    def _ordering(self, poses, nav=(), nav_last: bool = False) -> gtsam.ISAM2UpdateParams:
        """iSAM2's update parameters with the keyframe poses ``poses`` (and the velocities and biases
        of the keyframes ``nav``) eliminated after every landmark; with ``nav_last``, the velocities
        and biases after the poses."""
        groups = gtsam.KeyGroupMap()
        for k in poses:
            groups.insert2(X(k), 1)  # landmarks: group 0, first
        for k in nav:
            groups.insert2(V(k), 2 if nav_last else 1)
            groups.insert2(B(k), 2 if nav_last else 1)
        params = gtsam.ISAM2UpdateParams()
        params.constrainedKeys = groups
        return params

    def _timed(self, phase: str, t0_s: float) -> float:
        now = time.perf_counter()
        self.phase_s[phase] = self.phase_s.get(phase, 0.0) + now - t0_s
        return now

    def take_phases(self) -> dict[str, float]:
        """Seconds spent per phase (``solve``: iSAM2's updates; ``estimate``: reading the estimate
        back; ``cut``: the marginal of what leaves the window; ``rebuild``: the new iSAM2 after it;
        ``marginal``: a pose marginal) since the last call."""
        phases, self.phase_s = self.phase_s, {}
        return phases

    def update(self, iterations: int = 1) -> None:
        """An iSAM2 update with what was added since the last one, and ``iterations - 1`` more
        relinearisation steps; refreshes the estimates."""
        t0 = time.perf_counter()
        ordering = self._ordering([*self._pose_t, *self._new_pose_t], [*self._nav_t, *self._new_nav_t])
        try:
            self.isam.update(self._new_factors, self._new_values, ordering)
            for _ in range(iterations - 1):
                self.isam.update(gtsam.NonlinearFactorGraph(), gtsam.Values(), ordering)
        except RuntimeError as exc:  # gtsam reports an indeterminate system or a missing key this way
            text = one_line(exc)  # with the variable gtsam names
            if not self._recoverable(text):
                self._clear_pending()
                raise GraphUpdateError(f"the graph update at keyframe {self.last_keyframe} (t = {self.keyframe_t_s[-1]:.3f} s) failed: {text}") from None
            self._recover(text)  # the IMU's stiff factors: the window eliminated again, its velocities and biases last
        t1 = self._timed("solve", t0)
        self._factors.push_back(self._new_factors)
        self._factor_keys.extend(frozenset(self._new_factors.at(i).keys()) for i in range(self._new_factors.size()))
        self._pose_t.update(self._new_pose_t)
        self._point_t.update(self._new_point_t)
        self._nav_t.update(self._new_nav_t)
        self._clear_pending()
        self._read_window(self.isam.calculateEstimate())
        self._timed("estimate", t1)

    def _read_leaving(self, values: gtsam.Values, poses: list[int], points: list[int]) -> None:
        """The estimates of the keyframes ``poses`` (their velocities and biases too) and landmarks
        ``points`` about to be marginalised, from ``values``, each into an array of its own (they
        are kept for the rest of the run)."""
        for k in poses:
            self.poses[k] = values.atPose3(X(k)).matrix()
            if k in self._nav_t:
                self.velocities[k] = np.asarray(values.atVector(V(k)), dtype=float)
                self.biases[k] = np.asarray(values.atConstantBias(B(k)).vector(), dtype=float)
        for j in points:
            self.points[j] = values.atPoint3(L(j))

    def _read_window(self, values: gtsam.Values) -> None:
        """Every window variable's estimate from ``values``, each kind in one call (gtsam's
        ``extractVectors``/``extractPose3`` give the values of one symbol in key order, which is the
        index order: 0.3 against 1.3 ms per update for 600 landmarks and 50 keyframes read one by
        one). The kept estimates are rows of those arrays until the next read (:meth:`_read_leaving`
        gives what leaves the window arrays of its own)."""
        point_ids, pose_ids, nav_ids = sorted(self._point_t), sorted(self._pose_t), sorted(self._nav_t)
        # (the memory order of each value as gtsam gives a value read alone: numpy's products with it
        # then round the same)
        xyz = np.ascontiguousarray(gtsam.utilities.extractVectors(values, "l")) if point_ids else np.empty((0, 3))
        rows = gtsam.utilities.extractPose3(values)  # [R row by row (9), t (3)] per keyframe
        v_world = np.ascontiguousarray(gtsam.utilities.extractVectors(values, "v")) if nav_ids else np.empty((0, 3))
        if (len(xyz), len(rows), len(v_world)) != (len(point_ids), len(pose_ids), len(nav_ids)):  # (never seen: a restart, not a crash)
            raise GraphUpdateError(
                f"the smoother at keyframe {self.last_keyframe} holds {len(xyz)} landmarks, {len(rows)} poses and {len(v_world)} velocities; "
                f"its window has {len(point_ids)}, {len(pose_ids)} and {len(nav_ids)}"
            )
        T_transposed = np.zeros((len(pose_ids), 4, 4))  # each pose in column order, as Pose3.matrix() gives it
        T_transposed[:, :3, :3] = rows[:, :9].reshape(-1, 3, 3).transpose(0, 2, 1)
        T_transposed[:, 3, :3] = rows[:, 9:]
        T_transposed[:, 3, 3] = 1.0
        T = T_transposed.transpose(0, 2, 1)
        self.poses.update(zip(pose_ids, T))
        self.points.update(zip(point_ids, xyz))
        self.velocities.update(zip(nav_ids, v_world))
        for k in nav_ids:
            self.biases[k] = np.asarray(values.atConstantBias(B(k)).vector(), dtype=float)

    def _recoverable(self, failure: str) -> bool:
        """gtsam found the system indeterminate where the window has the IMU's velocities and biases."""
        return bool(self._nav_t or self._new_nav_t) and "Indeterminate" in failure

    def _window_values(self) -> gtsam.Values:
        """The window's variables at their kept estimates, with the pending new ones."""
        values = gtsam.Values()
        for k in self._pose_t:
            values.insert(X(k), gtsam.Pose3(self.poses[k]))
        for j in self._point_t:
            values.insert(L(j), gtsam.Point3(*self.points[j]))
        for k in self._nav_t:
            values.insert(V(k), self.velocities[k])
            values.insert(B(k), gtsam.imuBias.ConstantBias(self.biases[k][:3], self.biases[k][3:]))
        values.insert(self._new_values)
        return values

    def _recover(self, failure: str) -> None:
        """After iSAM2 found the window indeterminate (an update whose re-elimination put a
        keyframe's velocity and biases, tied to their neighbours with information near 1e11 by the
        IMU's factors, before the poses), a new iSAM2 over every factor, from the kept estimates, with
        the velocities and biases eliminated after the poses (docs/imu.md). Raises
        :class:`GraphUpdateError` when that fails too."""
        factors = gtsam.NonlinearFactorGraph(self._factors)
        factors.push_back(self._new_factors)
        values = self._window_values()
        self._start_isam(factors, values, failure)

    def _start_isam(self, factors: gtsam.NonlinearFactorGraph, values: gtsam.Values, failure: str | None = None) -> None:
        """A new iSAM2 over ``factors`` from ``values`` (the window's variable times kept): landmarks,
        then poses, velocities and biases; if iSAM2 finds that indeterminate (or ``failure`` says the
        last try did), again with the velocities and biases after the poses (counted in
        :attr:`recoveries`; from then on, every new iSAM2 of the run is built that way)."""
        state, kept = (self._pose_t, self._point_t, self._nav_t), (self._factors, self._factor_keys)
        poses, nav = [*self._pose_t, *self._new_pose_t], [*self._nav_t, *self._new_nav_t]
        # once a window was indeterminate, its successors are built the safe way at once
        orderings = (True,) if failure is not None or self.recoveries else (False, True)
        for nav_last in orderings:
            self._new_isam()
            (self._pose_t, self._point_t, self._nav_t), (self._factors, self._factor_keys) = state, kept
            try:
                self.isam.update(factors, values, self._ordering(poses, nav, nav_last=nav_last))
            except RuntimeError as exc:
                failure = one_line(exc)
                if self._recoverable(failure):
                    continue
                break
            self.recoveries += int(failure is not None)
            return
        self._clear_pending()
        raise GraphUpdateError(f"the graph at keyframe {self.last_keyframe} (t = {self.keyframe_t_s[-1]:.3f} s) is indeterminate: {failure}")

    @property
    def marginalization_due(self) -> bool:
        """The window spans more than ``lag_s + marginalize_every_s``."""
        oldest = min(min(self._pose_t.values(), default=np.inf), min(self._point_t.values(), default=np.inf))
        return oldest < self.keyframe_t_s[-1] - self.lag_s - self.marginalize_every_s

    def marginalize(self) -> int:
        """Marginalise every variable older than ``lag_s`` behind the newest keyframe; returns how many.

        The factors touching them are linearised at the current estimate and the old variables
        eliminated (timed as ``cut``); the remaining Gaussian factors on the variables they shared
        with the window enter a new iSAM2 as ``LinearContainerFactor``s, with every factor not
        touching them, started from the window's estimate (``rebuild``). A marginalised variable
        keeps its estimate; later observations of it are not taken."""
        t0 = time.perf_counter()
        t_cut = self.keyframe_t_s[-1] - self.lag_s
        old_poses = [k for k, t in self._pose_t.items() if t < t_cut]
        old_points = [j for j, t in self._point_t.items() if t < t_cut]
        if not old_poses and not old_points:
            return 0
        values = self.isam.calculateEstimate()
        self._read_leaving(values, old_poses, old_points)  # what the marginalised variables keep
        old_nav = [k for k in old_poses if k in self._nav_t]
        old = {X(k) for k in old_poses} | {L(j) for j in old_points} | {key(k) for k in old_nav for key in (V, B)}
        touching, kept_indices = gtsam.NonlinearFactorGraph(), []
        for i, keys in enumerate(self._factor_keys):
            if old.isdisjoint(keys):
                kept_indices.append(i)
            else:
                touching.add(self._factors.at(i))
        try:
            _, marginal = touching.linearize(values).eliminatePartialMultifrontal(gtsam.KeyVector(sorted(old)))
        except RuntimeError as exc:
            raise GraphUpdateError(f"marginalising the window before t = {t_cut:.3f} s failed: {one_line(exc)}") from None
        linear = [gtsam.LinearContainerFactor(marginal.at(i), values) for i in range(marginal.size()) if marginal.at(i) is not None and len(marginal.at(i).keys()) > 0]
        for k in old_poses:
            del self._pose_t[k]
        for j in old_points:
            del self._point_t[j]
        for k in old_nav:
            del self._nav_t[k]
        t1 = self._timed("cut", t0)
        kept, kept_keys = gtsam.NonlinearFactorGraph(), []
        for i in kept_indices:
            kept.add(self._factors.at(i))
            kept_keys.append(self._factor_keys[i])
        for f in linear:
            kept.add(f)
            kept_keys.append(frozenset(f.keys()))
        for key in old:
            values.erase(key)  # what is left: the window's estimate, the new iSAM2's start
        try:
            self._start_isam(kept, values)
        except GraphUpdateError as exc:
            raise GraphUpdateError(f"restarting iSAM2 after marginalising the window before t = {t_cut:.3f} s failed: {exc}") from None
        self._factors, self._factor_keys = kept, kept_keys
        # (the estimates are read at the next update: the new iSAM2 starts where the window was)
        self._timed("rebuild", t1)
        return len(old)

    def restart(self, T_world_body: np.ndarray, P: np.ndarray, point_priors: dict[int, tuple[np.ndarray, np.ndarray]]) -> None:
        """Start a new smoother from the newest keyframe after a failed update: its pose and the
        given points (landmark -> (X_world, 3x3 covariance)) enter with priors at their estimates;
        what the failed update held is dropped. Keyframe numbering and kept estimates continue."""
        self._new_isam()
        self._clear_pending()
        k = self.last_keyframe
        self._insert_pose(k, T_world_body)
        self._prior_on_pose(k, T_world_body, P)
        for lm, (X_world, Sigma) in point_priors.items():
            self.add_point(lm, X_world)
            self.add_factor(gtsam.PriorFactorPoint3(L(lm), gtsam.Point3(*X_world), gtsam.noiseModel.Gaussian.Covariance(np.asarray(Sigma, dtype=float))))
        self.update()

    def pose_covariance(self, k: int) -> np.ndarray:
        """Marginal covariance of keyframe ``k``'s pose (6x6, [rotation, translation], right perturbation)."""
        t0 = time.perf_counter()
        P = np.asarray(self.isam.marginalCovariance(X(k)))
        self._timed("marginal", t0)
        return P


__all__ = ["GraphUpdateError", "KeyframeGraph"]
