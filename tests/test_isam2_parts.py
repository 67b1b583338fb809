"""The graph estimator's parts on their own: the pose covariance's anchor, the landmarks' numbering,
the graph client applying a result, and the batch's log of a frame."""

from __future__ import annotations

from collections import Counter

import numpy as np
import pytest

from dem_graph.estimators.batch_log import BatchLog
from dem_graph.estimators.graph_client import GraphClient, Landmarks, PoseAnchor
from dem_graph.estimators.graph_worker import GraphResult
from dem_graph.estimators.isam2_config import Isam2Config
from dem_graph.estimators.live_points import LivePoints
from dem_graph.geometry.lie import adjoint
from dem_graph.geometry.se3 import invert

SIGMA_ROT, SIGMA_POS = 0.01, 0.02  # rad, m


def _translation(x_m: float) -> np.ndarray:
    T = np.eye(4)
    T[0, 3] = x_m
    return T


def test_anchor_carries_its_marginal_to_a_pose_and_a_point():
    P = np.diag([SIGMA_ROT**2] * 3 + [SIGMA_POS**2] * 3)
    Q = np.eye(6) * 1e-6
    anchor = PoseAnchor(np.eye(4), P, Q, 0.0)
    # 4 m straight ahead: the heading and pitch errors move the pose sideways and up by 4 m x sigma_rot
    lateral = SIGMA_POS**2 + 16 * SIGMA_ROT**2
    expected = np.diag([SIGMA_ROT**2] * 3 + [SIGMA_POS**2, lateral, lateral]) + Q
    P_far = anchor.pose_covariance(_translation(4.0))
    np.testing.assert_allclose(np.diag(P_far), np.diag(expected), rtol=1e-12)
    np.testing.assert_allclose(P_far, P_far.T, atol=0)
    # a point 3 m ahead: its own covariance plus the anchor's position and, across, 3 m of its rotation
    info = np.eye(3) / 0.05**2
    cov = anchor.point_covariance(np.array([3.0, 0.0, 0.0]), info)
    across = 0.05**2 + SIGMA_POS**2 + 9 * SIGMA_ROT**2
    np.testing.assert_allclose(cov, np.diag([0.05**2 + SIGMA_POS**2, across, across]), rtol=1e-12, atol=1e-18)


def test_landmarks_number_segments_and_keep_the_links_for_the_next_keyframe():
    book = Landmarks()
    np.testing.assert_array_equal(book.start(3), [0, 1, 2])
    Sigma = np.eye(3) * 1e-4
    assert book.split(point_id=7, old=1, Sigma_old=Sigma) == 3 and book.of_point[7] == 3
    np.testing.assert_array_equal(book.start(2), [4, 5])  # one numbering for both
    links = book.take_links()
    assert [(a, b) for a, b, _ in links] == [(1, 3)] and links[0][2] is Sigma and book.take_links() == []
    book.split(8, 4, Sigma)
    book.drop_links()  # a restart: the new smoother starts from priors, no links
    assert book.take_links() == []
    book.entered([0, 1, 2], 0)
    book.entered([3], 2)
    assert book.entered_after(3, 1) and not book.entered_after(3, 2) and not book.entered_after(0, 0)
    assert not book.entered_after(99, 0)  # never entered
    new = book.split(9, 3, Sigma)
    newer = book.split(9, new, Sigma)  # refreshed twice before a keyframe
    assert book.continuing() == {new: 3, newer: 3}


def test_batch_log_counts_a_refreshed_match_for_both_landmarks(smoke_log):
    batch = BatchLog(Isam2Config(batch=True, split_link_sigma_m=0.004), smoke_log.rig, np.eye(4), np.eye(6))
    uv = np.array([[1.0, 1.0], [2.0, 2.0], [3.0, 3.0]])
    batch.add_frame(0.04, _translation(0.1), np.eye(6) * 1e-4, np.array([5, 8, 9]), uv, np.array([-1, 4, -1]))
    batch.add_link(4, 8)
    frames, landmarks, uv_logged = batch.log.observations()
    np.testing.assert_array_equal(frames, [0, 0, 0, 0])
    np.testing.assert_array_equal(landmarks, [5, 8, 9, 4])  # point 8 was matched with landmark 4's patch
    np.testing.assert_array_equal(uv_logged, [[1.0, 1.0], [2.0, 2.0], [3.0, 3.0], [2.0, 2.0]])
    assert batch.log.links == [(4, 8, 0.004)] and batch.result is None


def test_graph_client_moves_what_it_sent_by_the_graphs_correction(smoke_log):
    """A result for keyframe 1 that moves it 0.1 m forward: the last keyframe moves with it, the live
    points take the graph's landmarks, a point placed after keyframe 1 moves by the correction, one
    whose patch was refreshed since the last keyframe (its new landmark not sent yet) takes the
    estimate of the landmark it continues, and one the graph no longer holds leaves."""
    client = GraphClient(Isam2Config(), smoke_log.rig, np.eye(4), np.eye(6) * 1e-8, 0.0, Counter())
    client.carry(_translation(0.05), np.eye(6) * 1e-4)
    empty = (np.zeros(0, dtype=np.int64), np.zeros((0, 2)), np.zeros(0))
    client.open_keyframe(0.04, _translation(0.05))
    assert client.send_keyframe(np.eye(6) * 1e-4, empty, []) is None
    assert [r.k for r in client.results()] == [1] and client.keyframe_t_s == [0.0, 0.04]
    live = LivePoints()
    live.add([10, 11, 12], client.landmarks.start(3), np.array([[5.0, 0.0, 0.0], [6.0, 1.0, 0.0], [7.0, -1.0, 0.0]]), np.tile(np.eye(3) * 1e-2, (3, 1, 1)))
    client.landmarks.entered([0, 1], 0)
    client.landmarks.entered([2], 2)  # started after keyframe 1, from a pose the correction moves
    # a patch refreshed in a frame that was not a keyframe: the new landmark goes with the next one
    live.add([13], [client.landmarks.split(13, 0, np.eye(3) * 1e-4)], np.array([[8.0, 2.0, 0.0]]), np.eye(3)[None] * 1e-2)
    T_smoothed = _translation(0.15)
    correction, C, keep = client.apply(GraphResult(1, {1: T_smoothed}, {0: np.array([5.0, 0.5, 0.0])}), live)
    np.testing.assert_allclose(correction, _translation(0.1), atol=1e-15)
    np.testing.assert_allclose(C, _translation(0.1), atol=1e-15)
    np.testing.assert_allclose(client.T_kf, T_smoothed, atol=1e-15)
    np.testing.assert_array_equal(keep, [True, False, True, True])
    np.testing.assert_array_equal(live.X[3], [5.0, 0.5, 0.0])  # landmark 0's estimate
    np.testing.assert_array_equal(live.X[0], [5.0, 0.5, 0.0])
    np.testing.assert_allclose(live.X[2], [7.1, -1.0, 0.0], atol=1e-15)
    np.testing.assert_allclose(client.points[2], live.X[2], atol=0)
    np.testing.assert_array_equal(client.poses[1], T_smoothed)
    # the anchor (no marginal asked for yet) is unchanged; the result answered the newest keyframe
    np.testing.assert_array_equal(client.anchor.T, np.eye(4))
    counters = Counter()
    client.count(counters)
    assert counters == Counter(keyframes=2, graph_lag_keyframes_median=0, graph_lag_keyframes_max=0)
    client.close(client.finish()[1])


def test_graph_client_carries_the_output_covariance_with_the_predicted_motion(smoke_log):
    """With an IMU a frame's pose is predicted with the gyroscope's rotation: the output covariance
    since the anchor takes that prediction's covariance, while the motion sent with the next keyframe
    (the graph's odometry factor; the gyroscope has its own) keeps the odometry's. A translation does
    not move a rotation error, so over 25 frames straight ahead each rotation block is the sum of the
    frames' variances. Without ``predicted`` both are the odometry's, as before."""
    Q_odo = np.diag([1e-5] * 3 + [1e-6] * 3)  # wheel odometry's rotation over a frame: about 0.2 deg
    Q_gyro = np.diag([1e-9] * 3 + [1e-6] * 3)  # the gyroscope's: about 0.002 deg, the same translation
    U = _translation(0.06)
    A = adjoint(invert(U))
    with_imu = GraphClient(Isam2Config(), smoke_log.rig, np.eye(4), np.eye(6) * 1e-8, 0.0, Counter())
    without = GraphClient(Isam2Config(), smoke_log.rig, np.eye(4), np.eye(6) * 1e-8, 0.0, Counter())
    for _ in range(25):
        with_imu.carry(U, Q_odo, A, predicted=(Q_gyro, A))
        without.carry(U, Q_odo, A)
    np.testing.assert_allclose(np.diag(with_imu.Q_kf)[:3], 25 * 1e-5, rtol=1e-12)
    np.testing.assert_allclose(np.diag(with_imu.anchor.Q)[:3], 25 * 1e-9, rtol=1e-12)
    np.testing.assert_array_equal(with_imu.Q_kf, without.Q_kf)
    np.testing.assert_array_equal(without.anchor.Q, without.Q_kf)
    for client in (with_imu, without):
        client.close(client.finish()[1])


@pytest.mark.parametrize("every_s, marginal", [(0.0, False), (0.03, True)])
def test_graph_client_asks_for_a_marginal_at_most_every(smoke_log, every_s, marginal):
    """``pose_covariance_every_s``: 0 never asks the smoother (the filter's covariance anchors the
    output); otherwise a keyframe at least that long after the anchor asks, and its marginal becomes the anchor."""
    client = GraphClient(Isam2Config(pose_covariance_every_s=every_s), smoke_log.rig, np.eye(4), np.eye(6) * 1e-8, 0.0, Counter())
    client.carry(_translation(0.05), np.eye(6) * 1e-4)
    empty = (np.zeros(0, dtype=np.int64), np.zeros((0, 2)), np.zeros(0))
    P_loc = np.eye(6) * 2e-4
    client.open_keyframe(0.04, _translation(0.05))
    client.send_keyframe(P_loc, empty, [])
    (r,) = client.results()
    assert (r.marginal is not None) == marginal
    client.apply(r, LivePoints())
    if marginal:  # the smoother's: the prior and one odometry step
        assert client.anchor.t_s == 0.04 and np.allclose(np.diag(client.anchor.P), 1e-4 + 1e-8, rtol=1e-6)
    else:  # the filter's, at the keyframe
        assert client.anchor.t_s == 0.0 and np.array_equal(client.anchor.P, P_loc) and np.array_equal(client.anchor.T, _translation(0.05))
    client.close(client.finish()[1])
