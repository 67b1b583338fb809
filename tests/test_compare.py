"""`dem-graph compare`: every estimator on the same data, one table, summary.json and a self-contained report."""

from __future__ import annotations

import base64
import json
import math
import re
import typing

import pytest
from click.testing import CliRunner
from pydantic import BaseModel, ValidationError

from dem_graph.cli import main
from dem_graph.datasets import FolderSequence
from dem_graph.errors import DemGraphError
from dem_graph.evaluation.trajectory_metrics import RpeSummary, TrajectoryAccuracy
from dem_graph.pipeline import ESTIMATORS, RunConfig
from dem_graph.pipeline.metrics import RunMetrics
from dem_graph.pipeline.run_dem import DemFailure
from dem_graph.pipeline.run_folder import json_text
from dem_graph.studies import compare as compare_module
from dem_graph.studies.compare import compare, parse_estimators
from dem_graph.studies.headline import COLUMNS, format_value, headline, metric_at

N_FIGURES = 4  # trajectories, position error, Fig. 8 local error, best DEM and its error


@pytest.fixture(scope="module")
def comparison(tiny_folder, tmp_path_factory):
    out = tmp_path_factory.mktemp("compare") / "cmp"
    return compare(FolderSequence(tiny_folder), out, ESTIMATORS, RunConfig(), warm_up_frames=0)


def _same(a, b) -> bool:
    """Equal numbers, or both missing (NaN in memory, null in JSON)."""
    missing = [x is None or (isinstance(x, float) and math.isnan(x)) for x in (a, b)]
    return all(missing) or (not any(missing) and a == b)


def test_summary_numbers_equal_each_run_folders_metrics(comparison):
    summary = json.loads((comparison.out_dir / "summary.json").read_text())
    assert summary["estimators"] == list(ESTIMATORS) and set(summary["runs"]) == set(ESTIMATORS)
    for name in ESTIMATORS:
        entry = summary["runs"][name]
        assert entry["status"] == "ok" and entry["error"] is None
        metrics = json.loads((comparison.out_dir / name / "metrics.json").read_text())
        for column in COLUMNS:
            assert _same(entry["headline"][column.key], metrics_value := metric_at(RunMetrics.model_validate(metrics), column.path)), (name, column.key, metrics_value)
        # the numbers every run of this log has (ground truth and elevation): exactly those of metrics.json
        assert entry["headline"]["ate_anchored_rmse_m"] == metrics["trajectory"]["ate_rmse_m"] > 0.0
        assert entry["headline"]["dem_rmse_laser_cells_m"] == metrics["dem"]["height_error_laser_cells"]["rmse_m"] > 0.0
        # a 0.5 m log is shorter than the RPE's 10 m: no number, and the run's metrics say why
        assert entry["headline"]["rpe_10m_translation_rmse_m"] is None
        assert "less than the RPE's 10 m" in metrics["trajectory"]["rpe"]["reason"]
    # every run used the same settings but its estimator
    configs = {name: (comparison.out_dir / name / "config.yaml").read_text() for name in ESTIMATORS}
    stripped = {re.sub(r"^estimator: .*$", "", text, flags=re.M) for text in configs.values()}
    assert len(stripped) == 1


def test_the_table_has_one_row_per_estimator_with_its_numbers(comparison):
    lines = comparison.table().splitlines()
    for name, run in zip(ESTIMATORS, comparison.runs):
        row = next(line for line in lines if line.split()[0] == name)
        values = headline(run.metrics)
        for column in COLUMNS:
            assert format_value(column, values[column.key]) in row.split()
        assert row.rstrip().endswith("ok")


def test_report_html_is_self_contained_with_every_row_and_figure(comparison):
    html = (comparison.out_dir / "report.html").read_text()
    for name in ESTIMATORS:
        assert f"<td>{name}</td>" in html
    images = re.findall(r'src="data:image/png;base64,([A-Za-z0-9+/=]+)"', html)
    assert len(images) == N_FIGURES
    # no script and nothing fetched from elsewhere: every src is a data URI
    assert "<script" not in html.lower()
    assert len(re.findall(r"\bsrc=", html)) == N_FIGURES and "href=" not in html
    # each embedded image is the PNG the Markdown report links, byte for byte
    md = (comparison.out_dir / "report.md").read_text()
    links = re.findall(r"!\[[^\]]*\]\(([^)]+)\)", md)
    assert len(links) == N_FIGURES
    for link, data in zip(links, images):
        png = (comparison.out_dir / link).read_bytes()
        assert png.startswith(b"\x89PNG\r\n\x1a\n")
        assert base64.b64decode(data) == png
    summary = json.loads((comparison.out_dir / "summary.json").read_text())
    assert summary["figures"] == links
    # the best DEM is the one with the lowest RMSE over the laser-swept cells
    rmse = {n: r["headline"]["dem_rmse_laser_cells_m"] for n, r in summary["runs"].items()}
    assert summary["best_dem"] == min(rmse, key=rmse.get)


def test_a_failing_estimator_is_reported_and_the_others_complete(tiny_folder, tmp_path, monkeypatch):
    real = compare_module.run_estimator

    def fails_for_isam2(sequence, config, with_dem=True):
        if config.estimator == "isam2":
            raise DemGraphError("the graph blew up\non two lines")
        return real(sequence, config, with_dem)

    monkeypatch.setattr(compare_module, "run_estimator", fails_for_isam2)
    out = tmp_path / "cmp"
    result = CliRunner().invoke(main, ["--no-progress", "compare", str(tiny_folder), "--out", str(out), "--estimators", "gm,isam2,ptpm", "--max-frames", "4"])
    assert result.exit_code == 2
    assert "Traceback" not in result.output
    assert "1 of 3 runs failed (isam2: the graph blew up on two lines)" in result.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["runs"]["isam2"] == {
        "status": "failed", "error": "the graph blew up on two lines", "run_dir": "isam2",
        "headline": {c.key: None for c in COLUMNS},
    }
    for name in ("gm", "ptpm"):
        assert summary["runs"][name]["status"] == "ok"
        metrics = json.loads((out / name / "metrics.json").read_text())
        assert metrics["frames"] == 4
        assert summary["runs"][name]["headline"]["ate_anchored_rmse_m"] == metrics["trajectory"]["ate_rmse_m"]
    assert not (out / "isam2").exists()
    row = next(line for line in result.stdout.splitlines() if line.split() and line.split()[0] == "isam2")
    assert row.split()[1 : 1 + len(COLUMNS)] == ["-"] * len(COLUMNS) and row.rstrip().endswith("failed: the graph blew up on two lines")
    assert "<td>failed: the graph blew up on two lines</td>" in (out / "report.html").read_text()


def test_estimator_names_are_checked_and_kept_in_order():
    assert parse_estimators("ptpm, gm,ptpm") == ("ptpm", "gm")
    with pytest.raises(DemGraphError, match="unknown estimator 'ekf'"):
        parse_estimators("gm,ekf")


def test_compare_bad_input_is_one_line(tiny_folder, tmp_path):
    r = CliRunner().invoke(main, ["--no-progress", "compare", str(tiny_folder), "--out", str(tmp_path / "c"), "--estimators", "gm,kalman"])
    assert r.exit_code == 2 and r.stderr.count("\n") == 1 and "unknown estimator 'kalman'" in r.stderr
    r = CliRunner().invoke(main, ["--no-progress", "compare", str(tmp_path / "none"), "--out", str(tmp_path / "c")])
    assert r.exit_code == 2 and r.stderr.count("\n") == 1 and f"{tmp_path / 'none'}: dataset folder not found" in r.stderr


def _accuracy(ate_m: float, rpe_m: float) -> TrajectoryAccuracy:
    rpe = RpeSummary(delta_m=10.0, pairs=0, translation_rmse_m=rpe_m, translation_mean_m=rpe_m, translation_max_m=rpe_m, translation_rmse_percent=rpe_m, rotation_rmse_deg=rpe_m, reason="short")
    return TrajectoryAccuracy(ate_rmse_m=ate_m, ate_max_m=ate_m, rotation_rmse_deg=0.1, final_error_m=ate_m, distance_m=5.0, drift_percent=1.0, n_poses=3, ate_aligned_rmse_m=ate_m, rpe=rpe)


def test_headline_reads_nested_numbers_and_nan_for_the_rest():
    metrics = RunMetrics(trajectory=_accuracy(0.25, math.nan), dem=DemFailure(error="no DEM"))
    assert metric_at(metrics, ("trajectory", "ate_rmse_m")) == 0.25
    assert math.isnan(metric_at(metrics, ("trajectory", "rpe", "translation_rmse_m")))
    assert math.isnan(metric_at(metrics, ("dem", "height_error_laser_cells", "rmse_m")))  # no DEM: not measured
    assert math.isnan(metric_at(metrics, ("time_per_frame", "total", "median_ms")))  # no frame
    dem = next(c for c in COLUMNS if c.key == "dem_rmse_laser_cells_m")
    assert format_value(dem, 0.01234) == "1.23" and format_value(dem, math.nan) == "-"


def _field_type(model, name: str):
    """The type of field ``name`` of ``model``, through Optional and unions (the measured form, not the failure's)."""
    annotation = typing.get_type_hints(model)[name]
    args = [a for a in typing.get_args(annotation) if a is not type(None)] or [annotation]
    models = [a for a in args if isinstance(a, type) and issubclass(a, BaseModel) and a is not DemFailure]
    return models[0] if models else args[0]


@pytest.mark.parametrize("column", COLUMNS, ids=lambda c: c.key)
def test_every_column_names_a_number_field_of_the_metrics(column):
    """Walked through the types, not a sample: a renamed field fails here instead of printing `-`."""
    kind = RunMetrics
    for key in column.path:
        if typing.get_origin(kind) is dict:  # a dict's key (time_per_frame's phases)
            kind = typing.get_args(kind)[1]
            continue
        assert isinstance(kind, type) and issubclass(kind, BaseModel) and key in kind.model_fields, (column.key, key)
        kind = _field_type(kind, key)
    assert kind in (float, int) or typing.get_origin(kind) is typing.Annotated and typing.get_args(kind)[0] is float, (column.key, kind)


def test_a_path_that_names_no_field_is_an_error():
    metrics = RunMetrics(trajectory=_accuracy(0.25, 0.1))
    with pytest.raises(AttributeError, match="ate_rmse"):
        metric_at(metrics, ("trajectory", "ate_rmse"))
    with pytest.raises(ValidationError):
        RunMetrics.model_validate({"trajectroy": {}})  # a key the metrics do not have


def test_metrics_json_is_the_typed_metrics_and_reads_back(comparison):
    """Each run folder's metrics.json is its RunMetrics as JSON; read back, it is the same metrics."""
    for run in comparison.runs:
        path = comparison.out_dir / run.estimator / "metrics.json"
        text = path.read_text()
        assert text == json_text(run.metrics.to_json_dict())
        assert json_text(RunMetrics.model_validate(json.loads(text)).to_json_dict()) == text


def test_a_run_that_tracked_nothing_is_marked_failed_and_keeps_its_folder(tiny_folder, tmp_path):
    """The tracker's search capped at 1 px (every search refused as too large on the 0.5 m smoke log,
    tests/test_yield_advice.py): ptpm goes to its end but matches under 10 %: its row, summary.json and
    the report say "failed: tracking failed: ...", its folder and metrics are kept, the exit code is 2
    with the reason; the odometry baseline, which tracks nothing, stays "ok"; the best DEM is not the
    failed run's."""
    config = tmp_path / "search_1px.yaml"
    config.write_text("frontend:\n  tracker:\n    max_search_half_size_px: 1\n")
    out = tmp_path / "cmp"
    result = CliRunner().invoke(main, ["--no-progress", "compare", str(tiny_folder), "--out", str(out), "--estimators", "odometry,ptpm", "--config", str(config)])
    assert result.exit_code == 2 and "Traceback" not in result.output
    summary = json.loads((out / "summary.json").read_text())
    ptpm = summary["runs"]["ptpm"]
    metrics = json.loads((out / "ptpm" / "metrics.json").read_text())
    assert metrics["status"] == "failed" and ptpm["status"] == "failed" and ptpm["error"] == metrics["failure"]
    assert ptpm["error"].startswith("tracking failed: 0 % of ") and "(under 10 %)" in ptpm["error"]
    assert ptpm["headline"]["ate_anchored_rmse_m"] == metrics["trajectory"]["ate_rmse_m"]  # its numbers are kept, marked
    assert summary["runs"]["odometry"]["status"] == "ok"
    assert f"1 of 2 runs failed (ptpm: {ptpm['error']})" in result.stderr
    row = next(line for line in result.stdout.splitlines() if line.split() and line.split()[0] == "ptpm")
    assert row.rstrip().endswith(f"failed: {ptpm['error']}")
    assert summary["best_dem"] == "odometry"
