"""The accuracy of one run folder against a dataset's ground truth (``dem-graph evaluate RUN --dataset DATASET``).

From the files of the run folder (see :mod:`dem_graph.pipeline.run_folder`):

- ``trajectory.tum`` (and ``trajectory_*.tum``, e.g. isam2's smoothed poses): anchored and aligned
  ATE, drift in % of distance and the RPE over 10 m (:func:`accuracy_summary`);
- ``poses.npz``, ``points.ply`` and the dataset's scans: the DEM made again, its height errors over
  the covered cells and over the laser-swept ones (RMSE, mean, std, 95th percentile of the absolute
  error), the corridor's coverage and the Fig. 8 local error (:func:`run_folder_dem`);
- ``metrics.json``, when there is one: the run's own measurements that need no truth (estimator,
  frames, time and points per frame) are carried over as they are.

The result has the layout of a run's ``metrics.json``, so :mod:`dem_graph.studies.headline`
reads both.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

from pydantic import ValidationError

from dem_graph.config_types import format_validation_error
from dem_graph.datasets.base import GroundTruth, Sequence
from dem_graph.datasets.open import open_sequence
from dem_graph.errors import DatasetError, DemGraphError
from dem_graph.estimators.base import EXTRA_TRAJECTORIES
from dem_graph.evaluation.trajectory_metrics import TrajectoryAccuracy, accuracy_summary, within_truth_span
from dem_graph.io.tum import read_tum
from dem_graph.pipeline.metrics import RunMetrics
from dem_graph.pipeline.run_dem import DemFailure, DemMetrics, RunDem
from dem_graph.pipeline.run_folder import (
    METRICS_JSON,
    POSES_NPZ,
    TRAJECTORY_TUM,
    read_run_metrics,
    run_folder_config,
    run_folder_dem,
    write_json,
)
from dem_graph.studies.headline import COLUMNS, format_value, headline

log = logging.getLogger(__name__)

EVALUATION_JSON = "evaluation.json"
# what a run measured that needs no truth: carried over from its metrics.json
_CARRIED = ("estimator", "frames", "elapsed_s", "error", "time_per_frame", "points_per_frame", "map_points")


def require_ground_truth(sequence: Sequence) -> GroundTruth:
    """The dataset's ground truth; :class:`DatasetError` naming the missing file when it has none."""
    if sequence.ground_truth is not None:
        return sequence.ground_truth
    root = getattr(sequence, "path", None)
    where = Path(root) / "ground_truth" / "trajectory.tum" if root is not None else sequence.name
    raise DatasetError(where, "not found: the dataset has no ground truth to evaluate against")


@dataclass
class RunEvaluation:
    """The metrics of one run folder against a truth, laid out as a run's ``metrics.json``."""

    run_dir: Path
    dataset: str
    metrics: RunMetrics = field(default_factory=RunMetrics)
    dem: RunDem | None = None  # the DEM made again, for figures (None without poses.npz)

    @property
    def headline(self) -> dict[str, float]:
        return headline(self.metrics)

    def table(self) -> str:
        """A short table: one line per number (the headline columns, then the DEM's details)."""
        values = self.headline
        rows = [[c.label, format_value(c, values[c.key])] for c in COLUMNS]
        m = self.metrics
        if m.trajectory is not None and m.trajectory.rpe.reason:
            rows.append(["RPE 10 m", m.trajectory.rpe.reason])
        dem = m.dem
        if isinstance(dem, DemMetrics):
            for e, label in ((dem.height_error, "all covered cells"), (dem.height_error_laser_cells, "laser-swept cells")):
                if e is not None and e.cells:
                    rows.append([f"DEM error, {label} (cm)", f"RMSE {100 * e.rmse_m:.2f}, mean {100 * e.mean_m:.2f}, std {100 * e.std_m:.2f}, p95 |e| {100 * e.p95_abs_m:.2f} ({e.cells} cells)"])
            c = dem.corridor
            if c is not None and c.corridor_cells:
                rows.append(["corridor coverage (%)", f"{100 * c.coverage:.1f} of {c.corridor_cells} cells within {c.half_width_m:g} m of the path"])
        elif isinstance(dem, DemFailure):
            rows.append(["DEM", f"not made ({dem.error})"])
        title = f"{self.run_dir} ({m.estimator or 'unknown estimator'}, {m.frames if m.frames is not None else '?'} frames) against {self.dataset}"
        width = max(len(label) for label, _ in rows)
        return "\n".join([title, *(f"  {label.ljust(width)}  {value}" for label, value in rows)])

    def as_dict(self) -> dict:
        return {"run_dir": str(self.run_dir), "dataset": self.dataset, "headline": self.headline, "metrics": self.metrics.to_json_dict()}

    def write_json(self, path: str | Path) -> Path:
        return write_json(path, self.as_dict(), "the evaluation")


def _trajectory_accuracy(path: Path, truth: GroundTruth) -> TrajectoryAccuracy:
    estimate, covered = within_truth_span(read_tum(path), truth.trajectory)
    if estimate is None:
        raise DatasetError(
            path, f"cannot be compared with the ground truth: {int(covered.sum())} of its {len(covered)} times lie inside the truth's span"
        )
    try:
        return accuracy_summary(estimate, truth.trajectory)
    except DemGraphError as exc:
        raise DatasetError(path, f"cannot be compared with the ground truth: {exc}") from None


def evaluate_run(run_dir: str | Path, sequence: Sequence | str | Path, with_dem: bool = True) -> RunEvaluation:
    """The metrics of the run folder ``run_dir`` against the ground truth of ``sequence`` (the dataset,
    or its folder, the run was made from: its laser scans make the DEM again). See the module for
    what is measured.

    Raises :class:`DatasetError` naming the file for a missing run folder, a missing or malformed
    ``trajectory.tum``, a dataset without ground truth, or a run whose times lie outside the truth's.
    A run folder without ``poses.npz`` gets no DEM metrics (``metrics.dem.error`` says why).
    """
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise DatasetError(run_dir, "run folder not found" if not run_dir.exists() else "not a folder")
    own = read_run_metrics(run_dir)
    sequence = open_sequence(sequence, own.get("dataset_options"))  # a KITTI run's ring, ...
    truth = require_ground_truth(sequence)
    try:
        metrics = RunMetrics.model_validate({k: own[k] for k in _CARRIED if k in own})
    except ValidationError as exc:
        raise DatasetError(run_dir / METRICS_JSON, f"not a run's metrics: {format_validation_error(exc)}") from None
    metrics.trajectory = _trajectory_accuracy(run_dir / TRAJECTORY_TUM, truth)
    for extra in sorted(run_dir.glob("trajectory_*.tum")):
        if extra.stem in EXTRA_TRAJECTORIES:
            setattr(metrics, extra.stem, _trajectory_accuracy(extra, truth))
        else:
            log.warning("%s: not a trajectory a run writes (%s): not evaluated", extra, ", ".join(f"{k}.tum" for k in EXTRA_TRAJECTORIES))
    dem = None
    if with_dem:
        if (run_dir / POSES_NPZ).is_file():
            config = run_folder_config(run_dir)
            dem = run_folder_dem(run_dir, sequence, None, config, local_errors=True)
            metrics.dem = dem.metrics
        else:
            metrics.dem = DemFailure(error=f"no {POSES_NPZ} in the run folder to make the DEM from")
    dataset = str(getattr(sequence, "path", sequence.name))
    _warn_if_another_dataset(run_dir, own.get("dataset"), dataset)
    return RunEvaluation(run_dir, dataset, metrics, dem)


def _warn_if_another_dataset(run_dir: Path, recorded: str | None, dataset: str) -> None:
    """A warning when the run folder names another dataset than the one it is evaluated against."""
    if recorded and Path(recorded).resolve() != Path(dataset).resolve():
        log.warning(
            "%s was made from %s, not %s: these metrics compare it with another dataset's truth", run_dir / METRICS_JSON, recorded, dataset
        )


__all__ = ["EVALUATION_JSON", "METRICS_JSON", "RunEvaluation", "evaluate_run", "require_ground_truth"]
