"""Per-cell fusion of ground measurements into an elevation grid with a variance per cell.

Each cell's height is a constant observed by every measurement that falls in it, so a Kalman
filter over a cell's measurements ends at their inverse-variance weighted mean, with variance
``1 / sum(1 / var_i)``. That is computed here for all cells at once (``np.bincount``), which makes
the result independent of the order of the measurements and lets the DEM be rebuilt from revised
poses in one vectorised pass.

Outliers are gated as in the elevation-mapping literature (Fankhauser et al., 2014): a measurement
is kept only if its Mahalanobis distance to the cell's estimate is within ``gate_sigma``. A
sequential filter gates against the estimate so far, which an early outlier can capture; here the
first gate is against the cell's median (robust), the second against the inliers' fused height:

    (z_i - h_cell)^2 <= gate_sigma^2 (var_i + var_cell + gate_floor_m^2)

``gate_floor_m`` stands for the terrain's height variation inside one cell, which the point
measurements' own variances do not describe (a slope within a 10 cm cell, grass).

Note that the cell variance treats measurements as independent. Returns placed with the same pose
share that pose's error, so the variance of a cell hit many times from one pose is optimistic.
"""

from __future__ import annotations

import logging

import numpy as np
from pydantic import Field

from dem_graph.config_types import StrictModel
from dem_graph.dem.layers import Dem
from dem_graph.dem.returns import GroundReturns, ReturnSource
from dem_graph.errors import DemGraphError
from dem_graph.geometry.grid import GridGeometry

log = logging.getLogger(__name__)

_Z_BITS = 24  # height quantisation bits in the median's sort key


class FusionConfig(StrictModel):
    resolution_m: float = Field(
        0.1,
        ge=0.01,
        allow_inf_nan=False,
        description="DEM cell size, metres (at least 1 cm: the ranging noise is centimetres, and the live local map is made again at every frame)",
    )
    gate_sigma: float = Field(3.0, gt=0, description="Mahalanobis gate on a measurement against its cell, in sigmas")
    gate_floor_m: float = Field(0.03, ge=0, description="height variation inside one cell, added to the gate's variance, metres")
    min_variance_m2: float = Field(1e-8, gt=0, description="floor on a measurement's height variance, m^2")
    gate_passes: int = Field(1, ge=1, description="gates against the fused height after the median's (each one more pass over the data)")
    margin_m: float = Field(0.5, ge=0, description="the global grid extends this far beyond the measurements, metres")
    max_cells: int = Field(
        50_000_000,
        ge=1,
        description="most cells a global grid may have (each costs about 60 bytes over its layers); a larger one is refused before it is allocated",
    )


def _cell_order_stats(cell: np.ndarray, z: np.ndarray, n_cells: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Lower median, minimum and maximum height of each cell (NaN where empty) and its number of
    measurements, from one sort of
    (cell, quantised height) keys; heights to within half a quantum (0.05 mm for heights spanning
    less than 1.6 km)."""
    z_lo, z_hi = float(z.min()), float(z.max())
    quantum = max(1e-4, (z_hi - z_lo) / (2**_Z_BITS - 2))
    key = cell << _Z_BITS
    zq = z - z_lo
    zq *= 1.0 / quantum
    zq += 0.5
    key |= zq.astype(np.int64)  # round to nearest; at most 2**_Z_BITS - 1 by the choice of quantum
    key.sort()
    cells_sorted = key >> _Z_BITS
    starts = np.flatnonzero(np.r_[True, cells_sorted[1:] != cells_sorted[:-1]])
    ends = np.r_[starts[1:], len(key)] - 1
    out = []
    for at in (starts + (ends - starts) // 2, starts, ends):
        values = np.full(n_cells, np.nan)
        k = key[at]
        values[k >> _Z_BITS] = z_lo + (k & (2**_Z_BITS - 1)) * quantum
        out.append(values)
    n = np.zeros(n_cells)
    n[cells_sorted[starts]] = ends - starts + 1
    return out[0], out[1], out[2], n


def fuse(returns: GroundReturns, geometry: GridGeometry, config: FusionConfig | None = None) -> Dem:
    """Fuse ``returns`` into the cells of ``geometry``; measurements outside the grid are ignored.

    Measurements with a non-finite position or variance are left out (and counted in the log);
    they never reach a cell. An empty input gives an empty map (every cell NaN, count 0).
    """
    config = config or FusionConfig()
    shape = geometry.shape
    n_cells = shape[0] * shape[1]
    xyz = np.asarray(returns.xyz_m, dtype=float)
    var = np.asarray(returns.var_z_m2, dtype=float)
    finite = np.isfinite(xyz[:, 0] + xyz[:, 1] + xyz[:, 2] + var) & (var >= 0)  # a sum is finite only if every term is
    if not np.all(finite):
        log.warning("%d of %d ground measurements have NaN or infinite values: left out of the DEM", int((~finite).sum()), len(finite))
    row, col, inside = geometry.cell_index(xyz[:, 0], xyz[:, 1])
    keep = finite & inside
    row *= shape[1]
    row += col
    all_kept = bool(np.all(keep))
    cell = row if all_kept else np.where(keep, row, 0)
    z = xyz[:, 2]
    var = np.maximum(var, config.min_variance_m2)
    t = np.asarray(returns.t_s, dtype=float)
    laser = np.asarray(returns.source) == ReturnSource.LASER_RETURN
    if not all_kept:  # compact only when something is left out (rare for a grid made to cover the data)
        cell, z, var, t, laser = cell[keep], z[keep], var[keep], t[keep], laser[keep]
    if len(z) == 0:
        return Dem.empty(geometry, n_measurements=len(returns))
    w = 1.0 / var
    wz = w * z
    gate2 = config.gate_sigma**2
    var_i = var + config.gate_floor_m**2  # a measurement's part of the gate's variance

    def gate(reference: np.ndarray, var_reference: np.ndarray) -> np.ndarray:
        d = z - np.take(reference, cell)
        d *= d
        bound = np.take(var_reference, cell)
        bound += var_i
        bound *= gate2
        return d <= bound

    # first gate: against the cell's median, whose variance is about pi/2 that of the mean
    median, z_min, z_max, n_all = _cell_order_stats(cell, z, n_cells)
    with np.errstate(divide="ignore"):
        var_median = (np.pi / 2.0) / np.bincount(cell, weights=w, minlength=n_cells)
    inlier = gate(median, var_median)
    # then against the inliers' fused height (what a Kalman filter gates against); the weights
    # times the inlier mask keep every array at full length
    for gate_pass in range(config.gate_passes + 1):
        W = np.bincount(cell, weights=w * inlier, minlength=n_cells)
        with np.errstate(invalid="ignore", divide="ignore"):
            h = np.bincount(cell, weights=wz * inlier, minlength=n_cells) / W
            var_h = 1.0 / W
        if gate_pass == config.gate_passes:
            break
        # a cell whose measurements all failed the median's gate keeps the median as its reference
        empty = W <= 0
        h[empty] = median[empty]
        var_h[empty] = var_median[empty]
        inlier = gate(h, var_h)

    count = np.bincount(cell, weights=inlier, minlength=n_cells)
    has = count > 0
    elevation = np.where(has, h, np.nan)
    variance = np.where(has, var_h, np.nan)
    outliers = n_all - count
    t_last = np.full(n_cells, -np.inf)
    np.maximum.at(t_last, cell, t)
    if np.any(outliers):  # the few cells with a rejected measurement: min, max, time over their inliers only (cells left without one are NaN below)
        redo = (outliers > 0)[cell] & inlier
        ci, zi, ti = cell[redo], z[redo], t[redo]
        lo, hi, last = np.full(n_cells, np.inf), np.full(n_cells, -np.inf), np.full(n_cells, -np.inf)
        np.minimum.at(lo, ci, zi)
        np.maximum.at(hi, ci, zi)
        np.maximum.at(last, ci, ti)
        fix = (outliers > 0) & has
        z_min[fix], z_max[fix], t_last[fix] = lo[fix], hi[fix], last[fix]
    laser_count = count if np.all(laser) else np.bincount(cell, weights=inlier & laser, minlength=n_cells)
    layers = {
        "elevation": elevation,
        "variance": variance,
        "count": count,
        "min": np.where(has, z_min, np.nan),
        "max": np.where(has, z_max, np.nan),
        "last_update_s": np.where(has, t_last, np.nan),
        "outliers": outliers,
        "laser_count": laser_count,
    }
    return Dem(geometry, {k: v.reshape(shape).astype(np.float32) for k, v in layers.items()}, n_measurements=len(returns), n_used=int(inlier.sum()))


def covering_geometry(returns: GroundReturns, config: FusionConfig | None = None) -> GridGeometry:
    """The north-up grid that covers every finite measurement, plus ``margin_m``."""
    config = config or FusionConfig()
    xyz = np.asarray(returns.xyz_m, dtype=float)
    ok = np.all(np.isfinite(xyz), axis=1)
    if not np.any(ok):
        raise DemGraphError("no ground measurement with a finite position: nothing to make a DEM from")
    lo = xyz[ok, :2].min(axis=0) - config.margin_m
    hi = xyz[ok, :2].max(axis=0) + config.margin_m
    r = config.resolution_m
    lo = np.floor(lo / r) * r  # cell edges on multiples of the resolution: maps of one place line up
    hi = np.ceil(hi / r) * r
    (width_m, height_m), n_cells = hi - lo, np.prod(np.ceil((hi - lo) / r))
    if n_cells > config.max_cells:
        raise DemGraphError(
            f"a DEM of {width_m:.1f} x {height_m:.1f} m in cells of {r:g} m would have {n_cells:.3g} cells, more than "
            f"dem.fusion.max_cells ({config.max_cells:.3g}): choose a coarser resolution"
        )
    return GridGeometry.covering(lo[0], lo[1], hi[0], hi[1], r)


__all__ = ["FusionConfig", "covering_geometry", "fuse"]
