"""Faults put into a log on purpose (`dem_graph.datasets.faults`, `dem-graph degrade`): exactly the
events inside the intervals are dropped or blacked out, the rest is the log unchanged."""

from __future__ import annotations

import numpy as np
import pytest
from click.testing import CliRunner

from dem_graph.cli import main
from dem_graph.datasets.events import CameraFrame, LaserScan, Odometry
from dem_graph.datasets.faults import Faults, FaultSequenceError, FaultySequence, parse_interval
from dem_graph.datasets.folder import FolderSequence


def _by_kind(events, kind):
    return [e for e in events if isinstance(e, kind)]


def test_gaps_drop_exactly_the_events_inside_and_renumber(smoke_log):
    faults = Faults(camera_gaps=((0.5, 1.0),), laser_gaps=((1.0, 1.6),), odometry_gaps=((2.0, 2.2),))
    base = list(smoke_log.events())
    kept = list(FaultySequence(smoke_log, faults).events())
    for kind, (t0, t1) in ((CameraFrame, (0.5, 1.0)), (LaserScan, (1.0, 1.6)), (Odometry, (2.0, 2.2))):
        before, after = _by_kind(base, kind), _by_kind(kept, kind)
        expected = [e for e in before if not t0 <= e.t_s < t1]
        assert len(expected) < len(before)  # the interval holds some of this stream
        assert [e.t_s for e in after] == [e.t_s for e in expected]
        assert [e.index for e in after] == list(range(len(after)))
    # everything outside the gaps is unchanged, in the same order
    assert [type(e) for e in kept] == [type(e) for e in base if not any(isinstance(e, k) and a <= e.t_s < b for k, (a, b) in ((CameraFrame, (0.5, 1.0)), (LaserScan, (1.0, 1.6)), (Odometry, (2.0, 2.2))))]


def test_black_frames_arrive_black_and_the_others_untouched(smoke_log):
    kept = _by_kind(FaultySequence(smoke_log, Faults(black_frames=((0.4, 0.8),))).events(), CameraFrame)
    base = _by_kind(smoke_log.events(), CameraFrame)
    assert len(kept) == len(base)
    for a, b in zip(kept, base):
        if 0.4 <= b.t_s < 0.8:
            assert a.image.shape == b.image.shape and not a.image.any()
        else:
            np.testing.assert_array_equal(a.image, b.image)


@pytest.mark.parametrize("text, problem", [("3:1", "end must be after the start"), ("a:b", "expected T0:T1"), ("1:2:3", "expected T0:T1"), ("1:nan", "finite")])
def test_a_bad_interval_is_refused_in_one_line(text, problem):
    with pytest.raises(FaultSequenceError, match=problem):
        parse_interval(text)


def test_degrade_writes_a_folder_without_the_gap_and_with_the_whole_truth(smoke_folder, tmp_path):
    out = tmp_path / "gap"
    r = CliRunner().invoke(main, ["--no-progress", "degrade", str(smoke_folder), "--out", str(out), "--camera-gap", "1:1.5"])
    assert r.exit_code == 0, r.output
    base, gap = FolderSequence(smoke_folder), FolderSequence(out)
    t_base, t_gap = base.camera_times(), gap.camera_times()
    np.testing.assert_array_equal(t_gap, t_base[(t_base < 1.0) | (t_base >= 1.5)])
    np.testing.assert_array_equal(gap.laser_scans()[1], base.laser_scans()[1])
    truth_base, truth_gap = base.ground_truth.trajectory, gap.ground_truth.trajectory
    np.testing.assert_array_equal(truth_gap.t_s, truth_base.t_s)


def test_degrade_refuses_its_own_input_and_a_bad_interval(smoke_folder, tmp_path):
    r = CliRunner().invoke(main, ["--no-progress", "degrade", str(smoke_folder), "--out", str(smoke_folder), "--camera-gap", "1:2", "--overwrite"])
    assert r.exit_code == 2 and "the output folder is the dataset being read" in r.output
    assert (smoke_folder / "dataset.yaml").is_file()
    r = CliRunner().invoke(main, ["--no-progress", "degrade", str(smoke_folder), "--out", str(tmp_path / "x"), "--laser-gap", "2:1"])
    assert r.exit_code == 2 and "interval 2.0:1.0: the end must be after the start" in r.output
