"""Accuracy against cost: one point per run of an estimator study, ATE against time per frame."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Protocol

from dem_graph.viz.bench_figure import FRAME_BUDGET_MS
from dem_graph.viz.plotting import colour, pyplot, save_figure

_MARKERS = ("o", "s", "^", "D", "v", "P", "X")


class RunPoint(Protocol):
    """What the figure reads of a study's row (:class:`dem_graph.studies.study.StudyRow`)."""

    estimator: str
    speed_mps: float
    ate_m: float
    frame_ms_median: float


def accuracy_cost_figure(path: str | Path, rows: list[RunPoint], title: str = "") -> Path:
    """Each run with a finite ATE as a point: median time per frame (x) against ATE anchored at
    the initial pose (y); colour per estimator, marker per speed; the 40 ms (25 Hz) budget dashed."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(8.0, 5.5))
    speeds = sorted({r.speed_mps for r in rows})
    names = list(dict.fromkeys(r.estimator for r in rows))
    for k, name in enumerate(names):
        for j, speed in enumerate(speeds):
            mine = [r for r in rows if r.estimator == name and r.speed_mps == speed and math.isfinite(r.ate_m) and math.isfinite(r.frame_ms_median)]
            if mine:
                ax.scatter([r.frame_ms_median for r in mine], [r.ate_m for r in mine], color=colour(name, k), marker=_MARKERS[j % len(_MARKERS)],
                           s=36, alpha=0.8, label=f"{name}, {speed:g} m/s")
    ax.axvline(FRAME_BUDGET_MS, color="k", ls=":", lw=1.2, label=f"{FRAME_BUDGET_MS:g} ms (25 Hz)")
    ax.set_xlabel("time per frame, median (ms)")
    ax.set_ylabel("ATE, anchored at the initial pose (m)")
    ax.set_xlim(left=0.0)
    ax.set_ylim(bottom=0.0)
    ax.set_title(title or "Accuracy against cost, one point per run", fontsize=10)
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best", fontsize=7, ncol=2)
    return save_figure(fig, path)


__all__ = ["accuracy_cost_figure"]
