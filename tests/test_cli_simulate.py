"""`dem-graph simulate` end to end: the written dataset equals the simulated stream; bad input gives one line."""

from __future__ import annotations

import numpy as np
import pytest
from click.testing import CliRunner

from dem_graph.cli import main
from dem_graph.datasets import CameraFrame, FolderSequence, LaserScan, Odometry
from dem_graph.sim.scenarios import scenario
from dem_graph.sim.simulator import SimulatedSequence


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    out = tmp_path_factory.mktemp("sim") / "smoke"
    result = CliRunner().invoke(main, ["--no-progress", "simulate", "--scenario", "smoke", "--seed", "5", "--length-m", "1.5", "--out", str(out)])
    assert result.exit_code == 0, result.output
    return out, result.output


def test_simulate_writes_what_the_simulator_streams(written):
    out, output = written
    loaded = FolderSequence(out)
    # the command reports what it wrote
    assert f"{loaded.n_frames} frames, {loaded.n_scans} laser scans, {loaded.n_odometry} odometry increments" in output
    simulated = SimulatedSequence.from_config(scenario("smoke", seed=5, length_m=1.5))
    a, b = list(simulated.events()), list(loaded.events())
    assert [type(e) for e in a] == [type(e) for e in b]
    for x, y in zip(a, b):
        assert x.t_s == y.t_s
        if isinstance(x, CameraFrame):
            assert np.array_equal(x.image, y.image)
        elif isinstance(x, LaserScan):
            assert np.array_equal(x.ranges_m, y.ranges_m, equal_nan=True)
        elif isinstance(x, Odometry):
            assert np.array_equal(x.T_prev_curr, y.T_prev_curr) and np.array_equal(x.covariance, y.covariance)
    np.testing.assert_array_equal(loaded.T_world_body_initial, simulated.T_world_body_initial)
    gt_loaded, gt_sim = loaded.ground_truth, simulated.ground_truth
    np.testing.assert_array_equal(gt_loaded.trajectory.positions_xyz, gt_sim.trajectory.positions_xyz)
    np.testing.assert_array_equal(gt_loaded.elevation.z_m, gt_sim.elevation.z_m)
    assert gt_loaded.elevation.geometry == gt_sim.elevation.geometry
    assert (out / "preview.png").stat().st_size > 10_000
    assert (out / "scenario.yaml").is_file()


def test_simulate_refuses_a_non_empty_folder(written):
    out, _ = written
    result = CliRunner().invoke(main, ["simulate", "--scenario", "smoke", "--out", str(out)])
    assert result.exit_code == 2
    assert result.output.strip().count("\n") == 0
    assert str(out) in result.output and "not empty" in result.output


@pytest.mark.parametrize(
    "args, message",
    [
        (["--scenario", "nope"], "unknown scenario 'nope'"),
        (["--scenario", "smoke", "--length-m", "-3"], "length_m"),
        (["--scenario", "smoke", "--speed-mps", "0"], "speed_mps"),
    ],
)
def test_simulate_bad_arguments_give_one_line(tmp_path, args, message):
    result = CliRunner().invoke(main, ["simulate", *args, "--out", str(tmp_path / "x")])
    assert result.exit_code == 2
    assert message in result.output
    assert "Traceback" not in result.output
    assert len(result.output.strip().splitlines()) == 1
