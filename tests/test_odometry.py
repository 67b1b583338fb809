"""Odometry composition between arbitrary times (shared by every estimator's prediction)."""

from __future__ import annotations

import numpy as np

from dem_graph.datasets.events import Odometry
from dem_graph.estimators.odometry import OdometryIntegrator
from dem_graph.geometry.lie import adjoint
from dem_graph.geometry.se3 import invert, make_pose, rotation_from_rpy


def _step(k):
    return make_pose(rotation_from_rpy(0.001 * k, -0.002, 0.01 + 0.001 * k), [0.03, 0.001 * k, -0.0005])


def test_whole_increments_compose_exactly_with_their_covariance():
    integ = OdometryIntegrator(0.0)
    Qs = [np.diag(np.full(6, 1e-6 * (k + 1))) for k in range(4)]
    for k in range(4):
        integ.add(Odometry(0.02 * (k + 1), 0.02 * k, _step(k), Qs[k]))
    assert integ.covers(0.08) and not integ.covers(0.081)
    U, Q = integ.increment(0.04)
    np.testing.assert_allclose(U, _step(0) @ _step(1), atol=1e-12)
    A = adjoint(invert(_step(1)))
    np.testing.assert_allclose(Q, A @ Qs[0] @ A.T + Qs[1], atol=1e-15)
    # the next call starts where this one stopped
    U, _ = integ.increment(0.08)
    np.testing.assert_allclose(U, _step(2) @ _step(3), atol=1e-12)


def test_a_cut_increment_is_shared_between_calls_and_the_end_is_extrapolated():
    integ = OdometryIntegrator(0.0)
    step = make_pose(rotation_from_rpy(0.0, 0.0, 0.02), [0.04, 0.0, 0.0])
    for k in range(2):
        integ.add(Odometry(0.02 * (k + 1), 0.02 * k, step, np.eye(6) * 1e-6))
    U1, _ = integ.increment(0.03)  # one and a half increments
    U2, _ = integ.increment(0.04)  # the other half
    # rotations compose exactly; a part of an increment is the straight chord of its translation,
    # so the split translation differs at second order: |t| * angle / 2 = 0.04 * 0.02 / 2
    np.testing.assert_allclose((U1 @ U2)[:3, :3], (step @ step)[:3, :3], atol=1e-12)
    np.testing.assert_allclose((U1 @ U2)[:3, 3], (step @ step)[:3, 3], atol=0.04 * 0.02 / 2)
    # past the last increment: extrapolated at its rate
    U3, _ = integ.increment(0.05)
    np.testing.assert_allclose(U3[:3, 3], [0.02, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(np.arctan2(U3[1, 0], U3[0, 0]), 0.01, atol=1e-12)
