"""A run's metrics beyond the trajectory: the tracking yield (pipeline/metrics.py)."""

from __future__ import annotations

import pytest

from dem_graph.pipeline.metrics import summary_lines, tracking_yield


def test_tracking_yield_from_the_counters():
    counters = {"track_ok": 60, "track_ambiguous": 25, "track_low_score": 10, "track_out_of_image": 5, "track_low_texture": 0, "outlier_rejected": 6, "added_laser": 99}
    y = tracking_yield(counters)
    assert y.searches == 100 and y.matched_fraction == pytest.approx(0.60) and y.outlier_fraction_of_matched == pytest.approx(0.10)
    assert list(y.failed_fraction.items()) == [("ambiguous", 0.25), ("low_score", 0.10), ("out_of_image", 0.05)]  # largest first, none of 0
    assert tracking_yield({"added_laser": 3}) is None


def test_a_run_reports_its_yield_and_prints_it(smoke_run):
    """The run's counters and its yield agree, and the printed line says it (PTPM on `smoke`)."""
    run = smoke_run({"estimator": "ptpm"}, with_dem=False)  # run_estimator(smoke_log, RunConfig(estimator="ptpm"), with_dem=False), made once in the session
    m = run.metrics
    ev = m.events
    searched = sum(v for k, v in ev.items() if k.startswith("track_"))
    assert m.tracking.searches == searched and m.tracking.matched_fraction == pytest.approx(ev["track_ok"] / searched)
    assert sum(m.tracking.failed_fraction.values()) + m.tracking.matched_fraction == pytest.approx(1.0)
    (line,) = [x for x in summary_lines(m) if x.startswith("tracking: ")]
    assert line.startswith(f"tracking: {100 * m.tracking.matched_fraction:.0f} % of {searched} searches matched")
