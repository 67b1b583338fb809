"""`dem-graph run`: the configuration file and the command line, which one decides."""

from __future__ import annotations

import json

import pytest
from click.testing import CliRunner

from dem_graph.cli import main


@pytest.fixture(scope="module")
def log_folder(tmp_path_factory):
    out = tmp_path_factory.mktemp("log") / "smoke"
    result = CliRunner().invoke(main, ["--no-progress", "simulate", "--scenario", "smoke", "--seed", "5", "--length-m", "0.5", "--out", str(out)])
    assert result.exit_code == 0, result.output
    return out


@pytest.mark.parametrize(("flags", "expected"), [([], "ekf-gm"), (["--estimator", "ptpm"], "ekf-ptpm")])
def test_the_config_files_estimator_holds_unless_the_command_line_names_one(log_folder, tmp_path, flags, expected):
    config = tmp_path / "run.yaml"
    config.write_text("estimator: gm\n")
    out = tmp_path / "run"
    result = CliRunner().invoke(main, ["--no-progress", "run", str(log_folder), "--config", str(config), "--max-frames", "3", "--out", str(out), *flags])
    assert result.exit_code == 0, result.output
    assert json.loads((out / "metrics.json").read_text())["estimator"] == expected


def test_graph_process_flag_reaches_the_written_configuration(log_folder, tmp_path):
    """`--graph-process` runs isam2's graph in a second process; the run's config.yaml says so,
    and the graph's lag is counted."""
    import yaml

    out = tmp_path / "run"
    result = CliRunner().invoke(main, ["--no-progress", "run", str(log_folder), "--estimator", "isam2", "--graph-process", "--max-frames", "8", "--out", str(out)])
    assert result.exit_code == 0, result.output
    assert yaml.safe_load((out / "config.yaml").read_text())["isam2"]["graph_process"] is True
    assert "graph_lag_keyframes_median" in json.loads((out / "metrics.json").read_text())["events"]


def test_realtime_replay_takes_the_logs_time_and_gives_the_same_run(smoke_log, smoke_run):
    """With `realtime` the events reach the estimator no sooner than their time after the first
    (the 65 frames of `smoke` span 2.56 s), and a deterministic estimator's run is the same, pose
    for pose, as when they come as fast as it takes them."""
    import time

    import numpy as np

    from dem_graph.pipeline import RunConfig, run_estimator

    # as fast as it takes them: the session's run, made once (other files check it too)
    runs = {False: smoke_run({"estimator": "ptpm", "realtime": False}, with_dem=False)}
    start = time.perf_counter()
    runs[True] = run_estimator(smoke_log, RunConfig(estimator="ptpm", realtime=True), with_dem=False)
    wall_s = time.perf_counter() - start
    events = list(smoke_log.events())
    span_s = events[-1].t_s - events[0].t_s
    assert span_s > 2.5 and wall_s >= span_s
    fast, paced = (runs[r].estimator.frames for r in (False, True))
    assert len(fast) == len(paced) == 65
    for a, b in zip(fast, paced):
        np.testing.assert_array_equal(a.T_world_body, b.T_world_body)


def test_realtime_flag_reaches_the_written_configuration(log_folder, tmp_path):
    import yaml

    out = tmp_path / "run"
    result = CliRunner().invoke(main, ["--no-progress", "run", str(log_folder), "--estimator", "ptpm", "--realtime", "--max-frames", "3", "--out", str(out)])
    assert result.exit_code == 0, result.output
    assert yaml.safe_load((out / "config.yaml").read_text())["realtime"] is True
