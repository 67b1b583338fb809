"""The odometry-only baseline (estimators/odometry_only.py) against the log's own odometry and the truth."""

from __future__ import annotations

import numpy as np
import pytest

from dem_graph.datasets.events import CameraFrame, Odometry
from dem_graph.errors import DemGraphError
from dem_graph.estimators.odometry import OdometryIntegrator
from dem_graph.pipeline.config import ESTIMATORS, RunConfig
from dem_graph.pipeline.run import run_estimator
from dem_graph.studies.compare import default_estimators, parse_estimators


@pytest.fixture(scope="module")
def baseline_run(smoke_log):
    return run_estimator(smoke_log, RunConfig(estimator="odometry"), with_dem=False)


def test_its_poses_are_the_odometry_integrated_and_its_covariance_covers_the_error(smoke_log, baseline_run):
    """Each frame's pose is the start composed with the log's increments up to that frame (to 1e-9),
    nothing is tracked, and the error against the truth at the end is within the covariance
    (squared Mahalanobis distance of the position below the chi-square(3) 99.7 % point)."""
    frames = baseline_run.estimator.frames
    events = list(smoke_log.events())
    integrator = OdometryIntegrator(smoke_log.t_start_s)
    T = smoke_log.T_world_body_initial.copy()
    camera_times = [e.t_s for e in events if isinstance(e, CameraFrame)]
    for e in events:
        if isinstance(e, Odometry):
            integrator.add(e)
    for t_s, record in zip(camera_times, frames):
        U, _ = integrator.increment(t_s)
        T = T @ U
        np.testing.assert_allclose(record.T_world_body, T, atol=1e-9)
    assert len(frames) == len(camera_times) and all(f.n_tracked == 0 and f.n_live == 0 for f in frames)
    last = frames[-1]
    truth = smoke_log.ground_truth.trajectory.at(np.array([last.t_s]))[0]
    R = last.T_world_body[:3, :3]
    error = last.T_world_body[:3, 3] - truth[:3, 3]
    P_world = R @ last.pose_covariance[3:, 3:] @ R.T
    assert error @ np.linalg.solve(P_world, error) < 14.2
    assert np.all(np.diff([np.trace(f.pose_covariance) for f in frames]) >= 0)  # dead reckoning only grows


def test_without_odometry_it_is_refused_in_one_line(smoke_log):
    from dem_graph.pipeline.live import make_estimator

    with pytest.raises(DemGraphError, match=r"^the odometry baseline needs a log with odometry"):
        make_estimator(smoke_log.rig, smoke_log.T_world_body_initial, smoke_log.t_start_s, False, RunConfig(estimator="odometry"))


def test_compare_runs_it_first_when_the_log_has_odometry(smoke_log):
    class NoOdometry:
        has_odometry = False

    assert default_estimators(smoke_log) == ("odometry", *ESTIMATORS)
    assert default_estimators(NoOdometry()) == ESTIMATORS
    assert parse_estimators("odometry,ptpm") == ("odometry", "ptpm")
    with pytest.raises(DemGraphError, match="choose from odometry, gm, ptpm, isam2, isam2-batch"):
        parse_estimators("ekf")
