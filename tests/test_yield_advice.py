"""A run whose tracking yield is low names the setting to look at, picked by the main reason the searches failed."""

from __future__ import annotations

from dem_graph.pipeline.metrics import LOW_YIELD_FRACTION, TrackingYield, yield_advice


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


def _run(dataset, out, config_text: str | None, tmp_path):
    """`dem-graph run` on ``dataset`` (with ``config_text`` as its --config): the printed summary and the measured yield."""
    import json

    from click.testing import CliRunner

    from dem_graph.cli import main

    args = ["--no-progress", "run", str(dataset), "--estimator", "ptpm", "--out", str(out)]
    if config_text is not None:
        (tmp_path / f"{out.name}.yaml").write_text(config_text)
        args += ["--config", str(tmp_path / f"{out.name}.yaml")]
    result = CliRunner().invoke(main, args)
    assert result.exit_code == 0, result.output
    return result.output, TrackingYield.model_validate(json.loads((out / "metrics.json").read_text())["tracking"])


def test_a_run_whose_search_is_too_small_warns_and_names_the_setting(tiny_folder, tmp_path):
    """A real run (the 0.5 m smoke log, 8 frames) with search regions capped at 1 px: the searches
    are refused as too large (measured: all 498; a region's half size is at least 2 px but for an exact
    prediction), and the summary names frontend.tracker.max_search_half_size_px; the same run with the
    defaults matches nearly all (measured: 569 of 569) and says nothing."""
    output, bad = _run(tiny_folder, tmp_path / "small_search", "frontend:\n  tracker:\n    max_search_half_size_px: 1\n", tmp_path)
    assert bad.searches > 100 and bad.matched_fraction < LOW_YIELD_FRACTION
    assert max(bad.failed_fraction, key=bad.failed_fraction.get) == "search_too_large" and bad.failed_fraction["search_too_large"] > 0.5
    warnings = [line for line in output.splitlines() if line.startswith("warning: only")]
    assert warnings == [yield_advice(bad)] and "frontend.tracker.max_search_half_size_px" in warnings[0]
    output, good = _run(tiny_folder, tmp_path / "defaults", None, tmp_path)
    assert good.searches > 100 and good.matched_fraction > 0.9 >= LOW_YIELD_FRACTION
    assert yield_advice(good) is None and "warning: only" not in output
