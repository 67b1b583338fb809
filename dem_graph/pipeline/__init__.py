"""The run: one estimator over one dataset, from its configuration to its run folder.

- :mod:`~dem_graph.pipeline.config`: the typed run configuration and its layering (defaults < the
  dataset's run settings < a YAML file < explicit overrides), in :func:`run_config`;
- :mod:`~dem_graph.pipeline.run`: the loop (:func:`run_estimator`) and :func:`run_dataset`, what
  ``dem-graph run`` runs, as one call;
- :mod:`~dem_graph.pipeline.run_dem`: the run's DEM from its poses, and its figures against the truth;
- :mod:`~dem_graph.pipeline.metrics`: the run's metrics (``metrics.json``);
- :mod:`~dem_graph.pipeline.run_folder`: the run folder, written and read back.
"""

from dem_graph.pipeline.config import ESTIMATORS, DemConfig, RunConfig, RunOverrides, run_config
from dem_graph.pipeline.result import RunResult
from dem_graph.pipeline.run import run_dataset, run_estimator
from dem_graph.pipeline.run_folder import write_run

__all__ = ["DemConfig", "ESTIMATORS", "RunConfig", "RunOverrides", "RunResult", "run_config", "run_dataset", "run_estimator", "write_run"]
