"""`dem-graph evaluate RUN --truth DATASET`: a run folder's metrics against the ground truth."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import yaml
from click.testing import CliRunner

from dem_graph.cli import main
from dem_graph.datasets import FolderSequence
from dem_graph.geometry.trajectory import Trajectory
from dem_graph.io.tum import write_tum
from dem_graph.pipeline import RunConfig, run_estimator, write_run
from dem_graph.studies.evaluate import evaluate_run


@pytest.fixture(scope="module")
def run_folder(tiny_folder, tmp_path_factory):
    out = tmp_path_factory.mktemp("evaluate") / "ptpm"
    write_run(run_estimator(FolderSequence(tiny_folder), RunConfig(estimator="ptpm")), out)
    return out


def test_evaluate_gives_the_runs_own_metrics_again(tiny_folder, run_folder, tmp_path):
    """The trajectory numbers come from the same poses (TUM is exact): equal to metrics.json. The DEM is
    made again from poses.npz and points.ply (variances stored as float32): equal to 1e-6 m."""
    out = tmp_path / "evaluation.json"
    r = CliRunner().invoke(main, ["--no-progress", "evaluate", str(run_folder), "--dataset", str(tiny_folder), "--out", str(out)])
    assert r.exit_code == 0, r.output
    assert "ATE (m)" in r.output and "DEM error, laser-swept cells (cm)" in r.output
    own = json.loads((run_folder / "metrics.json").read_text())
    evaluated = json.loads(out.read_text())
    assert evaluated["metrics"]["trajectory"] == own["trajectory"]
    for key in ("height_error", "height_error_laser_cells"):
        assert evaluated["metrics"]["dem"][key]["cells"] == own["dem"][key]["cells"] > 100
        for stat in ("rmse_m", "mean_m", "std_m", "p95_abs_m"):
            assert evaluated["metrics"]["dem"][key][stat] == pytest.approx(own["dem"][key][stat], abs=1e-6)
    assert evaluated["metrics"]["dem"]["corridor"] == own["dem"]["corridor"]
    for stat in ("mean_of_mean_m", "mean_of_std_m"):
        assert evaluated["metrics"]["dem"]["local_window"][stat] == pytest.approx(own["dem"]["local_window"][stat], abs=1e-6)
    # what needs no truth is carried over as the run measured it
    assert evaluated["metrics"]["time_per_frame"] == own["time_per_frame"]
    assert evaluated["headline"]["ate_anchored_rmse_m"] == own["trajectory"]["ate_rmse_m"]


def test_known_answers_the_truth_itself_and_the_truth_moved(tiny_folder, tmp_path):
    """A run folder holding the ground truth at the camera times has zero error; the truth moved by a
    known 0.3 m, 0.4 m step has an anchored ATE of 0.5 m and an aligned ATE of 0 (both to 1e-9 m)."""
    sequence = FolderSequence(tiny_folder)
    gt = sequence.ground_truth.trajectory
    t = gt.t_s[::3]
    truth_at_t = Trajectory.from_poses(t, gt.at(t))
    exact, moved = tmp_path / "exact", tmp_path / "moved"
    for folder, trajectory in ((exact, truth_at_t), (moved, Trajectory(t, truth_at_t.positions_xyz + [0.3, 0.4, 0.0], truth_at_t.orientations_quat_xyzw))):
        folder.mkdir()
        write_tum(folder / "trajectory.tum", trajectory)
    m = evaluate_run(exact, tiny_folder).metrics  # a folder path will do
    assert m.trajectory.ate_rmse_m == pytest.approx(0.0, abs=1e-9)
    assert m.trajectory.ate_aligned_rmse_m == pytest.approx(0.0, abs=1e-9)
    assert m.trajectory.rotation_rmse_deg == pytest.approx(0.0, abs=1e-6)
    # no poses.npz: no DEM, and the reason
    assert "no poses.npz" in m.dem.error
    m = evaluate_run(moved, sequence).metrics
    assert m.trajectory.ate_rmse_m == pytest.approx(0.5, abs=1e-9)
    assert m.trajectory.ate_aligned_rmse_m == pytest.approx(0.0, abs=1e-9)
    assert np.isnan(m.trajectory.rpe.translation_rmse_m)


@pytest.fixture
def no_truth_folder(tiny_folder, tmp_path):
    folder = tmp_path / "no_truth"
    shutil.copytree(tiny_folder, folder)
    meta = yaml.safe_load((folder / "dataset.yaml").read_text())
    meta["has_ground_truth"] = False
    (folder / "dataset.yaml").write_text(yaml.safe_dump(meta))
    return folder


@pytest.mark.parametrize(
    ("case", "message"),
    [
        ("missing_run", "{tmp}/nowhere: run folder not found"),
        ("no_trajectory", "{tmp}/empty_run/trajectory.tum: file not found"),
        ("no_truth", "{tmp}/no_truth/ground_truth/trajectory.tum: not found: the dataset has no ground truth"),
        ("outside_truth", "{tmp}/late_run/trajectory.tum: cannot be compared with the ground truth"),
    ],
)
def test_evaluate_bad_input_is_one_line_naming_the_file(tiny_folder, run_folder, no_truth_folder, tmp_path, case, message):
    (tmp_path / "empty_run").mkdir()
    late = tmp_path / "late_run"
    late.mkdir()
    write_tum(late / "trajectory.tum", Trajectory([100.0, 101.0], np.zeros((2, 3)), np.tile([0, 0, 0, 1.0], (2, 1))))
    run, truth = {
        "missing_run": (tmp_path / "nowhere", tiny_folder),
        "no_trajectory": (tmp_path / "empty_run", tiny_folder),
        "no_truth": (run_folder, no_truth_folder),
        "outside_truth": (late, tiny_folder),
    }[case]
    r = CliRunner().invoke(main, ["--no-progress", "evaluate", str(run), "--dataset", str(truth)])
    assert r.exit_code == 2
    assert r.stderr.count("\n") == 1 and "Traceback" not in r.output
    assert r.stderr.startswith("dem-graph: error: " + message.format(tmp=tmp_path))
