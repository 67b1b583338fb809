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
