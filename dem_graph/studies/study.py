"""Accuracy against cost of the estimators over several seeds, speeds and point budgets.

For each seed and speed the scenario is simulated once into a dataset folder
(``data_dir/<scenario>_seed<S>_<V>mps``); every estimator then runs on it with every point budget
(the cap on live points, with the focus cells and laser share set as ``dem-graph research bench`` sets
them, for the focus area at that speed, which is also the speed the run assumes before it has
measured one). A row holds the run's ATE (anchored and aligned), drift and time per frame (median and
p95, tracking included; for ``isam2-batch`` the online pass). No run folder and no DEM is
written: only the numbers.
"""

from __future__ import annotations

import csv
import math
from dataclasses import asdict, dataclass, fields
from pathlib import Path

import numpy as np

from dem_graph.datasets.folder import FolderSequence
from dem_graph.errors import DatasetError, DemGraphError, one_line
from dem_graph.evaluation.timing import format_table
from dem_graph.pipeline.config import ESTIMATORS, GRAPH_PROCESS, RunConfig, run_config, split_graph_process
from dem_graph.pipeline.run import run_estimator
from dem_graph.sim.pipeline import simulate
from dem_graph.sim.scenarios import scenario
from dem_graph.studies.bench_estimators import config_for_points, without_no_imu
from dem_graph.studies.compare import parse_estimators
from dem_graph.studies.grid import LOCAL, GridJob, JobFailure, run_grid
from dem_graph.studies.headline import headline


@dataclass(frozen=True)
class StudyRow:
    estimator: str
    seed: int
    speed_mps: float
    max_points: int
    ate_m: float  # anchored at the initial pose
    ate_aligned_m: float
    drift_percent: float
    frame_ms_median: float
    frame_ms_p95: float
    live_points: float  # median per frame
    status: str = "ok"  # or the one-line error of a run that failed or stopped
    final_height_error_m: float = math.nan  # signed, the last pose's z minus the truth's
    dem_rmse_m: float = math.nan  # the DEM's height RMSE over the laser cells
    matched_fraction: float = math.nan  # the tracking yield: searches for live points that matched
    pose_nees_mean: float = math.nan  # the poses' NEES against the truth, mean over the frames (6 for a consistent estimator)


def mean_or_nan(values: list[float]) -> float:
    """The mean, NaN for no value."""
    return float(np.mean(values)) if values else math.nan


def standard_error(values: list[float]) -> float:
    """The standard error of the mean (sample std / sqrt(n)), NaN for fewer than two values."""
    return float(np.std(values, ddof=1) / np.sqrt(len(values))) if len(values) > 1 else math.nan


@dataclass(frozen=True)
class EstimatorSummary:
    estimator: str
    runs: int  # runs with a finite ATE
    mean_ate_m: float
    mean_frame_ms: float  # mean over the runs of their median time per frame
    mean_final_height_error_m: float = math.nan  # signed: a drift one way shows here
    final_height_error_se_m: float = math.nan  # its standard error over the runs
    mean_dem_rmse_m: float = math.nan  # over the runs with a DEM


@dataclass
class StudyResult:
    rows: list[StudyRow]
    scenario: str
    frames: int | None  # camera frames per run at most (None: all)

    def table(self) -> str:
        headers = ["estimator", "seed", "speed (m/s)", "cap n", "ATE (m)", "ATE aligned (m)", "drift (%)", "end height error (m)", "DEM RMSE (cm)", "matched", "NEES mean",
                   "frame ms (median)", "frame ms (p95)", "live", "status"]
        rows = [
            [r.estimator, r.seed, f"{r.speed_mps:g}", r.max_points, f"{r.ate_m:.3f}", f"{r.ate_aligned_m:.3f}", f"{r.drift_percent:.2f}",
             f"{r.final_height_error_m:+.3f}", f"{100 * r.dem_rmse_m:.1f}", f"{r.matched_fraction:.2f}", f"{r.pose_nees_mean:.1f}",
             f"{r.frame_ms_median:.1f}", f"{r.frame_ms_p95:.1f}", f"{r.live_points:.0f}", r.status]
            for r in self.rows
        ]
        frames = f", at most {self.frames} frames per run" if self.frames else ""
        return format_table(headers, rows, title=f"estimator study on '{self.scenario}'{frames}")

    def summary(self) -> list[EstimatorSummary]:
        """Per estimator (in the order they ran): the mean ATE and mean time per frame of its runs with a finite ATE."""
        out = []
        for name in dict.fromkeys(r.estimator for r in self.rows):
            ok = [r for r in self.rows if r.estimator == name and math.isfinite(r.ate_m)]
            dz = [r.final_height_error_m for r in ok if math.isfinite(r.final_height_error_m)]
            dem = [r.dem_rmse_m for r in ok if math.isfinite(r.dem_rmse_m)]
            out.append(
                EstimatorSummary(
                    name, len(ok), mean_or_nan([r.ate_m for r in ok]), mean_or_nan([r.frame_ms_median for r in ok]), mean_or_nan(dz), standard_error(dz), mean_or_nan(dem)
                )
            )
        return out

    def conclusion(self) -> str:
        """What the rows say, in one paragraph: which estimator had the lowest mean ATE, at what cost,
        and the fastest one; built from the numbers only."""
        summary = [s for s in self.summary() if s.runs]
        if not summary:
            return "No run gave an ATE: nothing to conclude."
        best = min(summary, key=lambda s: s.mean_ate_m)
        fastest = min(summary, key=lambda s: s.mean_frame_ms)
        seeds = sorted({r.seed for r in self.rows})
        speeds = sorted({r.speed_mps for r in self.rows})
        budgets = sorted({r.max_points for r in self.rows})
        text = (
            f"Over {len(seeds)} seed(s), speed(s) {', '.join(f'{v:g}' for v in speeds)} m/s and point budget(s) {', '.join(map(str, budgets))} "
            f"on '{self.scenario}': {best.estimator} had the lowest mean ATE, {best.mean_ate_m:.3f} m over {best.runs} runs, "
            f"at {best.mean_frame_ms:.1f} ms per frame (mean of the medians). "
        )
        if fastest.estimator == best.estimator:
            text += "It was also the fastest."
        else:
            text += f"The fastest was {fastest.estimator} ({fastest.mean_frame_ms:.1f} ms per frame, mean ATE {fastest.mean_ate_m:.3f} m)."
        others = ", ".join(f"{s.estimator} {s.mean_ate_m:.3f} m at {s.mean_frame_ms:.1f} ms" for s in summary if s is not best)
        if others:
            text += f" Others: {others}."
        heights = [s for s in summary if math.isfinite(s.mean_final_height_error_m)]
        if heights:
            text += " Height error at the end, mean +- standard error: " + ", ".join(
                f"{s.estimator} {s.mean_final_height_error_m:+.3f} +- {s.final_height_error_se_m:.3f} m" for s in heights
            ) + "."
        dems = [s for s in summary if math.isfinite(s.mean_dem_rmse_m)]
        if dems:
            text += " Mean DEM RMSE over the laser cells: " + ", ".join(f"{s.estimator} {100 * s.mean_dem_rmse_m:.1f} cm" for s in dems) + "."
        failed = sum(r.status != "ok" for r in self.rows)
        if failed:
            text += f" {failed} run(s) failed or stopped early."
        return text

    def write_csv(self, path: str | Path) -> Path:
        return write_rows_csv(path, StudyRow, self.rows)


def parse_study_estimators(text: str) -> tuple[str, ...]:
    """The study's estimators from ``"gm,isam2"``: those ``compare`` knows, and ``isam2-process``;
    each may end in ``-noimu`` (the same estimator ignoring the dataset's IMU)."""
    names = [n.strip() for n in text.split(",") if n.strip()]
    others = [without_no_imu(n) for n in names if without_no_imu(n) != GRAPH_PROCESS]
    known = parse_estimators(others) if others else ()
    return tuple(dict.fromkeys(n for n in names if without_no_imu(n) == GRAPH_PROCESS or without_no_imu(n) in known))


def _study_config(sequence, name: str, speed_mps: float, max_points: int | None) -> RunConfig:
    """The run's configuration: ``dem-graph run``'s defaults for the dataset when ``max_points`` is
    None, else the bench's for that cap (:func:`config_for_points`)."""
    base = without_no_imu(name)
    if max_points is not None:
        config = config_for_points(base, max_points, sequence.rig, speed_mps)
    else:
        estimator, graph_process = split_graph_process(base)
        config = run_config(sequence).model_copy(update={"estimator": estimator}, deep=True)
        config.isam2.graph_process = graph_process
    config.motion.use_imu = base == name
    return config


def write_rows_csv(path: str | Path, row_type, rows) -> Path:
    """``rows`` (dataclasses of ``row_type``) as CSV at ``path``, a header of the field names first."""
    path = Path(path)
    try:
        with path.open("w", newline="") as f:
            writer = csv.writer(f)
            writer.writerow([f.name for f in fields(row_type)])
            writer.writerows(list(asdict(r).values()) for r in rows)
    except OSError as exc:
        raise DatasetError(path, f"cannot write ({exc.strerror or exc})") from None
    return path


def _run_row(sequence, name: str, seed: int, speed_mps: float, max_points: int | None, max_frames: int | None, realtime: bool = False) -> StudyRow:
    config = _study_config(sequence, name, speed_mps, max_points)
    config.max_frames = max_frames
    config.realtime = realtime
    cap = config.frontend.max_points
    nan = math.nan
    try:
        run = run_estimator(sequence, config)
    except DemGraphError as exc:
        return StudyRow(name, seed, speed_mps, cap, nan, nan, nan, nan, nan, nan, f"failed: {one_line(exc)}")
    h = headline(run.metrics)
    status = "ok" if run.error is None else f"stopped: {one_line(run.error)}"
    if run.error is None and run.metrics.failure:
        status = f"failed: {run.metrics.failure}"
    tracking = run.metrics.tracking
    return StudyRow(
        name, seed, speed_mps, cap, h["ate_anchored_rmse_m"], h["ate_aligned_rmse_m"], h["drift_percent"],
        h["time_per_frame_median_ms"], h["time_per_frame_p95_ms"], h["points_per_frame"], status,
        final_height_error_m=h["final_height_error_m"], dem_rmse_m=h["dem_rmse_laser_cells_m"],
        matched_fraction=nan if tracking is None else tracking.matched_fraction,
        pose_nees_mean=nan if run.metrics.pose_nees is None or run.metrics.pose_nees.mean is None else run.metrics.pose_nees.mean,
    )


def simulate_job(scenario_name: str, seed: int, speed_mps: float, length_m: float | None, folder: str) -> dict:
    """One of the study's datasets simulated into ``folder`` (a grid job: runs on a worker)."""
    simulate(scenario(scenario_name, seed=seed, speed_mps=speed_mps, length_m=length_m), folder, overwrite=True, preview=False)
    return {"folder": folder}


def run_job(folder: str, name: str, seed: int, speed_mps: float, max_points: int | None, max_frames: int | None, realtime: bool = False) -> dict:
    """One run of the study on the dataset in ``folder``, as a :class:`StudyRow`'s fields (a grid job);
    ``max_points`` None: ``dem-graph run``'s default settings; ``realtime``: the events at the camera's
    rate, as on the vehicle."""
    return asdict(_run_row(FolderSequence(folder), name, seed, speed_mps, max_points, max_frames, realtime))


def _dataset_name(scenario_name: str, seed: int, speed_mps: float, length_m: float | None) -> str:
    return f"{scenario_name}_seed{seed}_{speed_mps:g}mps" + ("" if length_m is None else f"_{length_m:g}m")


def estimator_study(
    data_dir: str | Path,
    scenario_name: str = "paper",
    seeds=(1, 2),
    speeds_mps=(1.5, 2.0, 5.0),
    point_budgets=(None,),
    estimators=ESTIMATORS,
    max_frames: int | None = None,
    length_m: float | None = None,
    scheduler: str = LOCAL,
    n_workers: int | None = None,
    realtime: bool = False,
) -> StudyResult:
    """Every estimator with every point budget on the scenario simulated for every seed and speed
    (``length_m`` shortens the drive; a budget None runs ``dem-graph run``'s default settings, a
    number the bench's for that cap; ``realtime`` gives each run its events at the camera's rate,
    which is fair only with a core per run), as a grid of jobs (:func:`~dem_graph.studies.grid.run_grid`):
    ``scheduler`` ``"local"`` (default) on a local Dask cluster, ``"serial"`` in this process, or the
    address of a Dask scheduler. Datasets go to ``data_dir/<scenario>_seed<S>_<V>mps[_<L>m]`` and each
    result to ``data_dir/study_results/``; a study started again keeps what is done there and runs
    the rest. A run that fails is a row with its error; the others go on."""
    data_dir = Path(data_dir)
    results_dir = data_dir / "study_results"
    datasets = {
        (seed, float(speed)): str(data_dir / _dataset_name(scenario_name, seed, float(speed), length_m)) for seed in seeds for speed in speeds_mps
    }
    sim_keys = {where: f"simulate_{Path(folder).name}" for where, folder in datasets.items()}
    sims = [GridJob(sim_keys[(seed, speed)], simulate_job, (scenario_name, seed, speed, length_m, folder)) for (seed, speed), folder in datasets.items()]
    simulated = run_grid(sims, results_dir, scheduler, n_workers, desc="simulate")
    jobs, where = [], {}
    for (seed, speed), folder in datasets.items():
        sim_key = sim_keys[(seed, speed)]
        for name in estimators:
            for n in point_budgets:
                n = None if n is None else int(n)
                cap = "default" if n is None else f"n{n}"
                key = f"run_{Path(folder).name}_{name}_{cap}" + ("" if max_frames is None else f"_f{max_frames}") + ("_realtime" if realtime else "")
                where[key] = (name, seed, speed, n)
                if isinstance(simulated[sim_key], JobFailure):
                    continue
                jobs.append(GridJob(key, run_job, (folder, name, seed, speed, n, max_frames, realtime)))
    done = run_grid(jobs, results_dir, scheduler, n_workers, desc="runs")
    rows = []
    nan = math.nan
    for key, (name, seed, speed, n) in where.items():
        result = done.get(key)
        if isinstance(result, dict):
            rows.append(StudyRow(**result))
        else:
            why = result.error if isinstance(result, JobFailure) else f"its dataset could not be simulated: {simulated[sim_keys[(seed, speed)]].error}"
            rows.append(StudyRow(name, seed, speed, -1 if n is None else n, nan, nan, nan, nan, nan, nan, f"failed: {why}"))
    return StudyResult(rows, scenario_name, max_frames)


__all__ = ["GRAPH_PROCESS", "EstimatorSummary", "StudyResult", "StudyRow", "estimator_study", "parse_study_estimators", "run_job", "mean_or_nan", "simulate_job", "standard_error", "write_rows_csv"]
