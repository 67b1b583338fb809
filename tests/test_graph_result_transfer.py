"""A graph result crosses to the estimator's process with the window's estimates packed one array per
kind (:class:`~dem_graph.estimators.graph_worker.GraphResult`'s pickling): the same numbers arrive."""

from __future__ import annotations

import pickle

import numpy as np

from dem_graph.estimators.graph_client import _take_window
from dem_graph.estimators.graph_worker import GraphResult


def test_a_result_arrives_with_every_estimate_to_the_bit_and_in_its_order():
    rng = np.random.default_rng(7)
    poses = {k: rng.normal(size=(4, 4)) for k in (12, 3, 40)}  # keys in no particular order
    points = {j: rng.normal(size=3) for j in range(900, 1400, 7)}
    sent = GraphResult(40, poses, points, marginal=rng.normal(size=(6, 6)), imu_bias=rng.normal(size=6), recoveries=2, worker_s=0.01, phases={"solve": 0.02})
    got = pickle.loads(pickle.dumps(sent, protocol=pickle.HIGHEST_PROTOCOL))
    assert list(got.poses) == [12, 3, 40] and list(got.points) == list(points)
    assert all(type(k) is int for k in (*got.poses, *got.points))
    for sent_d, got_d in ((poses, got.poses), (points, got.points)):
        for key, value in sent_d.items():
            assert got_d[key].shape == value.shape and np.array_equal(got_d[key], value)
    assert np.array_equal(got.marginal, sent.marginal) and np.array_equal(got.imu_bias, sent.imu_bias)
    assert (got.k, got.recoveries, got.worker_s, got.phases, got.failure, got.waiting) == (40, 2, 0.01, {"solve": 0.02}, None, False)
    # the estimator may keep a pose it was sent: each is its own row, changing one leaves the others
    got.poses[12][0, 0] += 1.0
    assert np.array_equal(got.poses[3], poses[3])


def test_a_failed_update_arrives_with_empty_estimates():
    got = pickle.loads(pickle.dumps(GraphResult(5, {}, {}, failure="indeterminate")))
    assert got.poses == {} and got.points == {} and got.failure == "indeterminate"


def test_an_estimate_kept_from_a_result_does_not_hold_the_others():
    """The estimator keeps every estimate for the whole run. The window's estimates arrive as rows of
    one array per result; once a landmark or keyframe has left the window, the estimator's copy of it
    is an array of its own, with the last value it was sent, so no result's array stays alive for it."""
    first = {j: np.full(3, float(j)) for j in range(500)}
    second = {j: np.full(3, float(j) + 0.5) for j in range(100, 600)}  # 0-99 left the window, 500-599 came in
    kept: dict[int, np.ndarray] = {}
    window: set[int] = set()
    for sent in (first, second):
        got = pickle.loads(pickle.dumps(GraphResult(1, {0: np.eye(4)}, sent)))
        window = _take_window(kept, window, got.points)
    assert window == set(second) and set(kept) == set(range(600))
    assert all(kept[j].base is None and np.array_equal(kept[j], np.full(3, float(j))) for j in range(100))
    assert all(np.array_equal(kept[j], second[j]) for j in range(100, 600))
    # the rows still in the window share the second result's array; that array is all they hold
    bases = {id(kept[j].base) for j in range(100, 600)}
    assert len(bases) == 1
