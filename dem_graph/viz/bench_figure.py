"""The paper's Fig. 12: time per frame against the number of live points, one line per estimator.

Each line joins the median time per frame of the benchmark's rows for one estimator, in order of
their live points (median per frame); a band spans from the median to the 95th percentile; a
horizontal line marks 40 ms, the time one frame has at 25 Hz. The time axis is logarithmic.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import numpy as np

from dem_graph.evaluation.timing import TimingStats
from dem_graph.viz.plotting import colour, pyplot, save_figure

FRAME_BUDGET_MS = 40.0  # one camera frame at 25 Hz


class TimedRow(Protocol):
    """What the figure reads of a benchmark's row (:class:`dem_graph.studies.bench_estimators.BenchRow`)."""

    estimator: str
    max_points: int
    frame: TimingStats
    live_points_median: float


@dataclass(frozen=True)
class TimeSeries:
    """One estimator's line: its rows in order of live points."""

    live_points: np.ndarray  # median live points per frame of each row
    median_ms: np.ndarray  # median time per frame
    p95_ms: np.ndarray  # 95th percentile of the time per frame


@dataclass
class BenchFigure:
    path: Path
    figure: object  # the matplotlib Figure (closed: its lines can still be read)
    series: dict[str, TimeSeries]  # what was plotted, per estimator


def time_series(rows: list[TimedRow]) -> dict[str, TimeSeries]:
    """The benchmark's rows grouped by estimator (in the order they first appear), each sorted by live points."""
    series = {}
    for name in dict.fromkeys(r.estimator for r in rows):
        mine = sorted((r for r in rows if r.estimator == name), key=lambda r: (r.live_points_median, r.max_points))
        series[name] = TimeSeries(
            np.array([r.live_points_median for r in mine], dtype=float),
            np.array([r.frame.median_ms for r in mine], dtype=float),
            np.array([r.frame.p95_ms for r in mine], dtype=float),
        )
    return series


def time_per_frame_figure(path: str | Path, rows: list[TimedRow], title: str = "") -> BenchFigure:
    """Fig. 12 as a PNG at ``path``: median time per frame (line) and up to its 95th percentile (band)
    against the live points per frame, one line per estimator, and the 40 ms (25 Hz) budget."""
    import matplotlib.ticker

    plt = pyplot()
    series = time_series(rows)
    fig, ax = plt.subplots(figsize=(8.0, 5.0))
    for k, (name, s) in enumerate(series.items()):
        c = colour(name if name != "isam2-process" else "isam2", k)
        style = "--" if name == "isam2-process" else "-"
        ax.plot(s.live_points, s.median_ms, style, marker="o", color=c, lw=1.5, ms=4, label=f"{name} (median)")
        ax.fill_between(s.live_points, s.median_ms, s.p95_ms, color=c, alpha=0.15, lw=0, label=f"{name} (to p95)")
    ax.axhline(FRAME_BUDGET_MS, color="k", ls=":", lw=1.2, label=f"{FRAME_BUDGET_MS:g} ms (25 Hz)")
    ax.set_xlabel("live points per frame (median)")
    ax.set_ylabel("time per frame (ms, log scale)")
    # a log scale: from 50 to 500 points the times span two decades, and the p95 of an in-process
    # graph would flatten every other line on a linear one
    ax.set_yscale("log")
    ax.yaxis.set_major_formatter(matplotlib.ticker.FuncFormatter(lambda v, _: f"{v:g}"))
    ax.set_title(title or "Time per frame against the number of points (Fig. 12)", fontsize=10)
    ax.grid(True, alpha=0.3)
    ax.legend(loc="upper left", fontsize=8, ncol=2)
    return BenchFigure(save_figure(fig, path), fig, series)


__all__ = ["FRAME_BUDGET_MS", "BenchFigure", "TimeSeries", "time_per_frame_figure", "time_series"]
