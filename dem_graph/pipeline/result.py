"""What a run gives: the estimator's result, the configuration it ran with, its metrics and its DEM."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from dem_graph.estimators.base import EstimatorResult
from dem_graph.pipeline.config import RunConfig
from dem_graph.pipeline.live_run import LiveRun
from dem_graph.pipeline.metrics import RunMetrics
from dem_graph.pipeline.run_dem import RunDem


@dataclass
class RunResult:
    estimator: EstimatorResult
    config: RunConfig
    metrics: RunMetrics = field(default_factory=RunMetrics)
    error: str | None = None  # set when the loop stopped early; the result holds what was done
    interrupted: bool = False  # stopped by Ctrl-C or SIGTERM (``error`` says after how many frames)
    elapsed_s: float = 0.0
    dem: RunDem | None = None  # the dense DEM from the run's poses (None if it could not be made)
    paths: dict[str, Path] = field(default_factory=dict)  # the run folder's files, once written
    live: LiveRun | None = None  # the live map as it was built, with its meter and saved maps


__all__ = ["RunResult"]
