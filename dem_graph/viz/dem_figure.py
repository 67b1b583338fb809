"""A DEM as a picture: a top view coloured by height, with a colour bar, a metre scale bar and the
trajectory drawn on it (``dem.png``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dem_graph.dem.layers import Dem
from dem_graph.viz.plotting import pyplot, save_figure


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
        cmap = matplotlib.colormaps["terrain"].with_extremes(bad="#dddddd")
        finite = dem.elevation[np.isfinite(dem.elevation)]
        vmin, vmax = (np.percentile(finite, [1, 99]) if finite.size else (0.0, 1.0))
        im = ax.imshow(z, extent=extent, origin="upper", cmap=cmap, vmin=vmin, vmax=max(vmax, vmin + 1e-3), interpolation="nearest")
        fig.colorbar(im, ax=ax, label="height (m)" if dem.frame == "world" else "height above the body origin (m)", shrink=0.8)
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


__all__ = ["write_dem_png"]
