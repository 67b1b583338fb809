"""The run configuration's layering (defaults < the dataset's run settings < a file < overrides) and
the one library call that runs what `dem-graph run` runs."""

from __future__ import annotations

import pytest
from click.testing import CliRunner

from dem_graph.cli import main
from dem_graph.datasets.memory import InMemorySequence
from dem_graph.errors import ConfigError
from dem_graph.io.tum import read_tum
from dem_graph.pipeline import RunConfig, RunOverrides, run_config, run_dataset, run_estimator


class SequenceWithSettings(InMemorySequence):
    """A log that brings run settings of its own, as KITTI does."""

    settings: dict = {}

    def run_settings(self) -> dict:
        return self.settings


def _with_settings(log: InMemorySequence, settings: dict) -> SequenceWithSettings:
    seq = SequenceWithSettings(log.rig, list(log.events()), log.T_world_body_initial, log.t_start_s, log.ground_truth, log.name)
    seq.settings = settings
    return seq


def test_each_layer_over_the_one_below(smoke_log, tmp_path):
    seq = _with_settings(smoke_log, {"frontend": {"max_points": 50, "min_separation_px": 10.0}, "motion": {"sigma_linear_acc_mps2": 0.7}, "isam2": {"lag_s": 3.0}})
    path = tmp_path / "run.yaml"
    path.write_text("frontend:\n  max_points: 60\nisam2:\n  lag_s: 2.0\nestimator: gm\n")
    config = run_config(seq, path, RunOverrides(max_points=70, no_odometry=True))
    default = RunConfig()
    assert config.frontend.max_points == 70  # override over file over dataset
    assert config.isam2.lag_s == 2.0  # file over dataset
    assert config.estimator == "gm"  # file over the default
    assert config.frontend.min_separation_px == 10.0 and config.motion.sigma_linear_acc_mps2 == 0.7  # dataset over the defaults
    assert config.motion.model == "constant_velocity"
    assert config.frontend.tracker == default.frontend.tracker and config.dem == default.dem  # untouched: the defaults


def test_an_estimator_run_without_a_configuration_takes_the_datasets_settings(smoke_log):
    """`run_estimator(sequence)` from a notebook runs what `dem-graph run` would: the dataset's own
    settings under it (here, a cap of 7 live points)."""
    seq = _with_settings(smoke_log, {"frontend": {"max_points": 7}})
    run = run_estimator(seq, with_dem=False)
    assert run.config.frontend.max_points == 7
    assert run.metrics.points_per_frame.live_max <= 7


def test_a_file_from_before_the_fig8_section_still_reads(tmp_path):
    path = tmp_path / "config.yaml"
    path.write_text("dem:\n  local_length_m: 4.0\n  local_every_n_frames: 2\n  local_history_s: 8.0\n")
    config = run_config(config_file=path)
    assert (config.local_error.length_m, config.local_error.every_n_frames, config.dem.local_history_s) == (4.0, 2, 8.0)


def test_a_wrong_value_names_the_file_and_the_field(tmp_path):
    path = tmp_path / "run.yaml"
    path.write_text("frontend:\n  max_points: -3\n")
    with pytest.raises(ConfigError, match=r"run\.yaml.*frontend\.max_points"):
        run_config(config_file=path)
    with pytest.raises(ConfigError, match="estimator"):
        run_config(overrides=RunOverrides(estimator="kalman"))


def _command_and_library(dataset, tmp_path, flags: list[str], overrides: RunOverrides):
    cli_out, lib_out = tmp_path / "cli", tmp_path / "lib"
    result = CliRunner().invoke(main, ["--no-progress", "run", str(dataset), "--out", str(cli_out), *flags])
    assert result.exit_code == 0, result.output
    run = run_dataset(dataset, overrides, out_dir=lib_out)
    return cli_out, lib_out, run


def test_the_command_and_the_library_run_the_same_on_a_simulated_log(tiny_folder, tmp_path):
    cli_out, lib_out, run = _command_and_library(tiny_folder, tmp_path, ["--estimator", "isam2"], RunOverrides(estimator="isam2"))
    assert (cli_out / "trajectory.tum").read_bytes() == (lib_out / "trajectory.tum").read_bytes()
    assert (cli_out / "config.yaml").read_text() == (lib_out / "config.yaml").read_text()
    assert len(read_tum(lib_out / "trajectory.tum")) == run.metrics.frames == 8


@pytest.mark.shared_data
def test_the_command_and_the_library_run_the_same_on_kitti(kitti_sample, tmp_path):
    """On KITTI the dataset's run settings (a car's starting speed, acceleration noise, search size)
    apply to both; without them the first frames track nothing."""
    flags, overrides = ["--estimator", "isam2", "--max-frames", "15"], RunOverrides(estimator="isam2", max_frames=15)
    cli_out, lib_out, run = _command_and_library(kitti_sample, tmp_path, flags, overrides)
    assert (cli_out / "trajectory.tum").read_bytes() == (lib_out / "trajectory.tum").read_bytes()
    assert run.config.motion.initial_speed_mps == pytest.approx(12.6, abs=0.3)  # the first two scans' speed, as the command's
    # no speed given: the cap is the default's, and the search follows the speed the estimator holds
    # (frontend.search_cap; test_kitti.py works the formula by hand)
    assert run.config.frontend.tracker.max_search_half_size_px == 40 and run.config.frontend.tracker.search_cap_follows_speed
    assert run.metrics.points_per_frame.tracked_median > 10
    assert run.metrics.trajectory.ate_rmse_m < 1.0  # 20 m driven
