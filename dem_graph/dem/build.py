"""A run's DEM: the dataset's laser scans placed with the run's poses, plus its map points.

Works on a run in memory (:func:`dem_from_result`) and on a run folder (:func:`load_run_poses`,
:func:`load_run_points`), so the DEM can be made again from the current poses at any time
(``dem-graph dem RUN``).

The poses are the run's best: the end-of-run smoothed trajectory for ``isam2``, the smoothed log
for ``isam2-batch``, the per-frame estimates for the EKF baselines. Their covariances are the
per-frame ones the estimator reported.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from pydantic import Field

from dem_graph.config_types import StrictModel
from dem_graph.datasets.base import Sequence
from dem_graph.dem.fusion import FusionConfig
from dem_graph.dem.returns import GroundReturns, PoseTrack, laser_returns_world, map_point_returns
from dem_graph.errors import DatasetError, DemGraphError
from dem_graph.estimators.base import EstimatorResult
from dem_graph.io.ply import read_points_ply

POSES_NPZ = "poses.npz"
SMOOTHED = "trajectory_smoothed"


class DemConfig(StrictModel):
    fusion: FusionConfig = Field(default_factory=FusionConfig, description="per-cell fusion and the grid")
    map_points: bool = Field(True, description="fuse the estimator's map points along with every laser return")
    traversability_window: int = Field(3, ge=3, description="cells on a side of the slope / step / roughness window (odd)")
    local_length_m: float = Field(5.0, gt=0, description="Fig. 8 measure: length of the window ahead of the vehicle, metres")
    local_width_m: float = Field(5.0, gt=0, description="Fig. 8 measure: width of that window, metres")
    local_start_m: float = Field(1.0, ge=0, description="Fig. 8 measure: the window starts this far ahead of the body origin, metres")
    local_every_n_frames: int = Field(5, ge=1, description="Fig. 8 measure: one local DEM every this many frames")
    local_history_s: float = Field(10.0, gt=0, description="a local DEM fuses the measurements of this many seconds before its time")


def pose_track_from_result(result: EstimatorResult) -> PoseTrack:
    """The run's best poses (see the module) with the per-frame covariances."""
    t = np.array([f.t_s for f in result.frames])
    poses = result.extra_poses.get(SMOOTHED)
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


def save_run_poses(path: str | Path, poses: PoseTrack) -> Path:
    path = Path(path)
    try:
        with path.open("wb") as fh:
            np.savez_compressed(fh, t_s=poses.t_s, T_world_body=poses.T_world_body, covariance=poses.covariance)
    except OSError as exc:
        raise DatasetError(path, f"cannot write ({exc.strerror or exc})") from None
    return path


def load_run_poses(run_dir: str | Path) -> PoseTrack:
    path = Path(run_dir) / POSES_NPZ
    if not path.is_file():
        raise DatasetError(path, "not found: is this a run folder written by `dem-graph run`?")
    try:
        with np.load(path, allow_pickle=False) as data:
            missing = [k for k in ("t_s", "T_world_body", "covariance") if k not in data]
            if missing:
                raise DatasetError(path, f"no {', '.join(missing)} in the file")
            t, T, P = (np.asarray(data[k], dtype=float) for k in ("t_s", "T_world_body", "covariance"))
    except (OSError, ValueError, EOFError) as exc:
        raise DatasetError(path, f"not a readable .npz file ({str(exc).splitlines()[0] if str(exc) else type(exc).__name__})") from None
    try:
        return PoseTrack(t, T, P)
    except DemGraphError as exc:  # the track's own checks: shapes, NaN, times not increasing
        raise DatasetError(path, str(exc)) from None


def load_run_points(run_dir: str | Path) -> GroundReturns:
    """The map points of a run folder's ``points.ply`` (positions, height variances, creation times)."""
    path = Path(run_dir) / "points.ply"
    xyz, attributes = read_points_ply(path)
    if "var_z_m2" not in attributes:
        raise DatasetError(path, "no var_z_m2 attribute: cannot weigh the map points")
    cov = np.zeros((len(xyz), 3, 3))
    cov[:, 2, 2] = attributes["var_z_m2"]
    created = attributes.get("created_t_s", np.zeros(len(xyz)))
    return map_point_returns(xyz, cov, created)


__all__ = [
    "DemConfig",
    "POSES_NPZ",
    "dem_from_result",
    "ground_returns",
    "load_run_points",
    "load_run_poses",
    "pose_track_from_result",
    "result_points",
    "save_run_poses",
]
