"""A run whose tracking yield is low names the setting to look at, picked by the main reason the
searches failed; one that matched almost nothing failed, says so last and exits non-zero."""

from __future__ import annotations

from dem_graph.pipeline.metrics import FAILED_YIELD_FRACTION, LOW_YIELD_FRACTION, RunMetrics, TrackingYield, tracking_failure, yield_advice


def _yield(matched: float, failed: dict[str, float]) -> TrackingYield:
    return TrackingYield(searches=1000, matched_fraction=matched, outlier_fraction_of_matched=0.0, failed_fraction=failed)


def test_a_low_yield_names_the_setting_of_its_main_failure():
    advice = yield_advice(_yield(0.05, {"search_too_large": 0.80, "low_score": 0.15}))
    assert advice.startswith("warning: only 5 % of the searches matched (under 25 %), most failed as search too large (80 %)")
    assert "frontend.tracker.max_search_half_size_px" in advice and "\n" not in advice
    assert "frontend.focus" in yield_advice(_yield(0.10, {"out_of_image": 0.6, "ambiguous": 0.3}))


def test_a_yield_at_or_above_the_threshold_says_nothing():
    assert yield_advice(_yield(LOW_YIELD_FRACTION, {"low_score": 0.75})) is None
    assert yield_advice(None) is None


def test_a_yield_under_a_tenth_is_a_failed_run_and_the_odometry_baseline_never_is():
    """The threshold is the module's (10 %): just under it fails, at it does not; the odometry
    baseline searches for nothing and is never a failed run; a tracking run with no search at all is."""
    def metrics(estimator: str, y: TrackingYield | None) -> RunMetrics:
        return RunMetrics(estimator=estimator, frames=50, tracking=y)

    under = tracking_failure(metrics("isam2", _yield(FAILED_YIELD_FRACTION - 0.001, {"search_too_large": 0.9})))
    assert under == "tracking failed: 10 % of 1000 searches matched (under 10 %): the trajectory is the motion model's alone"
    assert tracking_failure(metrics("isam2", _yield(FAILED_YIELD_FRACTION, {"low_score": 0.9}))) is None
    assert tracking_failure(metrics("odometry", None)) is None
    assert tracking_failure(metrics("ekf-ptpm", None)).startswith("no ground point was ever tracked")


def _run(dataset, out, config_text: str | None, tmp_path):
    """`dem-graph run` on ``dataset`` (with ``config_text`` as its --config): the exit code, the printed
    summary, the last line on stderr and metrics.json."""
    import json

    from click.testing import CliRunner

    from dem_graph.cli import main

    args = ["--no-progress", "run", str(dataset), "--estimator", "ptpm", "--out", str(out)]
    if config_text is not None:
        (tmp_path / f"{out.name}.yaml").write_text(config_text)
        args += ["--config", str(tmp_path / f"{out.name}.yaml")]
    result = CliRunner().invoke(main, args)
    assert result.exception is None or isinstance(result.exception, SystemExit), result.output
    stderr = result.stderr.strip().splitlines()
    return result.exit_code, result.stdout, stderr[-1] if stderr else "", json.loads((out / "metrics.json").read_text())


def test_a_run_that_matched_nothing_fails_in_its_last_line_and_keeps_its_files(tiny_folder, tmp_path):
    """A real run (the 0.5 m smoke log, 8 frames) with search regions capped at 1 px: the searches
    are refused as too large (measured: all 498; a region's half size is at least 2 px but for an exact
    prediction): the run ends with exit code 3 and, last, the failure with the setting to look at;
    metrics.json's status is "failed"; its files are written. The same run with the defaults matches
    nearly all (measured: 569 of 569), says nothing, exits 0 with status "ok"."""
    from dem_graph.cli.root import EXIT_RUN_FAILED

    code, stdout, last, metrics = _run(tiny_folder, tmp_path / "small_search", "frontend:\n  tracker:\n    max_search_half_size_px: 1\n", tmp_path)
    bad = TrackingYield.model_validate(metrics["tracking"])
    assert bad.searches > 100 and bad.matched_fraction < FAILED_YIELD_FRACTION
    assert max(bad.failed_fraction, key=bad.failed_fraction.get) == "search_too_large" and bad.failed_fraction["search_too_large"] > 0.5
    assert code == EXIT_RUN_FAILED == 3
    assert last.startswith(f"dem-graph: run failed: tracking failed: {100 * bad.matched_fraction:.0f} % of {bad.searches} searches matched (under 10 %)")
    assert "most searches failed as search too large" in last and "frontend.tracker.max_search_half_size_px" in last
    assert metrics["status"] == "failed" and metrics["failure"].startswith("tracking failed:")
    assert "warning: only" not in stdout  # the failure is said once, last
    assert {"trajectory.tum", "dem.tif", "metrics.json"} <= {p.name for p in (tmp_path / "small_search").iterdir()}
    code, stdout, last, metrics = _run(tiny_folder, tmp_path / "defaults", None, tmp_path)
    good = TrackingYield.model_validate(metrics["tracking"])
    assert code == 0 and good.searches > 100 and good.matched_fraction > 0.9 >= LOW_YIELD_FRACTION
    assert yield_advice(good) is None and "warning: only" not in stdout and metrics["status"] == "ok" and "failure" not in metrics


def test_a_low_yield_above_the_failure_threshold_warns_and_names_the_setting(tiny_folder, tmp_path):
    """Between the failure threshold and the warning's (10-25 %): a warning naming the setting in the
    summary, exit code 0. Measured on the same 8 frames: the search capped at 3 px matched 19 % of 515."""
    code, stdout, _, metrics = _run(tiny_folder, tmp_path / "search_3px", "frontend:\n  tracker:\n    max_search_half_size_px: 3\n", tmp_path)
    y = TrackingYield.model_validate(metrics["tracking"])
    assert FAILED_YIELD_FRACTION <= y.matched_fraction < LOW_YIELD_FRACTION, y
    assert code == 0 and metrics["status"] == "ok"
    assert [line for line in stdout.splitlines() if line.startswith("warning: only")] == [yield_advice(y)]
