"""From a run's measurements and poses to its DEM, its figures against the truth, and its files.

Used by ``dem-graph run`` (the DEM of every run) and ``dem-graph dem RUN`` (made again from a run
folder, globally or as the local map at a time).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dem_graph.datasets.base import GroundTruth
from dem_graph.dem.build import DemConfig, ground_returns, load_run_points, load_run_poses
from dem_graph.dem.export import write_dem_outputs, write_local_error_csv
from dem_graph.dem.layers import Dem
from dem_graph.dem.returns import GroundReturns, PoseTrack
from dem_graph.dem.views import global_dem, local_dem, speed_at, to_local
from dem_graph.errors import DemGraphError
from dem_graph.evaluation.dem_metrics import LocalErrorSeries, corridor_coverage, height_errors, local_error_series, truth_at_cells
from dem_graph.frontend.focus import FocusArea, FocusConfig

log = logging.getLogger(__name__)


@dataclass
class RunDem:
    dem: Dem
    returns: GroundReturns
    poses: PoseTrack
    metrics: dict = field(default_factory=dict)  # plain numbers, for metrics.json
    local_series: LocalErrorSeries | None = None  # the Fig. 8 measure frame by frame, for figures

    def write(self, out_dir: str | Path) -> dict[str, Path]:
        """The DEM's files (and, with the Fig. 8 series, ``local_dem_error.csv``); a local map's cloud
        and path are in its local frame."""
        p = self.poses.T_world_body[:, :3, 3]
        returns = self.returns
        if self.dem.frame == "local":
            T = self.dem.meta["T_world_local"]
            p = (p[self.poses.t_s <= self.dem.meta["t_s"]] - T[:3, 3]) @ T[:3, :3]
            returns = to_local(returns, T)
        paths = write_dem_outputs(out_dir, self.dem, returns, p[:, :2])
        if self.local_series is not None:
            paths["local_dem_error"] = write_local_error_csv(Path(out_dir) / "local_dem_error.csv", self.local_series)
        return paths


def evaluate_dem(dem: Dem, truth: GroundTruth, corridor_half_width_m: float) -> dict:
    """Height errors (all covered cells, and the cells a laser return reached) and corridor coverage."""
    out: dict = {}
    if truth.elevation is None:
        return out
    z_truth = truth_at_cells(dem, truth.elevation)
    out["height_error"] = height_errors(dem.elevation, z_truth).as_dict()
    out["height_error_laser_cells"] = height_errors(dem.elevation, z_truth, dem.layers["laser_count"] > 0).as_dict()
    out["corridor"] = corridor_coverage(dem, truth.trajectory, corridor_half_width_m)
    return out


def make_run_dem(
    returns: GroundReturns,
    poses: PoseTrack,
    ground_truth: GroundTruth | None = None,
    config: DemConfig | None = None,
    corridor_half_width_m: float = 1.5,
    local_errors: bool = True,
) -> RunDem:
    """The whole run's DEM with its metrics: rebuild time, coverage, errors and (with truth) the Fig. 8 measure."""
    config = config or DemConfig()
    if len(returns) == 0:
        raise DemGraphError("no ground measurement (no laser return and no map point): nothing to make a DEM from")
    start = time.perf_counter()
    dem = global_dem(returns, config.fusion, traversability_window=config.traversability_window)
    rebuild_s = time.perf_counter() - start
    m: dict = {
        "resolution_m": config.fusion.resolution_m,
        "grid_shape": list(dem.geometry.shape),
        "measurements": len(returns),
        "laser_returns": int(np.sum(returns.source == 0)),
        "fused": dem.n_used,
        "covered_cells": int(dem.covered.sum()),
        "rebuild_s": rebuild_s,
    }
    series = None
    if ground_truth is not None:
        m.update(evaluate_dem(dem, ground_truth, corridor_half_width_m))
        if local_errors and ground_truth.elevation is not None:
            series = local_error_series(
                returns, poses, ground_truth.elevation, poses.t_s[:: config.local_every_n_frames],
                (config.local_start_m, config.local_start_m + config.local_length_m), config.local_width_m / 2.0,
                config.fusion, config.local_history_s, truth_trajectory=ground_truth.trajectory,
            )
            m["local_window"] = {
                "x_range_m": [config.local_start_m, config.local_start_m + config.local_length_m],
                "width_m": config.local_width_m,
                **series.summary(),
            }
    return RunDem(dem, returns, poses, m, series)


def _require_time(poses: PoseTrack, t_s: float) -> None:
    if not poses.covers(np.array([t_s]))[0]:
        raise DemGraphError(f"time {t_s:.3f} s is outside the run's poses [{poses.t_s[0]:.3f}, {poses.t_s[-1]:.3f}] s")


def make_local_dem(returns: GroundReturns, poses: PoseTrack, t_s: float, x_range_m: tuple[float, float], half_width_m: float, config: DemConfig | None = None) -> RunDem:
    """The local map at ``t_s`` (what was measured until then), as the guidance asks for it."""
    config = config or DemConfig()
    _require_time(poses, t_s)
    dem = local_dem(returns, poses, t_s, x_range_m, half_width_m, config.fusion, history_s=config.local_history_s, traversability_window=config.traversability_window)
    return RunDem(dem, returns.until(t_s), poses, {"t_s": t_s, "covered_cells": int(dem.covered.sum()), "frame": "local"})


def run_folder_dem(
    run_dir: str | Path, sequence, at_s: float | None = None, config: DemConfig | None = None, focus: FocusConfig | None = None, local_errors: bool = False
) -> RunDem:
    """The DEM of a run folder made again from its saved poses and map points and the dataset's scans:
    the global map, or with ``at_s`` the local map at that time over the focus area the guidance
    needs at the vehicle's speed then. ``local_errors``: the global map's metrics also get the
    Fig. 8 measure, as a run's do (it needs the truth's elevation)."""
    config = config or DemConfig()
    focus = focus or FocusConfig()
    poses = load_run_poses(run_dir)
    points = load_run_points(run_dir) if config.map_points else None
    returns = ground_returns(sequence, poses, points)
    if at_s is None:
        return make_run_dem(returns, poses, sequence.ground_truth, config, corridor_half_width_m=focus.corridor_width_m / 2.0, local_errors=local_errors)
    _require_time(poses, at_s)
    area = FocusArea.for_speed(focus, sequence.rig, speed_at(poses, at_s))
    return make_local_dem(returns, poses, at_s, (area.x_near_m, area.x_far_m), area.half_width_m, config)


__all__ = ["RunDem", "evaluate_dem", "make_local_dem", "make_run_dem", "run_folder_dem"]
