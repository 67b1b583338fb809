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
