"""The estimators side by side on one dataset (``dem-graph compare DATASET --out DIR``).

Every estimator runs on the same data with the same settings (front end, motion model, DEM); only
``estimator`` differs. Each run is written to ``DIR/<estimator>/`` as ``dem-graph run`` writes it;
then::

    DIR/summary.json     every run's headline numbers (from its metrics.json), status and error
    DIR/report.md        the table and the figures (linked from DIR/figures/)
    DIR/report.html      the same in one file, the figures embedded
    DIR/figures/*.png    trajectories from above, position error, Fig. 8 local DEM error, best DEM and its error

A run that fails is kept in the table as failed, with its one-line error, and the others go on; a
run that stops part way (a corrupt image late in the log) keeps what it had, marked as stopped.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dem_graph.datasets.base import Sequence
from dem_graph.datasets.open import open_sequence
from dem_graph.dem.layers import Dem
from dem_graph.errors import DatasetError, DemGraphError, one_line
from dem_graph.estimators.odometry_only import ODOMETRY_BASELINE
from dem_graph.evaluation.dem_metrics import LocalErrorSeries
from dem_graph.evaluation.timing import format_table, machine_description
from dem_graph.geometry.trajectory import Trajectory
from dem_graph.pipeline.config import ESTIMATORS, RunConfig, run_config
from dem_graph.pipeline.metrics import RunMetrics
from dem_graph.pipeline.run import run_estimator
from dem_graph.pipeline.run_folder import prepare_run_folder, write_json, write_run
from dem_graph.progress import progress
from dem_graph.studies.headline import COLUMNS, format_value, headline
from dem_graph.studies.report import Figure, ReportPage

log = logging.getLogger(__name__)

SUMMARY_JSON = "summary.json"
REPORT_MD = "report.md"
REPORT_HTML = "report.html"
FIGURES_DIR = "figures"


@dataclass
class EstimatorRun:
    """One estimator's run in a comparison."""

    estimator: str
    run_dir: Path
    status: str  # "ok"; "stopped": the loop failed part way, the results up to there are kept; "failed": an error, or a run that measured nothing (its tracking failed: metrics.failure)
    error: str | None = None
    metrics: RunMetrics | None = None  # as in its metrics.json (None when it failed)
    trajectory: Trajectory | None = None  # its trajectory.tum
    local_series: LocalErrorSeries | None = None  # the Fig. 8 measure frame by frame

    @property
    def headline(self) -> dict[str, float]:
        return headline(self.metrics)

    def status_text(self) -> str:
        return self.status if self.error is None else f"{self.status}: {self.error}"


@dataclass
class BestDem:
    estimator: str
    dem: Dem
    path_xy: np.ndarray  # the run's positions, for drawing
    rmse_m: float  # its height RMSE over the laser-swept cells


@dataclass
class Comparison:
    dataset: str
    out_dir: Path
    runs: list[EstimatorRun]
    max_frames: int | None = None
    best_dem: BestDem | None = None
    paths: dict[str, Path] = field(default_factory=dict)  # summary, report_md, report_html and each figure
    figure_error: str | None = None  # why the figures are missing, if they are

    def rows(self) -> list[list[str]]:
        """One row per estimator: its name, each headline column as shown, its status."""
        return [[r.estimator, *(format_value(c, r.headline[c.key]) for c in COLUMNS), r.status_text()] for r in self.runs]

    @property
    def headers(self) -> list[str]:
        return ["estimator", *(c.label for c in COLUMNS), "status"]

    def table(self) -> str:
        frames = f", at most {self.max_frames} frames" if self.max_frames else ""
        return format_table(self.headers, self.rows(), title=f"estimators on {self.dataset}{frames}")

    def as_dict(self) -> dict:
        """The content of ``summary.json``."""
        return {
            "dataset": self.dataset,
            "max_frames": self.max_frames,
            "machine": machine_description(),
            "columns": {c.key: c.label for c in COLUMNS},
            "estimators": [r.estimator for r in self.runs],  # in the order they ran (the keys of "runs" are sorted)
            "runs": {
                r.estimator: {"status": r.status, "error": r.error, "run_dir": r.run_dir.name, "headline": r.headline}
                for r in self.runs
            },
            "best_dem": None if self.best_dem is None else self.best_dem.estimator,
            "figures": [p.relative_to(self.out_dir).as_posix() for k, p in self.paths.items() if k.startswith("figure_")],
        }


def parse_estimators(text: str | list[str] | tuple[str, ...]) -> tuple[str, ...]:
    """Estimator names from ``"gm,ptpm"`` or a sequence, in order, without repeats (``odometry``,
    the odometry-only baseline, among them); unknown names are an error."""
    known = (ODOMETRY_BASELINE, *ESTIMATORS)
    names = [n.strip() for n in (text.split(",") if isinstance(text, str) else text)]
    names = list(dict.fromkeys(n for n in names if n))
    unknown = [n for n in names if n not in known]
    if unknown or not names:
        raise DemGraphError(f"unknown estimator {', '.join(repr(n) for n in unknown) or '(none given)'}: choose from {', '.join(known)}")
    return tuple(names)


def default_estimators(sequence: Sequence) -> tuple[str, ...]:
    """What ``compare`` runs unless told: the odometry-only baseline first when the log has
    odometry (what the camera and the laser add is then in every table), then every estimator."""
    return ((ODOMETRY_BASELINE,) if sequence.has_odometry else ()) + ESTIMATORS


def _run_one(sequence: Sequence, config: RunConfig, name: str, run_dir: Path, dataset: str) -> tuple[EstimatorRun, BestDem | None]:
    cfg = config.model_copy(deep=True)
    cfg.estimator = name
    try:
        result = run_estimator(sequence, cfg)
        result.metrics.dataset = dataset
        result.metrics.dataset_options = sequence.open_options()
        prepare_run_folder(run_dir, overwrite=True)  # no file of an earlier comparison's run stays beside this one's
        write_run(result, run_dir)
    except DemGraphError as exc:
        log.error("%s failed: %s", name, exc)
        return EstimatorRun(name, run_dir, "failed", one_line(exc)), None
    except Exception as exc:  # a bug or a library's own error: the other runs still go on
        log.exception("%s failed", name)
        return EstimatorRun(name, run_dir, "failed", f"{type(exc).__name__}: {one_line(exc)}"), None
    status, why = "ok", None
    if result.error:
        status, why = "stopped", " ".join(result.error.split())
    elif result.metrics.failure:  # it ran, and measured nothing: not a result, though its files are there
        status, why = "failed", result.metrics.failure
        log.error("%s failed: %s", name, why)
    entry = EstimatorRun(name, run_dir, status, why, result.metrics, result.estimator.trajectory(), result.dem.local_series if result.dem is not None else None)
    dem = None
    rmse = entry.headline["dem_rmse_laser_cells_m"]
    if result.dem is not None and math.isfinite(rmse) and status != "failed":
        dem = BestDem(name, result.dem.dem, result.dem.poses.T_world_body[:, :2, 3].copy(), rmse)
    return entry, dem


def _warm_up(sequence: Sequence, config: RunConfig, name: str, frames: int) -> None:
    cfg = config.model_copy(deep=True)
    cfg.estimator = name
    cfg.max_frames = frames
    try:
        run_estimator(sequence, cfg, with_dem=False)
    except Exception as exc:  # the real run meets it again and reports it
        log.debug("warm-up run failed: %s", exc)


def compare(
    sequence: Sequence | str | Path,
    out_dir: str | Path,
    estimators: str | tuple[str, ...] | None = None,
    config: RunConfig | None = None,
    dataset: str | Path | None = None,
    warm_up_frames: int = 3,
) -> Comparison:
    """Run each of ``estimators`` on ``sequence`` (a dataset, or its folder) with ``config`` (its
    ``estimator`` field is set per run; None: the defaults with the dataset's run settings), write every run folder, ``summary.json``, the figures and
    the report into ``out_dir``. ``dataset`` names the data in the outputs (default: the sequence's
    folder, else its name).

    Before the runs, the first estimator runs untimed on ``warm_up_frames`` frames (0: not at all),
    so that what the process loads once (compiled kernels, caches) does not count in the first
    run's time per frame only."""
    sequence = open_sequence(sequence)
    names = parse_estimators(estimators if estimators is not None else default_estimators(sequence))
    config = config or run_config(sequence)
    out_dir = Path(out_dir)
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise DatasetError(out_dir, f"cannot create the folder ({exc.strerror or exc})") from None
    dataset = str(dataset if dataset is not None else getattr(sequence, "path", sequence.name))
    comparison = Comparison(dataset, out_dir, [], config.max_frames)
    if warm_up_frames:
        _warm_up(sequence, config, names[0], warm_up_frames)
    for name in progress(names, total=len(names), desc="compare", unit="run"):
        log.info("compare: running %s", name)
        entry, dem = _run_one(sequence, config, name, out_dir / name, dataset)
        comparison.runs.append(entry)
        if dem is not None and (comparison.best_dem is None or dem.rmse_m < comparison.best_dem.rmse_m):
            comparison.best_dem = dem
    try:
        comparison.paths.update(write_figures(comparison, sequence, config))
    except DemGraphError as exc:  # the runs and their numbers are kept: only the pictures are lost
        log.warning("the comparison's figures could not be drawn: %s", exc)
        comparison.figure_error = one_line(exc)
    comparison.paths["summary"] = write_json(out_dir / SUMMARY_JSON, comparison.as_dict(), "the comparison summary")
    md, html = report_page(comparison, config).write(out_dir / REPORT_MD, out_dir / REPORT_HTML)
    comparison.paths.update(report_md=md, report_html=html)
    return comparison


def write_figures(comparison: Comparison, sequence: Sequence, config: RunConfig) -> dict[str, Path]:
    """The comparison's figures into ``out_dir/figures`` (those that need the truth only with it)."""
    from dem_graph.viz import compare_figures as figures

    folder = comparison.out_dir / FIGURES_DIR
    try:
        folder.mkdir(exist_ok=True)
    except OSError as exc:
        raise DatasetError(folder, f"cannot create the folder ({exc.strerror or exc})") from None
    truth = sequence.ground_truth
    t0 = sequence.t_start_s
    estimates = {r.estimator: r.trajectory for r in comparison.runs if r.trajectory is not None}
    paths = {"figure_trajectories": figures.trajectories_figure(folder / "trajectories.png", truth.trajectory if truth else None, estimates)}
    if truth is None:
        return paths
    paths["figure_position_error"] = figures.position_error_figure(folder / "position_error.png", truth.trajectory, estimates, t0)
    series = {r.estimator: r.local_series for r in comparison.runs if r.local_series is not None}
    if series:
        w = config.local_error
        window = f"{w.length_m:g} x {w.width_m:g} m from {w.start_m:g} m ahead"
        paths["figure_local_error"] = figures.local_error_figure(folder / "local_dem_error.png", series, t0, window)
    best = comparison.best_dem
    if best is not None and truth.elevation is not None:
        paths["figure_best_dem"] = figures.dem_error_figure(folder / "best_dem_error.png", best.dem, truth.elevation, best.estimator, best.path_xy)
    return paths


_CAPTIONS = {
    "figure_trajectories": "Trajectories from above, with the ground truth over the same time (the paper's Fig. 10).",
    "figure_position_error": "Position error against time, anchored at the initial pose (Fig. 11).",
    "figure_local_error": "Height error of the local DEM in the window ahead of the vehicle: mean and standard deviation against time (Fig. 8).",
    "figure_best_dem": "The DEM of the estimator with the lowest DEM RMSE, and its height error against the ground-truth terrain at the cell centres.",
}


def report_page(comparison: Comparison, config: RunConfig) -> ReportPage:
    done = sum(r.status != "failed" for r in comparison.runs)
    frames = f"at most {comparison.max_frames} camera frames" if comparison.max_frames else "every camera frame"
    paragraphs = [
        f"Dataset: {comparison.dataset}; {frames}; {done} of {len(comparison.runs)} runs completed. "
        f"Every estimator ran with the same front end, motion model and DEM settings (motion model {config.motion.model}, "
        f"at most {config.frontend.max_points} live points); each run folder is DIR/<estimator>/.",
        "ATE: RMS position error anchored at the initial pose, and after the best rigid alignment; drift: final error in % of the "
        "distance travelled; RPE 10 m: RMS relative-pose error between poses 10 m apart along the ground truth ('-' for a shorter run); "
        "DEM RMSE: height error over the cells a laser return reached; Fig. 8: mean over time of the local DEM's mean and standard "
        "deviation of the height error ahead of the vehicle, in hindsight (made from the run's final poses); live Fig. 8: the same "
        "on the live map as the guidance had it at each frame; time per frame includes tracking; points/frame: live points, median; "
        "map ms: the live map's update per frame (scans placed, revisions, the local map), median.",
    ]
    notes = [f"{r.estimator}: {r.status_text()}" for r in comparison.runs if r.status != "ok"]
    if comparison.figure_error:
        notes.append(f"figures not drawn: {comparison.figure_error}")
    if comparison.best_dem is not None:
        notes.append(f"best DEM: {comparison.best_dem.estimator} ({100 * comparison.best_dem.rmse_m:.2f} cm RMSE over the laser-swept cells)")
    figures = [Figure(p, _CAPTIONS[k]) for k, p in comparison.paths.items() if k in _CAPTIONS]
    return ReportPage("Estimator comparison", paragraphs, comparison.headers, comparison.rows(), figures, notes)


__all__ = ["Comparison", "EstimatorRun", "compare", "parse_estimators", "report_page", "write_figures"]
