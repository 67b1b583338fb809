"""The figures of an estimator comparison, after the paper's: the trajectories from above with the
ground truth (Fig. 10), the position error against time (Fig. 11), the local DEM's height error
ahead of the vehicle against time (Fig. 8), and one run's DEM with its error against the truth.

Each function draws one PNG from arrays and returns its path; times are shown from ``t0_s``.
An estimator keeps its colour in every figure.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dem_graph.dem.layers import Dem
from dem_graph.evaluation.dem_metrics import LocalErrorSeries, truth_at_cells
from dem_graph.evaluation.trajectory_metrics import trajectory_errors
from dem_graph.geometry.grid import ElevationGrid
from dem_graph.geometry.trajectory import Trajectory
from dem_graph.viz.plotting import colour, pyplot, save_figure


def _truth_over(truth: Trajectory, estimates: dict[str, Trajectory]) -> Trajectory:
    """The truth over the time the estimates span (all of it if there is no estimate)."""
    if not estimates:
        return truth
    lo = min(e.t_s[0] for e in estimates.values())
    hi = max(e.t_s[-1] for e in estimates.values())
    part = truth.slice(lo, hi)
    return part if len(part) > 1 else truth


def trajectories_figure(path: str | Path, truth: Trajectory | None, estimates: dict[str, Trajectory]) -> Path:
    """The trajectories from above (x, y in the world frame), with the ground truth over the same time."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(8.0, 6.5))
    if truth is not None:
        xy = _truth_over(truth, estimates).positions_xyz[:, :2]
        ax.plot(xy[:, 0], xy[:, 1], "k-", lw=2.5, alpha=0.35, label="ground truth")
        ax.plot(xy[0, 0], xy[0, 1], "ko", ms=6, label="start")
    for k, (name, trajectory) in enumerate(estimates.items()):
        p = trajectory.positions_xyz
        ax.plot(p[:, 0], p[:, 1], "-", color=colour(name, k), lw=1.2, label=name)
        ax.plot(p[-1, 0], p[-1, 1], "^", color=colour(name, k), ms=6)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x (m, world)")
    ax.set_ylabel("y (m, world)")
    ax.set_title("Trajectories from above (end: triangle)")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best", fontsize=8)
    return save_figure(fig, path)


def position_error_figure(path: str | Path, truth: Trajectory, estimates: dict[str, Trajectory], t0_s: float) -> Path:
    """The norm of each estimate's position error (anchored, no alignment) against time."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(8.0, 4.5))
    for k, (name, trajectory) in enumerate(estimates.items()):
        errors = trajectory_errors(trajectory, truth)
        ax.plot(errors.t_s - t0_s, np.linalg.norm(errors.position_error_m, axis=1), color=colour(name, k), lw=1.2, label=name)
    ax.set_xlabel("time since the start (s)")
    ax.set_ylabel("position error (m)")
    ax.set_title("Position error against the ground truth (anchored at the initial pose)")
    ax.set_ylim(bottom=0.0)
    ax.grid(True, alpha=0.3)
    if estimates:
        ax.legend(loc="upper left", fontsize=8)
    return save_figure(fig, path)


def local_error_figure(path: str | Path, series: dict[str, LocalErrorSeries], t0_s: float, window: str = "") -> Path:
    """The local DEM's height error in the window ahead, its mean (top) and standard deviation
    (bottom) against time, one line per estimator (the paper's Fig. 8)."""
    plt = pyplot()
    fig, (ax_mean, ax_std) = plt.subplots(2, 1, figsize=(8.0, 6.0), sharex=True)
    for k, (name, s) in enumerate(series.items()):
        t = s.t_s - t0_s
        ax_mean.plot(t, 100.0 * s.mean_m, ".-", color=colour(name, k), lw=1.0, ms=3, label=name)
        ax_std.plot(t, 100.0 * s.std_m, ".-", color=colour(name, k), lw=1.0, ms=3, label=name)
    ax_mean.axhline(0.0, color="k", lw=0.6)
    ax_mean.set_ylabel("mean height error (cm)")
    ax_std.set_ylabel("std of the height error (cm)")
    ax_std.set_xlabel("time since the start (s)")
    ax_std.set_ylim(bottom=0.0)
    ax_mean.set_title(f"Local DEM against the terrain{', ' + window if window else ''} (Fig. 8)")
    for ax in (ax_mean, ax_std):
        ax.grid(True, alpha=0.3)
    if series:
        ax_mean.legend(loc="best", fontsize=8)
    return save_figure(fig, path)


def dem_error_figure(path: str | Path, dem: Dem, truth: ElevationGrid, name: str, trajectory_xy: np.ndarray | None = None) -> Path:
    """A world-frame DEM (left, height) and its error against the truth at the cell centres (right,
    DEM minus truth, a diverging scale symmetric about zero)."""
    import matplotlib

    plt = pyplot()
    g = dem.geometry
    extent = (g.x_min_m, g.x_max_m, g.y_min_m, g.y_max_m)
    error_cm = 100.0 * (dem.elevation.astype(float) - truth_at_cells(dem, truth))
    aspect = g.n_rows / max(g.n_cols, 1)
    fig, (ax_z, ax_e) = plt.subplots(1, 2, figsize=(12.0, float(np.clip(5.0 * aspect, 3.0, 9.0)) + 1.2))
    z = dem.elevation[np.isfinite(dem.elevation)]
    lo, hi = np.percentile(z, [1, 99]) if z.size else (0.0, 1.0)
    im = ax_z.imshow(np.ma.masked_invalid(dem.elevation), extent=extent, origin="upper", interpolation="nearest",
                     cmap=matplotlib.colormaps["terrain"].with_extremes(bad="#dddddd"), vmin=lo, vmax=max(hi, lo + 1e-3))
    fig.colorbar(im, ax=ax_z, label="height (m)", shrink=0.8)
    e = np.abs(error_cm[np.isfinite(error_cm)])
    limit = max(float(np.percentile(e, 98)), 0.1) if e.size else 1.0
    im = ax_e.imshow(np.ma.masked_invalid(error_cm), extent=extent, origin="upper", interpolation="nearest",
                     cmap=matplotlib.colormaps["RdBu_r"].with_extremes(bad="#dddddd"), vmin=-limit, vmax=limit)
    fig.colorbar(im, ax=ax_e, label="DEM minus truth (cm)", shrink=0.8)
    rmse = float(np.sqrt(np.mean(e**2))) if e.size else float("nan")
    ax_z.set_title(f"DEM of {name}, {g.resolution_m:g} m cells")
    ax_e.set_title(f"height error: RMSE {rmse:.1f} cm over {e.size:,} cells")
    for ax in (ax_z, ax_e):
        if trajectory_xy is not None and len(trajectory_xy):
            ax.plot(trajectory_xy[:, 0], trajectory_xy[:, 1], "k-", lw=0.8, label="trajectory")
            ax.legend(loc="upper right", fontsize=8)
        ax.set_xlim(g.x_min_m, g.x_max_m)
        ax.set_ylim(g.y_min_m, g.y_max_m)
        ax.set_aspect("equal")
        ax.set_xlabel("x (m, world)")
        ax.set_ylabel("y (m, world)")
    return save_figure(fig, path)


__all__ = ["dem_error_figure", "local_error_figure", "position_error_figure", "trajectories_figure"]
