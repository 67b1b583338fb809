"""A DEM as a picture: a top view coloured by height, with a colour bar, a metre scale bar and the
trajectory drawn on it (``dem.png``).

The colours span the ground near the path (:func:`colour_range`), not the whole map: a street's
walls or a field's hedges, metres above the ground the vehicle drove on, would otherwise take the
scale and leave the ground one colour. Heights outside the span take the end colours (the colour
bar's arrows)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dem_graph.dem.layers import Dem
from dem_graph.viz.plotting import pyplot, save_figure

NEAR_PATH_M = 5.0
"""The colour scale is taken from the cells whose centre lies within this distance of the path, metres."""
COLOUR_PERCENTILES = (2.0, 98.0)
"""The percentiles of those cells' heights that the colours span (robust to a few wrong cells)."""
MIN_NEAR_CELLS = 50
"""Fewer covered cells than this near the path (or no path): the scale is taken from every covered cell."""


def colour_range(dem: Dem, trajectory_xy: np.ndarray | None = None, near_m: float = NEAR_PATH_M) -> tuple[float, float, str]:
    """The heights the colours span, metres, and what they were taken from (for the colour bar): the
    :data:`COLOUR_PERCENTILES` of the covered cells within ``near_m`` of the path's xy positions,
    or of every covered cell when the path is missing or passes by fewer than :data:`MIN_NEAR_CELLS`."""
    from scipy.spatial import cKDTree

    z = dem.elevation
    finite = np.isfinite(z)
    if not finite.any():
        return 0.0, 1.0, "no covered cell"
    what, heights = "every covered cell", z[finite]
    if trajectory_xy is not None and len(trajectory_xy):
        X, Y = dem.geometry.cell_centers_xy()
        path = np.asarray(trajectory_xy, dtype=float)[:, :2]
        path = path[np.all(np.isfinite(path), axis=1)]
        if len(path):
            distance, _ = cKDTree(path).query(np.stack([X[finite], Y[finite]], axis=1), distance_upper_bound=near_m)
            near = heights[np.isfinite(distance)]
            if near.size >= MIN_NEAR_CELLS:
                what, heights = f"the ground within {near_m:g} m of the path", near
    low, high = np.percentile(heights, COLOUR_PERCENTILES)
    return float(low), float(max(high, low + 1e-3)), f"{what}, {COLOUR_PERCENTILES[0]:g}-{COLOUR_PERCENTILES[1]:g} %"


def _nice_length(extent_m: float) -> float:
    """A round scale-bar length near a fifth of ``extent_m``."""
    target = max(extent_m / 5.0, 1e-3)
    base = 10 ** np.floor(np.log10(target))
    return float(base * max(m for m in (1, 2, 5) if m * base <= target))


def write_dem_png(path: str | Path, dem: Dem, trajectory_xy: np.ndarray | None = None, title: str | None = None) -> Path:
    """Top view of the elevation (colour map and bar), a metre scale bar and the trajectory."""
    import matplotlib
    from mpl_toolkits.axes_grid1.anchored_artists import AnchoredSizeBar

    plt = pyplot()
    g = dem.geometry
    z = np.ma.masked_invalid(dem.elevation)
    extent = (g.x_min_m, g.x_max_m, g.y_min_m, g.y_max_m)
    aspect = g.n_rows / max(g.n_cols, 1)
    fig, ax = plt.subplots(figsize=(8.0, float(np.clip(6.5 * aspect, 3.0, 10.0)) + 1.0))
    try:
        cmap = matplotlib.colormaps["terrain"].with_extremes(bad="#dddddd", over="#505050")  # above the span: dark grey, not the scale's white
        vmin, vmax, scaled_to = colour_range(dem, trajectory_xy)
        im = ax.imshow(z, extent=extent, origin="upper", cmap=cmap, vmin=vmin, vmax=vmax, interpolation="nearest")
        height = "height (m)" if dem.frame == "world" else "height above the body origin (m)"
        fig.colorbar(im, ax=ax, label=f"{height}; scaled to {scaled_to}", shrink=0.8, extend="both")
        if trajectory_xy is not None and len(trajectory_xy):
            ax.plot(trajectory_xy[:, 0], trajectory_xy[:, 1], "k-", lw=1.0, label="trajectory")
            ax.plot(trajectory_xy[-1, 0], trajectory_xy[-1, 1], "k^", ms=6)
            ax.legend(loc="upper right", fontsize=8)
        ax.set_xlim(g.x_min_m, g.x_max_m)  # the path may reach beyond the map
        ax.set_ylim(g.y_min_m, g.y_max_m)
        length = _nice_length(g.x_max_m - g.x_min_m)
        ax.add_artist(AnchoredSizeBar(ax.transData, length, f"{length:g} m", "lower left", pad=0.4, frameon=True, size_vertical=0))
        frame = "world" if dem.frame == "world" else "local: x ahead, y left"
        ax.set_xlabel(f"x (m, {frame})")
        ax.set_ylabel("y (m)")
        ax.set_aspect("equal")
        covered = dem.covered.sum()
        ax.set_title(title or f"DEM, {g.resolution_m:g} m cells, {covered} covered")
    except BaseException:
        plt.close(fig)
        raise
    return save_figure(fig, path, dpi=110)


__all__ = ["COLOUR_PERCENTILES", "NEAR_PATH_M", "colour_range", "write_dem_png"]
