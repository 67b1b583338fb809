"""A DEM against the ground-truth terrain: height errors, coverage of the driven corridor, and the
paper's Fig. 8 measure (the local DEM's height error ahead of the vehicle, frame by frame).

Truth heights are the ground-truth elevation grid interpolated at each DEM cell's centre.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydantic import Field
from scipy.spatial import cKDTree

from dem_graph.config_types import StrictModel
from dem_graph.dem.fusion import FusionConfig
from dem_graph.dem.layers import Dem
from dem_graph.dem.returns import GroundReturns, PoseTrack
from dem_graph.dem.views import local_dem, local_frame, local_to_world_xy
from dem_graph.evaluation.results import MetricsModel, Number
from dem_graph.geometry.grid import ElevationGrid
from dem_graph.geometry.trajectory import Trajectory
from dem_graph.progress import progress


class HeightErrors(MetricsModel):
    """Statistics of a DEM's height error over the cells where it and the truth are known (NaN over none)."""

    cells: int
    rmse_m: Number
    mean_m: Number
    std_m: Number
    p95_abs_m: Number  # 95th percentile of the absolute error
    max_abs_m: Number


def _truth_at(truth: ElevationGrid, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    return np.asarray(truth.height_at(x, y), dtype=float)


def height_errors(elevation: np.ndarray, truth: np.ndarray, mask: np.ndarray | None = None) -> HeightErrors:
    """Statistics of ``elevation - truth`` over the cells where both are known (and ``mask``)."""
    e = np.asarray(elevation, dtype=float) - np.asarray(truth, dtype=float)
    ok = np.isfinite(e) if mask is None else np.isfinite(e) & mask
    e = e[ok]
    if e.size == 0:
        nan = float("nan")
        return HeightErrors(cells=0, rmse_m=nan, mean_m=nan, std_m=nan, p95_abs_m=nan, max_abs_m=nan)
    a = np.abs(e)
    return HeightErrors(
        cells=int(e.size), rmse_m=float(np.sqrt(np.mean(e * e))), mean_m=float(e.mean()), std_m=float(e.std()), p95_abs_m=float(np.percentile(a, 95)), max_abs_m=float(a.max())
    )


def truth_at_cells(dem: Dem, truth: ElevationGrid) -> np.ndarray:
    """The truth's height at each cell centre of a world-frame DEM (NaN outside the truth)."""
    x, y = dem.geometry.cell_centers_xy()
    with np.errstate(invalid="ignore"):
        return _truth_at(truth, x.ravel(), y.ravel()).reshape(x.shape)


def corridor_mask(dem: Dem, trajectory: Trajectory, half_width_m: float) -> np.ndarray:
    """Cells whose centre lies within ``half_width_m`` of the driven path (its positions, densified to the cell size)."""
    p = trajectory.positions_xyz[:, :2]
    step = np.linalg.norm(np.diff(p, axis=0), axis=1)
    s = np.r_[0.0, np.cumsum(step)]
    if s[-1] > 0:
        s_fine = np.arange(0.0, s[-1] + 1e-9, dem.geometry.resolution_m / 2.0)
        p = np.stack([np.interp(s_fine, s, p[:, k]) for k in range(2)], axis=1)
    x, y = dem.geometry.cell_centers_xy()
    d, _ = cKDTree(p).query(np.stack([x.ravel(), y.ravel()], axis=1), distance_upper_bound=half_width_m + 1e-9)
    return (d <= half_width_m).reshape(x.shape)


class CorridorCoverage(MetricsModel):
    """How much of the driven corridor (the cells within ``half_width_m`` of the path) has a fused height."""

    corridor_cells: int
    covered_cells: int
    coverage: Number  # covered_cells / corridor_cells
    half_width_m: float


def corridor_coverage(dem: Dem, trajectory: Trajectory, half_width_m: float) -> CorridorCoverage:
    """How much of the driven corridor has a fused height (the corridor: within ``half_width_m`` of the path)."""
    corridor = corridor_mask(dem, trajectory, half_width_m)
    n = int(corridor.sum())
    covered = int((corridor & dem.covered).sum())
    return CorridorCoverage(corridor_cells=n, covered_cells=covered, coverage=covered / n if n else float("nan"), half_width_m=half_width_m)


class LocalErrorConfig(StrictModel):
    """The window of the Fig. 8 measure: a local DEM every few frames, compared with the truth over
    a rectangle ahead of the vehicle."""

    start_m: float = Field(1.0, ge=0, description="the window starts this far ahead of the body origin, metres")
    length_m: float = Field(5.0, gt=0, description="length of the window ahead of the vehicle, metres")
    width_m: float = Field(5.0, gt=0, description="width of the window, metres")
    every_n_frames: int = Field(5, ge=1, description="one local DEM every this many frames")

    @property
    def x_range_m(self) -> tuple[float, float]:
        return (self.start_m, self.start_m + self.length_m)


@dataclass(frozen=True)
class LocalErrorSeries:
    """Per-frame height error of the local DEM in a window ahead (the paper's Fig. 8).

    Two comparisons of the same local DEM:

    - ``mean_m``, ``std_m`` (the paper's): against the terrain where the estimate puts the cells
      in the world, so the trajectory's drift is part of the error;
    - ``relative_mean_m``, ``relative_std_m``: against the terrain in the true local frame (the
      ground-truth pose at that time), relative to the true body height: the error of the map the
      guidance steers by, whatever the drift.
    """

    t_s: np.ndarray
    mean_m: np.ndarray
    std_m: np.ndarray
    relative_mean_m: np.ndarray
    relative_std_m: np.ndarray
    covered_fraction: np.ndarray

    def summary(self, config: LocalErrorConfig) -> LocalErrorSummary:
        """The series in a few numbers (means over the frames with data), with the window ``config`` it was measured over."""
        window = {"x_range_m": list(config.x_range_m), "width_m": config.width_m, "frames": int(len(self.t_s))}
        ok = np.isfinite(self.mean_m)
        if not np.any(ok):
            return LocalErrorSummary(**window, frames_with_data=0)
        out = LocalErrorSummary(
            **window,
            frames_with_data=int(ok.sum()),
            mean_of_mean_m=float(np.mean(self.mean_m[ok])),
            mean_abs_mean_m=float(np.mean(np.abs(self.mean_m[ok]))),
            mean_of_std_m=float(np.mean(self.std_m[ok])),
            covered_fraction_median=float(np.median(self.covered_fraction)),
        )
        rel = np.isfinite(self.relative_mean_m)
        if np.any(rel):
            out.relative_mean_abs_mean_m = float(np.mean(np.abs(self.relative_mean_m[rel])))
            out.relative_mean_of_std_m = float(np.mean(self.relative_std_m[rel]))
        return out


class LocalErrorSummary(MetricsModel):
    """The Fig. 8 measure over a run (``metrics.json``'s ``dem.local_window``): the window, then the
    means over the frames whose local DEM had data (none without such frames; the relative ones
    only where the truth's pose is known)."""

    x_range_m: list[float]  # the window ahead of the body origin, metres
    width_m: float
    frames: int  # local DEMs made
    frames_with_data: int
    mean_of_mean_m: Number | None = None  # the paper's Fig. 8: the mean error, averaged over the frames
    mean_abs_mean_m: Number | None = None
    mean_of_std_m: Number | None = None
    covered_fraction_median: Number | None = None
    relative_mean_abs_mean_m: Number | None = None  # against the truth in the true local frame
    relative_mean_of_std_m: Number | None = None


def _truth_in_local(truth: ElevationGrid, T_world_local: np.ndarray, x_local: np.ndarray, y_local: np.ndarray) -> np.ndarray:
    """Truth heights at local cell centres, relative to the local frame's origin height."""
    xw, yw = local_to_world_xy(T_world_local, x_local, y_local)
    with np.errstate(invalid="ignore"):
        return _truth_at(truth, xw.ravel(), yw.ravel()).reshape(x_local.shape) - T_world_local[2, 3]


def local_dem_errors(dem: Dem, truth: ElevationGrid, truth_trajectory: Trajectory | None = None) -> tuple[float, float, float, float, float]:
    """One local DEM (``dem.meta``: ``t_s``, ``T_world_local``) against the truth: mean and std of
    its height error with the cells where the estimate puts them, the same in the true local frame
    (NaN without the truth's pose then), and its covered fraction (see :class:`LocalErrorSeries`)."""
    t = float(dem.meta["t_s"])
    xl, yl = dem.geometry.cell_centers_xy()
    err = height_errors(dem.elevation, _truth_in_local(truth, dem.meta["T_world_local"], xl, yl))
    rel_mean = rel_std = float("nan")
    if truth_trajectory is not None and truth_trajectory.t_s[0] <= t <= truth_trajectory.t_s[-1]:
        rel = height_errors(dem.elevation, _truth_in_local(truth, local_frame(truth_trajectory.at(t)), xl, yl))
        rel_mean, rel_std = rel.mean_m, rel.std_m
    return (err.mean_m, err.std_m, rel_mean, rel_std, float(dem.covered.mean()))


def local_error_series_from_rows(times_s, rows) -> LocalErrorSeries:
    """A series from :func:`local_dem_errors`' rows, one per time."""
    a = np.array(rows, dtype=float).reshape(-1, 5)
    return LocalErrorSeries(np.asarray(times_s, dtype=float), a[:, 0], a[:, 1], a[:, 2], a[:, 3], a[:, 4])


def local_error_series(
    returns: GroundReturns,
    poses: PoseTrack,
    truth: ElevationGrid,
    times_s: np.ndarray,
    x_range_m: tuple[float, float] = (1.0, 6.0),
    half_width_m: float = 2.5,
    config: FusionConfig | None = None,
    history_s: float = 10.0,
    truth_trajectory: Trajectory | None = None,
) -> LocalErrorSeries:
    """At each time, the local DEM over the window against the truth, made in hindsight from ``returns``
    (see :class:`LocalErrorSeries`)."""
    times_s = np.asarray(times_s, dtype=float)
    rows = []
    for t in progress(times_s, desc="local DEM errors", unit="frame"):
        dem = local_dem(returns, poses, float(t), x_range_m, half_width_m, config, history_s=history_s, traversability_window=None)
        rows.append(local_dem_errors(dem, truth, truth_trajectory))
    return local_error_series_from_rows(times_s, rows)


__all__ = ["CorridorCoverage", "HeightErrors", "LocalErrorConfig", "LocalErrorSeries", "LocalErrorSummary", "corridor_coverage", "corridor_mask", "height_errors", "local_dem_errors", "local_error_series", "local_error_series_from_rows", "truth_at_cells"]
