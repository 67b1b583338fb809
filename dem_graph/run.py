"""Running an estimator over a dataset: the loop, timing, metrics and the run folder.

``run_estimator`` owns the loop over a :class:`Sequence` (the estimators only see events). If the
loop fails part way (a corrupt image late in a log, say), what was estimated so far is still
returned, with the error, so :func:`write_run` can save it.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal, get_args

import numpy as np
import yaml
from pydantic import Field, ValidationError
from threadpoolctl import threadpool_limits

from dem_graph.config_types import format_validation_error
from dem_graph.datasets.base import Sequence
from dem_graph.datasets.events import CameraFrame, LaserScan, Odometry
from dem_graph.dem.build import POSES_NPZ, DemConfig, dem_from_result, pose_track_from_result, save_run_poses
from dem_graph.dem.pipeline import RunDem, make_run_dem
from dem_graph.errors import ConfigError, DemGraphError
from dem_graph.estimators.base import Estimator, EstimatorResult
from dem_graph.estimators.ekf import EkfConfig, EkfOptions, EkfSlam
from dem_graph.estimators.isam2 import Isam2Config, Isam2Options, Isam2Slam
from dem_graph.estimators.settings import SharedSettings
from dem_graph.evaluation.run_output import frame_timing_summary, write_run_outputs
from dem_graph.evaluation.trajectory_metrics import accuracy_summary, nees_bounds, pose_nees
from dem_graph.progress import progress

log = logging.getLogger(__name__)

EstimatorName = Literal["gm", "ptpm", "isam2", "isam2-batch"]
ESTIMATORS = get_args(EstimatorName)


class RunConfig(SharedSettings):
    """A run: which estimator, the settings all estimators share (front end, motion model, false
    matches), and each estimator's own options."""

    estimator: EstimatorName = Field("ptpm", description="which estimator")
    ekf: EkfOptions = Field(default_factory=EkfOptions, description="EKF baselines (gm, ptpm)")
    isam2: Isam2Options = Field(default_factory=Isam2Options, description="the graph estimator (isam2, isam2-batch)")
    max_frames: int | None = Field(None, ge=1, description="stop after this many camera frames")
    realtime: bool = Field(
        False,
        description="give each event to the estimator when its time since the first event has passed on the wall clock, as the sensors would on the "
        "vehicle; false: as fast as the estimator takes them. Matters with isam2.graph_process, whose graph then keeps up as it would live",
    )
    blas_threads: int = Field(
        1,
        ge=1,
        description="threads numpy's linear algebra may use while the estimator runs. The matrices are small, and more threads contend with the graph's "
        "process and the rest of the machine: on 2 busy cores, 1 thread took GM's p95 time per frame at 150 points from 337-373 to 127-131 ms",
    )
    dem: DemConfig = Field(default_factory=DemConfig, description="the dense DEM made from the run's poses (grid, fusion, Fig. 8 window)")


def make_estimator(sequence: Sequence, config: RunConfig) -> Estimator:
    shared = {k: getattr(config, k) for k in SharedSettings.model_fields}
    args = (sequence.rig, sequence.T_world_body_initial, sequence.t_start_s, sequence.has_odometry)
    if config.estimator in ("gm", "ptpm"):
        return EkfSlam(*args, EkfConfig(**shared, **dict(config.ekf), variant=config.estimator))
    if config.estimator in ("isam2", "isam2-batch"):
        return Isam2Slam(*args, Isam2Config(**shared, **dict(config.isam2), batch=config.estimator == "isam2-batch"))
    raise DemGraphError(f"unknown estimator '{config.estimator}'; choose one of {', '.join(ESTIMATORS)}")


@dataclass
class RunResult:
    estimator: EstimatorResult
    config: RunConfig
    metrics: dict = field(default_factory=dict)
    error: str | None = None  # set when the loop stopped early; the result holds what was done
    elapsed_s: float = 0.0
    dem: RunDem | None = None  # the dense DEM from the run's poses (None if it could not be made)


def feed(estimator: Estimator, sequence: Sequence, max_frames: int | None = None, finish: bool = True, realtime: bool = False) -> Iterator[int]:
    """Give the sequence's events to ``estimator`` in time order (with a progress bar), up to
    ``max_frames`` camera frames, then call its ``finish`` (unless ``finish`` is false). Yields the
    number of camera frames given so far after each one. With ``realtime`` an event is given no
    sooner than its time after the first event's has passed on the wall clock (an estimator that
    falls behind gets the next one at once, as from a sensor's buffer)."""
    frames = 0
    t0_s = wall0_s = None
    for event in progress(sequence.events(), total=sequence.event_count(), desc=estimator.name, unit="event"):
        if realtime:
            if t0_s is None:
                t0_s, wall0_s = event.t_s, time.perf_counter()
            wait_s = (event.t_s - t0_s) - (time.perf_counter() - wall0_s)
            if wait_s > 0:
                time.sleep(wait_s)
        if isinstance(event, CameraFrame):
            estimator.on_frame(event)
            frames += 1
            yield frames
            if max_frames and frames >= max_frames:
                break
        elif isinstance(event, LaserScan):
            estimator.on_scan(event)
        elif isinstance(event, Odometry):
            estimator.on_odometry(event)
    if finish:
        estimator.finish()


def with_dataset_speed(sequence: Sequence, config: RunConfig) -> RunConfig:
    """``config``, its starting speed replaced by the dataset's own estimate (``initial_speed_mps``)
    when ``motion.initial_speed_from_dataset`` asks for it and the dataset has one."""
    if not config.motion.initial_speed_from_dataset or config.motion.uses_odometry(sequence.has_odometry):
        return config
    speed = sequence.initial_speed_mps
    if speed is None:
        log.warning("the dataset gives no starting speed: starting at %.2f m/s (motion.initial_speed_mps)", config.motion.initial_speed_mps)
        return config
    config = config.model_copy(deep=True)
    config.motion.initial_speed_mps = float(speed)
    return config


def run_estimator(sequence: Sequence, config: RunConfig | None = None, with_dem: bool = True) -> RunResult:
    config = with_dataset_speed(sequence, config or RunConfig())
    estimator = make_estimator(sequence, config)
    start = time.perf_counter()
    error = None
    frames = 0
    try:
        with threadpool_limits(limits=config.blas_threads, user_api="blas"):
            for frames in feed(estimator, sequence, config.max_frames, realtime=config.realtime):  # noqa: B007 - read in the handler below
                pass
    except DemGraphError as exc:
        error = str(exc)
        log.error("run stopped after %d frames: %s", frames, exc)
    result = estimator.result()
    run = RunResult(result, config, error=error, elapsed_s=time.perf_counter() - start)
    run.metrics = compute_metrics(sequence, run)
    if with_dem and result.frames:
        run.dem = run_dem(run, sequence)
    return run


def run_dem(run: RunResult, sequence: Sequence) -> RunDem | None:
    """The run's DEM and its metrics (into ``run.metrics["dem"]``); a failure is logged, the run kept."""
    try:
        returns, poses = dem_from_result(run.estimator, sequence, run.config.dem)
        half_width = run.config.frontend.focus.corridor_width_m / 2.0
        dem = make_run_dem(returns, poses, sequence.ground_truth, run.config.dem, corridor_half_width_m=half_width)
    except DemGraphError as exc:
        log.warning("no DEM for this run: %s", exc)
        run.metrics["dem"] = {"error": str(exc)}
        return None
    run.metrics["dem"] = dem.metrics
    return dem


def compute_metrics(sequence: Sequence, run: RunResult) -> dict:
    res = run.estimator
    metrics: dict = {"estimator": res.name, "frames": len(res.frames), "elapsed_s": run.elapsed_s}
    if run.error:
        metrics["error"] = run.error
    if not res.frames:
        return metrics
    phases = sorted({k for f in res.frames for k in f.timing_s})
    metrics["time_per_frame"] = frame_timing_summary({k: [f.timing_s.get(k, 0.0) for f in res.frames] for k in phases})
    live = np.array([f.n_live for f in res.frames])
    tracked = np.array([f.n_tracked for f in res.frames])
    metrics["points_per_frame"] = {"live_median": float(np.median(live)), "live_max": int(live.max()), "tracked_median": float(np.median(tracked))}
    metrics["map_points"] = len(res.points)
    metrics["events"] = dict(sorted(res.counters.items()))
    gt = sequence.ground_truth
    if gt is not None and len(res.frames) > 1:
        est = res.trajectory()
        metrics["trajectory"] = accuracy_summary(est, gt.trajectory)
        for name, extra in res.extra_trajectories().items():
            metrics[name] = accuracy_summary(extra, gt.trajectory)
        nees = pose_nees(est.poses_se3, gt.trajectory.at(est.t_s), res.pose_covariances())
        lo, hi = nees_bounds(6, 0.95)
        later = nees[1:]
        metrics["pose_nees"] = {"median": float(np.median(later)), "fraction_within_95": float(np.mean((later >= lo) & (later <= hi))), "fraction_below_upper_95": float(np.mean(later <= hi))}
    return metrics


def merge_settings(base: dict, over: dict) -> dict:
    """``base`` with ``over``'s values in its place, key by key down nested mappings."""
    out = dict(base)
    for key, value in over.items():
        out[key] = merge_settings(out[key], value) if isinstance(value, dict) and isinstance(out.get(key), dict) else value
    return out


def load_run_config(
    path: str | Path | None = None,
    estimator: str | None = None,
    max_points: int | None = None,
    no_odometry: bool = False,
    max_frames: int | None = None,
    lag_s: float | None = None,
    keyframe_every: int | None = None,
    graph_process: bool = False,
    dataset_settings: dict | None = None,
    realtime: bool = False,
) -> RunConfig:
    """The run configuration: defaults, then the dataset's own settings (:meth:`Sequence.run_settings`),
    then the YAML file at ``path``, then the given overrides."""
    data: dict = {}
    if path is not None:
        path = Path(path)
        if not path.is_file():
            raise ConfigError("configuration file not found", path)
        try:
            data = yaml.safe_load(path.read_text()) or {}
        except (yaml.YAMLError, OSError, UnicodeDecodeError) as exc:
            raise ConfigError(f"cannot read the configuration ({str(exc).splitlines()[0]})", path) from None
        if not isinstance(data, dict):
            raise ConfigError("a run configuration must be a mapping", path)
    if dataset_settings:
        data = merge_settings(dataset_settings, data)
    try:
        config = RunConfig.model_validate(data)
        if estimator is not None:
            config.estimator = estimator
        if max_frames is not None:
            config.max_frames = max_frames
        if max_points is not None:
            config.frontend.max_points = max_points
        if no_odometry:
            config.motion.model = "constant_velocity"
        if lag_s is not None:
            config.isam2.lag_s = lag_s
        if keyframe_every is not None:  # the batch's online pass has its own spacing
            if config.estimator == "isam2-batch":
                config.isam2.batch_keyframe_every = keyframe_every
            else:
                config.isam2.keyframe_every = keyframe_every
        if graph_process:
            config.isam2.graph_process = True
        if realtime:
            config.realtime = True
    except ValidationError as exc:
        raise ConfigError(f"invalid run configuration: {format_validation_error(exc)}", path) from None
    return config


def run_folder_config(run_dir: str | Path) -> RunConfig:
    """The configuration a run folder was made with (its ``config.yaml``), the defaults if it has none."""
    path = Path(run_dir) / "config.yaml"
    return load_run_config(path) if path.is_file() else RunConfig()


def summary_lines(run: RunResult) -> list[str]:
    m = run.metrics
    lines = [f"{m.get('estimator')}: {m.get('frames', 0)} frames in {m.get('elapsed_s', 0.0):.1f} s"]
    if "time_per_frame" in m:
        t = m["time_per_frame"]["total"]
        p = m["points_per_frame"]
        lines.append(f"time per frame: median {t['median_ms']:.1f} ms, p95 {t['p95_ms']:.1f} ms; live points median {p['live_median']:.0f}, tracked {p['tracked_median']:.0f}")
    if "trajectory" in m:
        tr = m["trajectory"]
        lines.append(f"ATE RMSE {tr['ate_rmse_m']:.3f} m ({tr['ate_aligned_rmse_m']:.3f} m aligned), final error {tr['final_error_m']:.3f} m over {tr['distance_m']:.1f} m: drift {tr['drift_percent']:.2f} %")
        rpe = tr["rpe"]
        if rpe["pairs"]:
            lines.append(f"RPE over {rpe['delta_m']:g} m: {rpe['translation_rmse_m']:.3f} m, {rpe['rotation_rmse_deg']:.2f} deg (RMSE of {rpe['pairs']} pairs)")
        else:
            lines.append(f"RPE over {rpe['delta_m']:g} m: none ({rpe['reason']})")
    d = m.get("dem")
    if d and "error" not in d:
        line = f"DEM: {d['covered_cells']} cells of {d['resolution_m']:g} m from {d['measurements']} measurements, rebuilt in {d['rebuild_s']:.2f} s"
        if "height_error_laser_cells" in d:
            e, c = d["height_error_laser_cells"], d["corridor"]
            line += f"; height RMSE {100 * e['rmse_m']:.1f} cm over the laser-swept cells, corridor {100 * c['coverage']:.0f} % covered"
        lines.append(line)
        if "local_window" in d and d["local_window"].get("frames_with_data"):
            lw = d["local_window"]
            line = f"local DEM, {lw['width_m']:g} m window ahead (Fig. 8): mean error {100 * lw['mean_of_mean_m']:.1f} cm, std {100 * lw['mean_of_std_m']:.1f} cm"
            if "relative_mean_abs_mean_m" in lw:
                line += f"; relative to the vehicle: |mean| {100 * lw['relative_mean_abs_mean_m']:.1f} cm, std {100 * lw['relative_mean_of_std_m']:.1f} cm"
            lines.append(line)
    elif d:
        lines.append(f"DEM: not made ({d['error']})")
    return lines


def write_run(run: RunResult, out_dir: str | Path) -> dict[str, Path]:
    res = run.estimator
    pts = res.points.arrays()
    cov = pts["covariance"]
    attributes = {
        "point_id": pts["point_id"],
        "kind": pts["kind"],
        "var_x_m2": cov[:, 0, 0].astype(np.float32),
        "var_y_m2": cov[:, 1, 1].astype(np.float32),
        "var_z_m2": cov[:, 2, 2].astype(np.float32),
        "n_tracked": pts["n_tracked"],
        "created_t_s": pts["created_t_s"],
    }
    if not res.frames:
        raise DemGraphError("the run produced no pose: nothing to write")
    paths = write_run_outputs(out_dir, res.trajectory(), pts["xyz"], attributes, run.metrics, run.config.model_dump(mode="json"), res.extra_trajectories())
    poses = run.dem.poses if run.dem is not None else pose_track_from_result(res)
    paths["poses"] = save_run_poses(Path(out_dir) / POSES_NPZ, poses)
    if run.dem is not None:
        paths.update(run.dem.write(out_dir))
    return paths
