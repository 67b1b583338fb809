"""The pieces GM, PTPM and the graph estimator share: the scan queue, the prediction's source, the
screening of injected wrong matches and the point archive."""

from __future__ import annotations

from collections import Counter

import numpy as np
import pytest

from dem_graph.datasets.events import LaserScan, Odometry
from dem_graph.estimators.base import ScanQueue
from dem_graph.estimators.false_matches import FalseMatches
from dem_graph.estimators.motion import FrameMotion, constant_velocity_increment
from dem_graph.estimators.point_archive import PointArchive
from dem_graph.estimators.settings import FalseMatchConfig, MotionConfig
from dem_graph.frontend.frontend import FrontEnd, FrontendConfig, PointKind, PointTrack
from dem_graph.frontend.tracker import TrackBatch
from dem_graph.geometry.se3 import transform_points


def _scan(t_s: float) -> LaserScan:
    return LaserScan(t_s, np.zeros(3))


def test_scan_queue_gives_a_frame_the_scans_up_to_its_time():
    q = ScanQueue()
    for t in (0.30, 0.10, 0.20, 0.45):  # arrival order, not time order
        q.append(_scan(t))
    assert [s.t_s for s in q.take_until(0.20)] == [0.10, 0.20]  # at the frame's time included, in arrival order
    assert len(q) == 2 and q.take_until(0.25) == []
    assert [s.t_s for s in q.take_until(1.0)] == [0.30, 0.45] and len(q) == 0


def _odometry(t_prev_s: float, t_s: float, dx_m: float) -> Odometry:
    T = np.eye(4)
    T[0, 3] = dx_m
    return Odometry(t_s, t_prev_s, T, np.eye(6) * 1e-4)


def test_frame_motion_takes_the_odometry_when_the_run_uses_it():
    motion = FrameMotion(MotionConfig(), has_odometry=True, t_start_s=1.0)
    assert motion.uses_odometry and motion.holds(1.1)  # no odometry yet: the frame waits
    motion.add_odometry(_odometry(1.0, 1.1, 0.2))
    motion.add_odometry(_odometry(1.1, 1.2, 0.2))
    assert not motion.holds(1.15)
    dt, (U, Q) = motion.advance(1.15)
    assert dt == pytest.approx(0.15) and motion.t_s == 1.15
    np.testing.assert_allclose(U[:3, 3], [0.3, 0.0, 0.0], atol=1e-12)  # one increment and half the next
    # 1.5 increments of noise; the first one's rotation noise, carried 0.1 m further, adds 0.1^2 * 1e-4 across
    np.testing.assert_allclose(np.diag(Q), [1.5e-4] * 4 + [1.51e-4] * 2, rtol=1e-9)
    # without odometry in the dataset (model auto), or by choice: nothing measured, nothing waited for
    for motion in (FrameMotion(MotionConfig(), False, 0.0), FrameMotion(MotionConfig(model="constant_velocity"), True, 0.0)):
        assert not motion.uses_odometry and not motion.holds(0.04)
        assert motion.advance(0.04) == (0.04, None)
    assert not FrameMotion(MotionConfig(wait_for_odometry=False), True, 0.0).holds(0.04)


def test_constant_velocity_increment():
    sigma_acc = FrameMotion(MotionConfig(sigma_angular_acc_radps2=0.5, sigma_linear_acc_mps2=2.0), False, 0.0).sigma_acc
    np.testing.assert_array_equal(sigma_acc, [0.5, 0.5, 0.5, 2.0, 2.0, 2.0])
    U, Q = constant_velocity_increment(np.array([0.0, 0.0, 0.2, 2.0, 0.0, 0.0]), 0.5, sigma_acc)
    c, s = np.cos(0.1), np.sin(0.1)
    np.testing.assert_allclose(U[:3, :3], [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], atol=1e-15)  # 0.1 rad about z
    np.testing.assert_allclose(U[:3, 3], [1.0, 0.0, 0.0], atol=1e-15)  # the translation in the start frame (decoupled)
    np.testing.assert_allclose(Q, np.diag(sigma_acc**2 * 0.125) + 1e-10 * np.eye(6), rtol=1e-15)
    _, Q0 = constant_velocity_increment(np.zeros(6), 0.0, sigma_acc)  # no time: the noise of 1 ms
    np.testing.assert_allclose(np.diag(Q0), sigma_acc**2 * 1e-9 + 1e-10, rtol=1e-15)


def _batch(uv: np.ndarray, ok: np.ndarray) -> TrackBatch:
    n = len(uv)
    return TrackBatch(np.where(ok, 0, 1).astype(np.int8), np.where(ok[:, None], uv, np.nan), np.ones(n), np.zeros(n), np.full((n, 2), 10))


def test_screening_without_injection_keeps_the_trackers_matches():
    counters = Counter()
    fm = FalseMatches(FalseMatchConfig(), counters)
    uv_pred = np.array([[10.0, 10.0], [20.0, 20.0], [30.0, 30.0], [40.0, 40.0]])
    sel = np.array([0, 2, 3])
    found = uv_pred[sel] + 0.5
    idx, uv = fm.screen_batch(sel, _batch(found, np.array([True, False, True])), uv_pred, lambda i, y: False)
    np.testing.assert_array_equal(idx, [0, 3])
    np.testing.assert_array_equal(uv, [[10.5, 10.5], [40.5, 40.5]])
    assert fm.screen(None, uv_pred[0], lambda y: True) is None and not counters


def test_screening_injects_in_point_order_and_counts_the_gates_decisions():
    uv_pred = np.array([[10.0, 10.0], [20.0, 20.0], [30.0, 30.0]])
    sel = np.array([0, 1, 2])
    found = uv_pred + np.array([[0.0, 0.0], [0.0, 0.0], [3.0, 4.0]])
    batch = _batch(found, np.array([True, False, True]))  # point 1 not found: injected near its prediction
    counters = Counter()
    fm = FalseMatches(FalseMatchConfig(fraction=1.0, offset_px=12.0, seed=7), counters)
    seen = []

    def accepts(i, y):
        seen.append((int(i), y.copy()))
        return i != 1

    idx, uv = fm.screen_batch(sel, batch, uv_pred, accepts)
    # every match was replaced, 12 px from the tracker's (or the prediction), each searched point's gate asked
    np.testing.assert_array_equal(idx, [0, 2])
    assert [i for i, _ in seen] == [0, 1, 2]
    np.testing.assert_allclose(np.linalg.norm(uv - found[[0, 2]], axis=1), 12.0, rtol=1e-12)
    for i, y in seen:
        base = found[i] if i != 1 else uv_pred[i]
        assert np.linalg.norm(y - (base - uv_pred[i])) == pytest.approx(12.0, rel=1e-12)
    assert counters == Counter(injected=3, injected_accepted=2, injected_rejected=1)
    # the same draws, one point at a time in the same order
    reference = FalseMatches(FalseMatchConfig(fraction=1.0, offset_px=12.0, seed=7), Counter())
    expected = [reference.apply(found[0], uv_pred[0])[0], reference.apply(None, uv_pred[1])[0], reference.apply(found[2], uv_pred[2])[0]]
    np.testing.assert_array_equal(uv, np.array(expected)[[0, 2]])


@pytest.fixture()
def frontend(smoke_log) -> FrontEnd:
    return FrontEnd(FrontendConfig(), smoke_log.rig)


def test_point_archive_keeps_dropped_points_and_lists_them_before_the_live_ones(frontend):
    rig = frontend.rig
    for pid, kind, t_s in ((4, PointKind.LASER, 0.1), (7, PointKind.CAMERA, 0.2), (9, PointKind.CAMERA, 0.3)):
        frontend.tracks[pid] = PointTrack(pid, kind, None, np.eye(4), t_s, n_tracked=pid + 1)
    archive = PointArchive(frontend)
    # point 4 behind the vehicle, point 7 on the camera's axis 5 m ahead (the image centre)
    X_world = np.array([[-5.0, 0.0, 0.0], transform_points(rig.T_body_cam, np.array([[0.0, 0.0, 5.0]]))[0]])
    cov = {0: np.eye(3) * 0.01, 1: np.eye(3) * 0.02}
    keep, uv = archive.drop_points(np.array([4, 7]), X_world, np.eye(4), lambda i: (cov[i], X_world[i]))
    np.testing.assert_array_equal(keep, [False, True])
    np.testing.assert_allclose(uv, [[rig.camera_model.cx_px, rig.camera_model.cy_px]], atol=1e-9)
    assert 4 not in frontend.tracks and frontend.counters["dropped_behind"] == 1 and len(archive) == 1
    X_world[0] = 99.0  # the archive kept the estimate at its drop
    archive.archive(9, "marginalized", np.eye(3) * 0.03)  # without a position: given at the end
    res = archive.result("test", [], np.array([7]), lambda i: np.array([1.0, 2.0, 3.0]), lambda i: np.eye(3) * 0.04, archived_xyz=lambda pid: np.full(3, float(pid)))
    pts = res.points.arrays()
    np.testing.assert_array_equal(pts["point_id"], [4, 9, 7])
    np.testing.assert_array_equal(pts["kind"], [PointKind.LASER, PointKind.CAMERA, PointKind.CAMERA])
    np.testing.assert_array_equal(pts["xyz"], [[-5.0, 0.0, 0.0], [9.0, 9.0, 9.0], [1.0, 2.0, 3.0]])
    np.testing.assert_array_equal(pts["covariance"][:, 0, 0], [0.01, 0.03, 0.04])
    np.testing.assert_array_equal(pts["n_tracked"], [5, 10, 8])
    np.testing.assert_array_equal(pts["created_t_s"], [0.1, 0.3, 0.2])
    assert res.counters == Counter(dropped_behind=1, dropped_marginalized=1) and res.counters is not frontend.counters
