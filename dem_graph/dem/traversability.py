"""Traversability layers for the guidance, per cell, from a DEM's elevation.

Over the ``window`` x ``window`` cells centred on each cell (the cells with a height):

- ``slope_deg``: inclination of the least-squares plane through their heights, degrees;
- ``step_height_m``: highest minus lowest height, metres;
- ``roughness_m``: standard deviation of their heights about that plane (``n - 3`` degrees of
  freedom), metres: 0 on any plane, whatever its slope.

A cell without a height, or with fewer than 4 heights in its window (3 for the step), gets NaN.
Every sum is a box filter over the grid (``scipy.ndimage``): no loop over cells.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from dem_graph.dem.layers import Dem
from dem_graph.errors import DemGraphError

TRAVERSABILITY_LAYERS = ("slope_deg", "step_height_m", "roughness_m")


def traversability(elevation: np.ndarray, resolution_m: float, window: int = 3) -> dict[str, np.ndarray]:
    """Slope, step height and roughness of a (rows, cols) elevation array (NaN: unknown)."""
    if window < 3 or window % 2 == 0:
        raise DemGraphError(f"the traversability window must be an odd number of cells >= 3, got {window}")
    z = np.asarray(elevation, dtype=float)
    known = np.isfinite(z)
    rows, cols = np.indices(z.shape, dtype=float)
    # plane z = c0 + gx * x + gy * y, x east (columns), y north (rows upward), metres; the sums are
    # centred on each window's means before solving
    x = cols * resolution_m
    y = -rows * resolution_m
    z0 = float(np.median(z[known])) if np.any(known) else 0.0
    zz = np.where(known, z - z0, 0.0)  # an offset keeps the sums of squares well conditioned
    # every window sum in one filter pass over the stacked terms (unknown cells count 0)
    terms = np.stack([np.ones_like(z), x, y, x * x, y * y, x * y, zz, x * zz, y * zz, zz * zz])
    terms *= known
    sums = ndimage.uniform_filter(terms, size=(1, window, window), mode="constant") * (window * window)
    n, sx, sy, sxx, syy, sxy, sz, sxz, syz, szz = sums
    with np.errstate(invalid="ignore", divide="ignore"):
        mx, my, mz = sx / n, sy / n, sz / n
        cxx = sxx - n * mx * mx
        cyy = syy - n * my * my
        cxy = sxy - n * mx * my
        cxz = sxz - n * mx * mz
        cyz = syz - n * my * mz
        czz = szz - n * mz * mz
        det = cxx * cyy - cxy * cxy
        ok = known & (n >= 4) & (det > 1e-12 * resolution_m**4)
        gx = np.where(ok, (cyy * cxz - cxy * cyz) / det, np.nan)
        gy = np.where(ok, (cxx * cyz - cxy * cxz) / det, np.nan)
        sse = np.maximum(czz - gx * cxz - gy * cyz, 0.0)
        roughness = np.where(ok, np.sqrt(sse / np.maximum(n - 3, 1)), np.nan)
    slope = np.degrees(np.arctan(np.hypot(gx, gy)))
    hi = ndimage.maximum_filter(np.where(known, z, -np.inf), size=window, mode="constant", cval=-np.inf)
    lo = ndimage.minimum_filter(np.where(known, z, np.inf), size=window, mode="constant", cval=np.inf)
    step = np.where(known & (n >= 3), hi - lo, np.nan)
    return {"slope_deg": slope.astype(np.float32), "step_height_m": step.astype(np.float32), "roughness_m": roughness.astype(np.float32)}


def add_traversability(dem: Dem, window: int = 3) -> Dem:
    """``dem`` with the traversability layers added (computed from its elevation)."""
    dem.layers.update(traversability(dem.layers["elevation"], dem.geometry.resolution_m, window))
    return dem


__all__ = ["TRAVERSABILITY_LAYERS", "add_traversability", "traversability"]
