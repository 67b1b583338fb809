"""A camera frame out of time order stops the run with the package's error; what was estimated
before it is kept, written, and the same as a run that never saw it."""

from __future__ import annotations

import numpy as np
import pytest

from dem_graph.datasets.events import CameraFrame
from dem_graph.errors import EventOrderError
from dem_graph.estimators.ekf import EkfSlam
from dem_graph.io.tum import read_tum
from dem_graph.pipeline import RunConfig, run_dataset, run_estimator

GOOD_FRAMES = 20


def _with_a_frame_from_the_past(log):
    """``log`` with frame 10 given again after frame ``GOOD_FRAMES`` (and the odometry covering it)."""
    events = list(log.events())
    frames = [i for i, e in enumerate(events) if isinstance(e, CameraFrame)]
    return log.replace_events([*events[: frames[GOOD_FRAMES]], events[frames[9]], *events[frames[GOOD_FRAMES] :]])


@pytest.mark.parametrize("estimator", ["gm", "ptpm", "isam2", "isam2-batch"])
def test_a_frame_from_the_past_stops_the_run_and_keeps_what_was_done(smoke_log, estimator, tmp_path):
    bad = _with_a_frame_from_the_past(smoke_log)
    run = run_dataset(bad, out_dir=tmp_path / "run") if estimator == "ptpm" else run_estimator(bad, RunConfig(estimator=estimator))
    assert "camera frame 9 at" in run.error and "is not after the frame before" in run.error
    assert run.metrics.frames == GOOD_FRAMES and run.metrics.error == run.error
    assert run.dem is not None and run.metrics.dem.laser_returns > 0
    if estimator == "ptpm":  # the run folder holds the frames before the error
        assert len(read_tum(tmp_path / "run" / "trajectory.tum")) == GOOD_FRAMES
    if estimator != "isam2-batch":  # (the batch smooths only a finished log: its frames are the online pass's)
        clean = run_estimator(smoke_log, RunConfig(estimator=estimator, max_frames=GOOD_FRAMES), with_dem=False)
        for a, b in zip(run.estimator.frames[: GOOD_FRAMES - 1], clean.estimator.frames):
            np.testing.assert_array_equal(a.T_world_body, b.T_world_body)


def test_a_frame_before_the_start_is_refused(smoke_log):
    est = EkfSlam(smoke_log.rig, smoke_log.T_world_body_initial, smoke_log.t_start_s, has_odometry=False)
    frame = next(e for e in smoke_log.events() if isinstance(e, CameraFrame))
    with pytest.raises(EventOrderError, match="is not after the start"):
        est.on_frame(CameraFrame(smoke_log.t_start_s - 0.1, frame.image, 0))
    with pytest.raises(EventOrderError, match="nan"):
        est.on_frame(CameraFrame(float("nan"), frame.image, 0))
