"""dem_graph: camera + single-line laser SLAM and dense Digital Elevation Maps.

Conventions (see docs/concepts/frames.md): world z-up; body x-forward, y-left, z-up; camera OpenCV
(x right, y down, z forward); ``T_a_b`` maps coordinates in frame b to frame a.
6-vectors and 6x6 covariances follow gtsam's Pose3 tangent order [rotation, translation].

What a script or a notebook needs is importable from here::

    from dem_graph import RunOverrides, open_dataset, run_dataset, scenario, simulate

The names are loaded on first use (PEP 562), so ``import dem_graph`` stays light: the pipeline
pulls in gtsam, open3d and numba, seconds of start-up a command like ``dem-graph --help`` does not need.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

from dem_graph.errors import ConfigError, DatasetError, DemGraphError, MissingDependencyError

__version__ = "0.1.0"

# name -> the module that defines it
_EXPORTS = {
    # a run: one estimator over one dataset (what `dem-graph run` runs)
    "run_dataset": "dem_graph.pipeline.run",
    "run_estimator": "dem_graph.pipeline.run",
    "run_config": "dem_graph.pipeline.config",
    "RunConfig": "dem_graph.pipeline.config",
    "RunOverrides": "dem_graph.pipeline.config",
    "ESTIMATORS": "dem_graph.pipeline.config",
    "RunResult": "dem_graph.pipeline.result",
    # the live pipeline: events in, a local map per frame out
    "LivePipeline": "dem_graph.pipeline.live",
    "LiveUpdate": "dem_graph.pipeline.live",
    # datasets and their events
    "open_dataset": "dem_graph.datasets.open",
    "DatasetOptions": "dem_graph.datasets.open",
    "Sequence": "dem_graph.datasets.base",
    "CameraFrame": "dem_graph.datasets.events",
    "LaserScan": "dem_graph.datasets.events",
    "Odometry": "dem_graph.datasets.events",
    "ImuSample": "dem_graph.datasets.events",
    # the sensor rig
    "SensorRig": "dem_graph.geometry.rig",
    "load_rig": "dem_graph.geometry.rig",
    "save_rig": "dem_graph.geometry.rig",
    "default_rig": "dem_graph.geometry.rig",
    # the simulator
    "scenario": "dem_graph.sim.scenarios",
    "simulate": "dem_graph.sim.pipeline",
    # studies
    "compare": "dem_graph.studies.compare",
    "evaluate_run": "dem_graph.studies.evaluate",
}

__all__ = [  # the errors, then _EXPORTS' names (written out for linters; tests/test_docs_snippets.py checks they agree)
    "ConfigError", "DatasetError", "DemGraphError", "MissingDependencyError", "__version__",
    "run_dataset", "run_estimator", "run_config", "RunConfig", "RunOverrides", "ESTIMATORS", "RunResult",
    "LivePipeline", "LiveUpdate",
    "open_dataset", "DatasetOptions", "Sequence", "CameraFrame", "LaserScan", "Odometry", "ImuSample",
    "SensorRig", "load_rig", "save_rig", "default_rig",
    "scenario", "simulate",
    "compare", "evaluate_run",
]  # fmt: skip

if TYPE_CHECKING:  # for type checkers and editors; at run time __getattr__ loads them
    from dem_graph.datasets.base import Sequence
    from dem_graph.datasets.events import CameraFrame, ImuSample, LaserScan, Odometry
    from dem_graph.datasets.open import DatasetOptions, open_dataset
    from dem_graph.geometry.rig import SensorRig, default_rig, load_rig, save_rig
    from dem_graph.pipeline.config import ESTIMATORS, RunConfig, RunOverrides, run_config
    from dem_graph.pipeline.live import LivePipeline, LiveUpdate
    from dem_graph.pipeline.result import RunResult
    from dem_graph.pipeline.run import run_dataset, run_estimator
    from dem_graph.sim.pipeline import simulate
    from dem_graph.sim.scenarios import scenario
    from dem_graph.studies.compare import compare
    from dem_graph.studies.evaluate import evaluate_run


def __getattr__(name: str):
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'dem_graph' has no attribute '{name}'")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value  # loaded once
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_EXPORTS))
