"""The live map as the viewer draws it in 3D: arrays in, arrays out (no rerun here).

- :func:`surface_mesh`: a DEM's known cells as a triangle mesh, a flat square per cell, coloured by
  its height or by its height's standard deviation (the ``variance`` layer's root);
- :func:`focus_outline`: the focus area's rectangle in the heading frame, as a closed line;
- :func:`scan_returns_world`: the world positions of the laser returns of the scans the live map
  took since a count of scans, placed with the poses the map holds them at now.
"""

from __future__ import annotations

from typing import Literal

import numpy as np

from dem_graph.dem.layers import Dem
from dem_graph.dem.live_map import LiveMap
from dem_graph.errors import DemGraphError

ColourBy = Literal["height", "sigma"]
COLOUR_BY: tuple[str, ...] = ("height", "sigma")
HEIGHT_COLORMAP = "viridis"
SIGMA_COLORMAP = "magma"


def colour_values(values: np.ndarray, value_range: tuple[float, float], colormap: str) -> np.ndarray:
    """(N,3) uint8 colours of ``values`` through ``colormap``, clipped to ``value_range`` (low, high)."""
    from matplotlib import colormaps

    lo, hi = value_range
    if not hi > lo:
        raise DemGraphError(f"a colour range needs low < high, got {value_range}")
    scaled = np.clip((np.asarray(values, dtype=float) - lo) / (hi - lo), 0.0, 1.0)
    return (colormaps[colormap](np.nan_to_num(scaled, nan=0.0))[..., :3] * 255).astype(np.uint8).reshape(-1, 3)


def surface_mesh(
    dem: Dem,
    colour_by: ColourBy = "height",
    height_range_m: tuple[float, float] = (-0.3, 0.3),
    sigma_range_m: tuple[float, float] = (0.0, 0.05),
    height_reference_m: float = 0.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The known cells of ``dem`` as a mesh in the DEM's own frame (world, or the heading frame of a
    local map): each known cell a flat square at its height, as a grid map is drawn, so that every
    cell shows and none is interpolated.

    Returns vertices (4N,3) float32, the four corners of each known cell (x and y in metres, z the
    ``elevation`` layer as it is), cells in row-major order (``dem.elevation[dem.covered]``);
    triangles (2N,3) uint32, counter-clockwise seen from above; colours (4N,3) uint8.
    ``colour_by="height"``: ``elevation - height_reference_m`` over ``height_range_m`` (viridis);
    ``"sigma"``: the square root of ``variance`` over ``sigma_range_m`` (magma)."""
    if colour_by not in COLOUR_BY:
        raise DemGraphError(f"colour_by must be one of {', '.join(COLOUR_BY)}, got {colour_by!r}")
    g = dem.geometry
    z = np.asarray(dem.elevation)
    known = np.isfinite(z)
    X, Y = g.cell_centers_xy()
    h = g.resolution_m / 2.0
    corner_dx = np.array([-h, h, h, -h])  # south-west, south-east, north-east, north-west: counter-clockwise from above
    corner_dy = np.array([-h, -h, h, h])
    n = int(known.sum())
    vertices = np.stack([
        (X[known][:, None] + corner_dx).ravel(), (Y[known][:, None] + corner_dy).ravel(), np.repeat(z[known], 4),
    ], axis=1).astype(np.float32)
    first = 4 * np.arange(n)[:, None]
    triangles = np.concatenate([first + [0, 1, 2], first + [0, 2, 3]], axis=1).reshape(-1, 3).astype(np.uint32)
    if colour_by == "height":
        cell_colours = colour_values(z[known] - height_reference_m, height_range_m, HEIGHT_COLORMAP)
    else:
        cell_colours = colour_values(np.sqrt(np.asarray(dem.variance)[known]), sigma_range_m, SIGMA_COLORMAP)
    return vertices, triangles, np.repeat(cell_colours, 4, axis=0)


def focus_outline(x_range_m: tuple[float, float], half_width_m: float, z_m: float = 0.0) -> np.ndarray:
    """(5,3) float32: the focus area's rectangle in the heading frame (``x_range_m`` ahead,
    ``half_width_m`` to each side, at height ``z_m``), closed."""
    x0, x1 = x_range_m
    w = half_width_m
    return np.array([[x0, -w, z_m], [x1, -w, z_m], [x1, w, z_m], [x0, w, z_m], [x0, -w, z_m]], dtype=np.float32)


def scan_returns_world(live_map: LiveMap, scans_seen: int) -> tuple[np.ndarray, int]:
    """The world positions (N,3) of the returns of the scans ``live_map`` took after its first
    ``scans_seen`` scans, each placed with the pose the map holds its scan at now (after the frame's
    revision), and the number of scans it has taken.

    A scan already frozen out of the map's revision window is not returned."""
    taken = int(live_map.counters["scans"])
    return live_map.newest_returns_world(taken - int(scans_seen)), taken


__all__ = ["COLOUR_BY", "ColourBy", "colour_values", "focus_outline", "scan_returns_world", "surface_mesh"]
