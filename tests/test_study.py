"""The estimator study's summary and conclusion, from a known table."""

from __future__ import annotations

import csv
import math
from dataclasses import replace

import pytest

from dem_graph.frontend.focus import FocusArea
from dem_graph.geometry.rig import default_rig
from dem_graph.studies.bench_estimators import config_for_points
from dem_graph.studies.study import StudyResult, StudyRow

NAN = math.nan


def _row(name, seed, ate_m, frame_ms, status="ok"):
    return StudyRow(name, seed, 1.5, 140, ate_m, ate_m / 2, 0.1, frame_ms, 2 * frame_ms, 130.0, status)


def _study() -> StudyResult:
    return StudyResult(
        [
            _row("gm", 1, 0.30, 20.0), _row("gm", 2, 0.50, 30.0),
            _row("ptpm", 1, 0.10, 40.0), _row("ptpm", 2, 0.20, 60.0),
            _row("isam2", 1, 0.25, 10.0), _row("isam2", 2, NAN, NAN, "failed: diverged"),
        ],
        "paper",
        None,
    )


def test_summary_means_over_the_runs_with_a_finite_ate():
    summary = {s.estimator: s for s in _study().summary()}
    assert list(summary) == ["gm", "ptpm", "isam2"]
    assert math.isclose(summary["gm"].mean_ate_m, 0.40, abs_tol=1e-12) and math.isclose(summary["gm"].mean_frame_ms, 25.0, abs_tol=1e-12)
    assert math.isclose(summary["ptpm"].mean_ate_m, 0.15, abs_tol=1e-12) and math.isclose(summary["ptpm"].mean_frame_ms, 50.0, abs_tol=1e-12)
    # the failed run is left out, not counted as zero
    assert summary["isam2"].runs == 1 and math.isclose(summary["isam2"].mean_ate_m, 0.25, abs_tol=1e-12)


def test_height_error_at_the_end_is_summarised_with_its_standard_error_and_the_dem_in_cm():
    dz = {1: 0.10, 2: -0.04}
    rows = [replace(_row("isam2-batch", seed, 0.1, 10.0), final_height_error_m=dz[seed], dem_rmse_m=0.02 * seed) for seed in (1, 2)]
    (s,) = StudyResult(rows, "paper", None).summary()
    assert math.isclose(s.mean_final_height_error_m, 0.03, abs_tol=1e-12)
    assert math.isclose(s.final_height_error_se_m, 0.07, abs_tol=1e-12)  # std (ddof 1) 0.0990 / sqrt(2)
    assert math.isclose(s.mean_dem_rmse_m, 0.03, abs_tol=1e-12)
    text = StudyResult(rows, "paper", None).conclusion()
    assert "isam2-batch +0.030 +- 0.070 m" in text and "isam2-batch 3.0 cm" in text


def test_conclusion_names_the_most_accurate_and_the_fastest_from_the_numbers():
    text = _study().conclusion()
    assert "ptpm had the lowest mean ATE, 0.150 m over 2 runs, at 50.0 ms per frame" in text
    assert "The fastest was isam2 (10.0 ms per frame, mean ATE 0.250 m)" in text
    assert "gm 0.400 m at 25.0 ms" in text
    assert "1 run(s) failed or stopped early" in text


def test_csv_holds_every_row_with_its_numbers(tmp_path):
    study = _study()
    with study.write_csv(tmp_path / "study.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == len(study.rows)
    for written, row in zip(rows, study.rows):
        assert written["estimator"] == row.estimator and int(written["seed"]) == row.seed
        ate = float(written["ate_m"])
        assert (math.isnan(ate) and math.isnan(row.ate_m)) or ate == row.ate_m


@pytest.mark.parametrize("speed_mps", [None, 1.5, 5.0])
def test_point_budget_sets_about_as_many_focus_cells_as_points_at_the_run_speed(speed_mps):
    # the focus area grows with the stopping distance: at 5 m/s it is longer than at 1.5 m/s, and the
    # cells must grow with it so that the cap, not the cells, limits the live points
    rig = default_rig()
    config = config_for_points("ptpm", 140, rig, speed_mps)
    focus = FocusArea.for_speed(config.frontend.focus, rig, None)
    nx, ny = focus.shape
    assert config.frontend.focus.nominal_speed_mps == (1.5 if speed_mps is None else speed_mps)
    assert config.frontend.max_points == 140 and config.frontend.max_laser_points == 98
    # 0.8 cells per point by construction; ceil() of the two sides adds at most a row and a column.
    # Sized for 1.5 m/s, the 5 m/s area would hold 770 cells.
    assert 0.8 * 140 <= nx * ny <= 1.25 * 0.8 * 140
