"""A run's DEM: the dataset's laser scans placed with the run's poses, plus its map points, fused,
with its figures against the truth.

Used by every run (the DEM of its final poses) and by ``dem-graph dem RUN`` (made again from a run
folder, globally or as the local map at a time: :mod:`dem_graph.pipeline.run_folder`).

The poses are the run's best: the end-of-run smoothed trajectory for ``isam2``, the smoothed log
for ``isam2-batch``, the per-frame estimates for the EKF baselines. Their covariances are the
per-frame ones the estimator reported.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import numpy as np

from dem_graph.datasets.base import GroundTruth, Sequence
from dem_graph.dem.layers import Dem
from dem_graph.dem.returns import GroundReturns, PoseTrack, ReturnSource, laser_returns_world, map_point_returns
from dem_graph.dem.views import global_dem, local_dem, speed_at
from dem_graph.errors import DemGraphError
from dem_graph.estimators.base import SMOOTHED_TRAJECTORY, EstimatorResult
from dem_graph.evaluation.dem_metrics import (
    CorridorCoverage,
    HeightErrors,
    LocalErrorConfig,
    LocalErrorSeries,
    LocalErrorSummary,
    corridor_coverage,
    height_errors,
    local_error_series,
    truth_at_cells,
)
from dem_graph.evaluation.results import MetricsModel
from dem_graph.frontend.focus import FocusArea, FocusConfig
from dem_graph.pipeline.config import DemConfig

log = logging.getLogger(__name__)

def pose_track_from_result(result: EstimatorResult) -> PoseTrack:
    """The run's best poses (see the module) with the per-frame covariances."""
    t = np.array([f.t_s for f in result.frames])
    poses = result.extra_poses.get(SMOOTHED_TRAJECTORY)
    if poses is None:
        poses = np.array([f.T_world_body for f in result.frames])
    return PoseTrack(t, np.asarray(poses, dtype=float), result.pose_covariances())


def ground_returns(sequence: Sequence, poses: PoseTrack, points: GroundReturns | None = None) -> GroundReturns:
    """Every laser return of ``sequence`` placed with ``poses``, and ``points`` (map points) if given, in time order."""
    scan_t_s, ranges_m = sequence.laser_scans()
    laser = laser_returns_world(scan_t_s, ranges_m, sequence.rig, poses)
    return GroundReturns.concatenate([laser, points if points is not None else GroundReturns.empty()])


def result_points(result: EstimatorResult) -> GroundReturns:
    a = result.points.arrays()
    return map_point_returns(a["xyz"], a["covariance"], a["created_t_s"])


def dem_from_result(result: EstimatorResult, sequence: Sequence, config: DemConfig | None = None) -> tuple[GroundReturns, PoseTrack]:
    """The ground measurements and poses a run's DEM is fused from."""
    config = config or DemConfig()
    poses = pose_track_from_result(result)
    points = result_points(result) if config.map_points else None
    return ground_returns(sequence, poses, points), poses


class DemMetrics(MetricsModel):
    """A run's DEM in numbers (``metrics.json``'s ``dem``); against the truth, where the dataset has it,
    its height errors, the corridor's coverage and the Fig. 8 measure."""

    resolution_m: float
    grid_shape: list[int]  # rows, columns
    measurements: int  # laser returns and map points given to the fusion
    laser_returns: int
    fused: int  # measurements fused into a cell (inside the grid, finite, through the gate)
    covered_cells: int
    rebuild_s: float  # the fusion's time
    height_error: HeightErrors | None = None  # over every covered cell
    height_error_laser_cells: HeightErrors | None = None  # over the cells a laser return reached
    corridor: CorridorCoverage | None = None
    local_window: LocalErrorSummary | None = None  # Fig. 8


class DemFailure(MetricsModel):
    """Why a run has no DEM."""

    error: str


class LocalDemMetrics(MetricsModel):
    """A local map at a time (``dem-graph dem RUN --at-s T``)."""

    t_s: float
    covered_cells: int
    frame: str = "local"


@dataclass
class RunDem:
    dem: Dem
    returns: GroundReturns
    poses: PoseTrack
    metrics: DemMetrics | LocalDemMetrics
    local_series: LocalErrorSeries | None = None  # the Fig. 8 measure frame by frame, for figures


def evaluate_dem(dem: Dem, truth: GroundTruth, corridor_half_width_m: float) -> dict[str, MetricsModel]:
    """Height errors (all covered cells, and the cells a laser return reached) and corridor coverage,
    by :class:`DemMetrics` field (none without the truth's elevation)."""
    if truth.elevation is None:
        return {}
    z_truth = truth_at_cells(dem, truth.elevation)
    return {
        "height_error": height_errors(dem.elevation, z_truth),
        "height_error_laser_cells": height_errors(dem.elevation, z_truth, dem.layers["laser_count"] > 0),
        "corridor": corridor_coverage(dem, truth.trajectory, corridor_half_width_m),
    }


def make_run_dem(
    returns: GroundReturns,
    poses: PoseTrack,
    ground_truth: GroundTruth | None = None,
    config: DemConfig | None = None,
    corridor_half_width_m: float = 1.5,
    local_errors: bool = True,
    local_error: LocalErrorConfig | None = None,
) -> RunDem:
    """The whole run's DEM with its metrics: rebuild time, coverage, errors and (with truth and
    ``local_errors``) the Fig. 8 measure over the window ``local_error``."""
    config = config or DemConfig()
    window = local_error or LocalErrorConfig()
    if len(returns) == 0:
        raise DemGraphError("no ground measurement (no laser return and no map point): nothing to make a DEM from")
    start = time.perf_counter()
    dem = global_dem(returns, config.fusion, traversability_window=config.traversability_window)
    rebuild_s = time.perf_counter() - start
    m = DemMetrics(
        resolution_m=config.fusion.resolution_m,
        grid_shape=list(dem.geometry.shape),
        measurements=len(returns),
        laser_returns=int(np.sum(returns.source == ReturnSource.LASER_RETURN)),
        fused=dem.n_used,
        covered_cells=int(dem.covered.sum()),
        rebuild_s=rebuild_s,
        **(evaluate_dem(dem, ground_truth, corridor_half_width_m) if ground_truth is not None else {}),
    )
    series = None
    if ground_truth is not None:
        if local_errors and ground_truth.elevation is not None:
            series = local_error_series(
                returns, poses, ground_truth.elevation, poses.t_s[:: window.every_n_frames], window.x_range_m, window.width_m / 2.0,
                config.fusion, config.local_history_s, truth_trajectory=ground_truth.trajectory,
            )
            m.local_window = series.summary(window)
    return RunDem(dem, returns, poses, m, series)


def require_time(poses: PoseTrack, t_s: float) -> None:
    if not poses.covers(np.array([t_s]))[0]:
        raise DemGraphError(f"time {t_s:.3f} s is outside the run's poses [{poses.t_s[0]:.3f}, {poses.t_s[-1]:.3f}] s")


def make_local_dem(returns: GroundReturns, poses: PoseTrack, t_s: float, x_range_m: tuple[float, float], half_width_m: float, config: DemConfig | None = None) -> RunDem:
    """The local map at ``t_s`` (what was measured until then), as the guidance asks for it."""
    config = config or DemConfig()
    require_time(poses, t_s)
    dem = local_dem(returns, poses, t_s, x_range_m, half_width_m, config.fusion, history_s=config.local_history_s, traversability_window=config.traversability_window)
    return RunDem(dem, returns.until(t_s), poses, LocalDemMetrics(t_s=t_s, covered_cells=int(dem.covered.sum())))


def focus_local_dem(returns: GroundReturns, poses: PoseTrack, t_s: float, rig, focus: FocusConfig | None = None, config: DemConfig | None = None) -> RunDem:
    """The local map at ``t_s`` over the focus area the guidance needs at the vehicle's speed then."""
    require_time(poses, t_s)
    area = FocusArea.for_speed(focus or FocusConfig(), rig, speed_at(poses, t_s))
    return make_local_dem(returns, poses, t_s, (area.x_near_m, area.x_far_m), area.half_width_m, config)


__all__ = [
    "DemFailure",
    "DemMetrics",
    "LocalDemMetrics",
    "RunDem",
    "dem_from_result",
    "evaluate_dem",
    "focus_local_dem",
    "ground_returns",
    "make_local_dem",
    "make_run_dem",
    "pose_track_from_result",
    "require_time",
    "result_points",
]
