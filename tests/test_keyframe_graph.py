"""The keyframe graph's own marginalisation against a full smoothing of every factor."""

from __future__ import annotations

import gtsam
import numpy as np
from gtsam.symbol_shorthand import L, X

from dem_graph.estimators.graph_factors import odometry_factor, point_in_frame_factors
from dem_graph.estimators.keyframe_graph import KeyframeGraph
from dem_graph.geometry.lie import retract
from dem_graph.geometry.se3 import invert, transform_points


def _scene(rng):
    """A vehicle driving 0.2 m per keyframe with a slow turn, over points on the ground ahead."""
    T = [np.eye(4)]
    for _ in range(15):
        T.append(T[-1] @ retract(np.eye(4), np.array([0, 0, 0.03, 0.2, 0, 0])))
    X_world = np.column_stack([rng.uniform(1, 5, 60), rng.uniform(-2, 2, 60), rng.normal(0, 0.05, 60)])
    return np.array(T), X_world


def _drive(lag_s: float, cut_while_driving: bool, relinearize_threshold: float = 1e-5):
    """Feed the scene to a keyframe graph (odometry and 1 cm point-in-frame measurements), cutting
    the window whenever it is due if ``cut_while_driving``; returns the graph, every factor in one
    graph with the initial guesses, and how many cuts were made."""
    rng = np.random.default_rng(3)
    T_true, X_true = _scene(rng)
    sigma_m, dt_s = 0.01, 0.1
    P0 = np.diag([1e-6] * 6)
    Q = np.diag([1e-4] * 3 + [4e-4] * 3)
    g = KeyframeGraph(T_true[0], P0, 0.0, lag_s=lag_s, marginalize_every_s=0.1, relinearize_threshold=relinearize_threshold)
    full = gtsam.NonlinearFactorGraph()
    full.add(gtsam.PriorFactorPose3(X(0), gtsam.Pose3(T_true[0]), gtsam.noiseModel.Gaussian.Covariance(P0)))
    guess = gtsam.Values()
    guess.insert(X(0), gtsam.Pose3(T_true[0]))
    seen: set[int] = set()
    cuts = 0
    for k in range(1, len(T_true)):
        U = retract(invert(T_true[k - 1]) @ T_true[k], rng.multivariate_normal(np.zeros(6), Q))
        T_guess = g.poses[k - 1] @ U
        g.add_keyframe(k * dt_s, T_guess)
        guess.insert(X(k), gtsam.Pose3(T_guess))
        factors = [odometry_factor(X(k - 1), X(k), U, Q)]
        # the points 1-4 m ahead of this keyframe, measured in its frame
        p_body = transform_points(invert(T_true[k]), X_true)
        for j in map(int, np.flatnonzero((p_body[:, 0] > 1) & (p_body[:, 0] < 4))):
            z = p_body[j] + rng.normal(0, sigma_m, 3)
            if j not in seen:
                seen.add(j)
                X_guess = transform_points(T_guess, z[None])[0]
                g.add_point(j, X_guess)
                guess.insert(L(j), gtsam.Point3(*X_guess))
            g.observed(j)
            factors += point_in_frame_factors(X(k), L(j), z, sigma_m**2 * np.eye(3))
        for f in factors:
            g.add_factor(f)
            full.add(f)
        g.update()
        if cut_while_driving and g.marginalization_due:
            g.marginalize()
            cuts += 1
    for _ in range(5):  # iSAM2 takes one Gauss-Newton step per update: converge
        g.update()
    return g, full, guess, cuts


def _gaps_to_full_smoothing(g: KeyframeGraph, full, guess):
    """Per variable in the window: its distance from the full smoothing (m) and that estimate's sigma (m)."""
    reference = gtsam.LevenbergMarquardtOptimizer(full, guess).optimize()
    marginals = gtsam.Marginals(full, reference)
    gaps, sigmas = [], []
    for key in g.timestamps():
        sym = gtsam.Symbol(key)
        if sym.chr() == ord("x"):
            gaps.append(np.linalg.norm(g.poses[sym.index()][:3, 3] - reference.atPose3(key).translation()))
            sigmas.append(np.sqrt(np.trace(marginals.marginalCovariance(key)[3:, 3:])))
        else:
            gaps.append(np.linalg.norm(g.points[sym.index()] - reference.atPoint3(key)))
            sigmas.append(np.sqrt(np.trace(marginals.marginalCovariance(key))))
    return np.array(gaps), np.array(sigmas)


def test_marginalising_a_converged_window_is_exact():
    """Cut once, after every measurement is in and the estimate has converged: what is left of the
    window sits where a full smoothing of every factor puts it (Gaussian elimination is exact at
    the linearisation point), to 10 micrometres."""
    g, full, guess, _ = _drive(lag_s=100.0, cut_while_driving=False)
    g.lag_s = 0.35
    assert g.marginalize() > 20
    gaps, _ = _gaps_to_full_smoothing(g, full, guess)
    assert len(gaps) >= 10
    assert gaps.max() < 1e-5


def test_marginalising_while_driving_stays_close_to_the_full_smoothing():
    """Cut the window every 0.1 s while driving: each cut linearises at the estimate of its time,
    so the window drifts from the full smoothing by a small fraction of its own uncertainty (here
    at most 3.3 % of a sigma, 2.5 mm): at most 5 % of a sigma, and the window stays bounded."""
    g, full, guess, cuts = _drive(lag_s=0.35, cut_while_driving=True)
    assert cuts >= 3
    window = g.timestamps()
    assert min(window.values()) >= g.keyframe_t_s[-1] - 0.35 - 0.1 - 1e-9
    gaps, sigmas = _gaps_to_full_smoothing(g, full, guess)
    assert len(gaps) >= 10
    assert np.max(gaps / sigmas) < 0.05


def test_the_window_read_at_once_is_the_smoothers_estimate_and_what_left_owns_its_arrays():
    """After every update the graph reads the whole window in one call per kind: each keyframe's
    pose, each landmark and each velocity must be, to the last bit, what the smoother gives for that
    variable read alone; what the cuts marginalised is kept in arrays of its own."""
    g, _, _, cuts = _drive(lag_s=0.35, cut_while_driving=True)
    assert cuts >= 3
    k = g.last_keyframe
    v_world = np.array([2.0, 0.1, -0.05])
    g.add_nav(k, v_world, gtsam.imuBias.ConstantBias(np.array([0.01, 0.0, 0.0]), np.zeros(3)), sigma_v_mps=0.1, sigma_bias=np.full(6, 0.01))
    g.update()
    estimate = g.isam.calculateEstimate()
    window = g.window_estimates()
    assert len(window[0]) >= 3 and len(window[1]) >= 10
    for k_pose, T in window[0].items():
        assert np.array_equal(T, estimate.atPose3(X(k_pose)).matrix())
    for j, X_world in window[1].items():
        assert np.array_equal(X_world, estimate.atPoint3(L(j)))
    assert np.array_equal(g.velocities[k], np.asarray(estimate.atVector(gtsam.symbol("v", k))))
    assert np.allclose(g.velocities[k], v_world, atol=1e-6)  # only its prior says where it is
    left = [j for j in g.points if j not in window[1]]
    assert len(left) >= 10
    read_at_once = next(iter(window[1].values())).base  # the window's landmarks: rows of one array
    assert all(X_world.base is read_at_once for X_world in window[1].values())
    assert not any(np.shares_memory(g.points[j], read_at_once) for j in left)
