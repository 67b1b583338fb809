"""Traversability layers for the guidance, per cell, from a DEM's elevation.

Over the ``window`` x ``window`` cells centred on each cell (the cells with a height):

- ``slope_deg``: inclination of the least-squares plane through their heights, degrees;
- ``step_height_m``: highest minus lowest height, metres;
- ``roughness_m``: standard deviation of their heights about that plane (``n - 3`` degrees of
  freedom), metres: 0 on any plane, whatever its slope.

A cell without a height, or with fewer than 4 heights in its window (3 for the step), gets NaN.
One compiled pass over the cells (numba), each window's sums taken about its centre cell.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from dem_graph.dem.layers import Dem
from dem_graph.errors import DemGraphError

TRAVERSABILITY_LAYERS = ("slope_deg", "step_height_m", "roughness_m")


def traversability(elevation: np.ndarray, resolution_m: float, window: int = 3) -> dict[str, np.ndarray]:
    """Slope, step height and roughness of a (rows, cols) elevation array (NaN: unknown)."""
    if window < 3 or window % 2 == 0:
        raise DemGraphError(f"the traversability window must be an odd number of cells >= 3, got {window}")
    z = np.ascontiguousarray(elevation, dtype=float)
    if z.ndim != 2:
        raise DemGraphError(f"the traversability needs a (rows, cols) elevation array, got shape {z.shape}")
    slope, step, roughness = _layers(z, float(resolution_m), int(window))
    return {"slope_deg": slope, "step_height_m": step, "roughness_m": roughness}


@numba.njit(cache=True, nogil=True)
def _layers(z: np.ndarray, resolution_m: float, window: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The three layers (float32) cell by cell. Within each window, positions are taken from the
    window's centre cell (x east along the columns, y north up the rows, metres) and heights from
    its height, so the sums stay well conditioned wherever the grid lies; the plane is then solved
    about the window's means."""
    rows, cols = z.shape
    half = window // 2
    slope = np.full((rows, cols), np.nan, dtype=np.float32)
    step = np.full((rows, cols), np.nan, dtype=np.float32)
    roughness = np.full((rows, cols), np.nan, dtype=np.float32)
    det_min = 1e-12 * resolution_m**4
    for r in range(rows):
        for c in range(cols):
            z_c = z[r, c]
            if not np.isfinite(z_c):
                continue
            n = 0.0
            sx = sy = sxx = syy = sxy = sz = sxz = syz = szz = 0.0
            hi = -np.inf
            lo = np.inf
            for rr in range(max(r - half, 0), min(r + half + 1, rows)):
                y = (r - rr) * resolution_m
                for cc in range(max(c - half, 0), min(c + half + 1, cols)):
                    zz = z[rr, cc]
                    if not np.isfinite(zz):
                        continue
                    hi = max(hi, zz)
                    lo = min(lo, zz)
                    x = (cc - c) * resolution_m
                    d = zz - z_c
                    n += 1.0
                    sx += x
                    sy += y
                    sxx += x * x
                    syy += y * y
                    sxy += x * y
                    sz += d
                    sxz += x * d
                    syz += y * d
                    szz += d * d
            if n >= 3:
                step[r, c] = hi - lo
            if n < 4:
                continue
            mx, my, mz = sx / n, sy / n, sz / n
            cxx = sxx - n * mx * mx
            cyy = syy - n * my * my
            cxy = sxy - n * mx * my
            cxz = sxz - n * mx * mz
            cyz = syz - n * my * mz
            czz = szz - n * mz * mz
            det = cxx * cyy - cxy * cxy
            if not det > det_min:
                continue
            gx = (cyy * cxz - cxy * cyz) / det
            gy = (cxx * cyz - cxy * cxz) / det
            sse = max(czz - gx * cxz - gy * cyz, 0.0)
            roughness[r, c] = math.sqrt(sse / max(n - 3.0, 1.0))
            slope[r, c] = math.degrees(math.atan(math.hypot(gx, gy)))
    return slope, step, roughness


def compile_kernel() -> None:
    """Run the compiled layers once on a small grid, so that numba compiles them (the first run after
    an install) or loads them from its cache before a live run's first frame rather than in it."""
    traversability(np.zeros((3, 3)), 0.1)


def add_traversability(dem: Dem, window: int = 3) -> Dem:
    """``dem`` with the traversability layers added (computed from its elevation)."""
    dem.layers.update(traversability(dem.layers["elevation"], dem.geometry.resolution_m, window))
    return dem


__all__ = ["TRAVERSABILITY_LAYERS", "add_traversability", "compile_kernel", "traversability"]
