"""A DEM's files: ``dem.tif``, ``dem.npz``, ``cloud.ply`` and ``dem.png``.

- ``dem.tif``: north-up float32 GeoTIFF in world (or local) metres, one band per layer, each band
  described by its layer's name (``elevation``, ``variance``, ``count`` first), nodata NaN
  (:mod:`dem_graph.io.geotiff`).
- ``dem.npz``: every layer and the grid's geometry (:meth:`Dem.save_npz`).
- ``cloud.ply``: the measurements that were fused, with ``var_z_m2``, ``t_s`` and ``source``
  (0 laser return, 1 map point).
- ``dem.png``: a top view coloured by height, with a colour bar, a metre scale bar and the
  trajectory drawn on it.
- ``local_dem_error.csv`` (with ground truth): the Fig. 8 measure frame by frame, one row per
  evaluated time: ``t_s``, ``mean_m``, ``std_m``, ``relative_mean_m``, ``relative_std_m``,
  ``covered_fraction`` (see :class:`~dem_graph.evaluation.dem_metrics.LocalErrorSeries`); empty
  cells are NaN.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dem_graph.dem.layers import Dem
from dem_graph.dem.returns import GroundReturns
from dem_graph.errors import DatasetError
from dem_graph.evaluation.dem_metrics import LocalErrorSeries
from dem_graph.io.geotiff import write_elevation_geotiff
from dem_graph.io.ply import write_points_ply
from dem_graph.viz.plotting import pyplot, save_figure

_FIRST = ("variance", "count")


def write_dem_geotiff(path: str | Path, dem: Dem) -> Path:
    path = Path(path)
    names = ["elevation", *_FIRST, *[k for k in dem.layers if k not in ("elevation", *_FIRST)]]
    write_elevation_geotiff(path, dem.elevation_grid(), {k: dem.layers[k] for k in names[1:]})
    return path


def write_cloud_ply(path: str | Path, returns: GroundReturns) -> Path:
    path = Path(path)
    write_points_ply(
        path,
        returns.xyz_m,
        {"var_z_m2": returns.var_z_m2.astype(np.float32), "t_s": returns.t_s.astype(np.float64), "source": returns.source.astype(np.uint8)},
    )
    return path


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


def write_dem_outputs(out_dir: str | Path, dem: Dem, returns: GroundReturns | None = None, trajectory_xy: np.ndarray | None = None) -> dict[str, Path]:
    """Write ``dem.tif``, ``dem.npz``, ``dem.png`` and (with ``returns``) ``cloud.ply`` into ``out_dir``."""
    out = Path(out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise DatasetError(out, f"cannot create the folder ({exc.strerror or exc})") from None
    paths = {
        "dem_tif": write_dem_geotiff(out / "dem.tif", dem),
        "dem_npz": dem.save_npz(out / "dem.npz"),
        "dem_png": write_dem_png(out / "dem.png", dem, trajectory_xy),
    }
    if returns is not None:
        row, col, inside = dem.geometry.cell_index(returns.xyz_m[:, 0], returns.xyz_m[:, 1])
        ok = inside & np.all(np.isfinite(returns.xyz_m), axis=1) & np.isfinite(returns.var_z_m2)
        paths["cloud_ply"] = write_cloud_ply(out / "cloud.ply", returns.select(ok))
    return paths


LOCAL_ERROR_COLUMNS = ("t_s", "mean_m", "std_m", "relative_mean_m", "relative_std_m", "covered_fraction")


def write_local_error_csv(path: str | Path, series: LocalErrorSeries) -> Path:
    """Write the Fig. 8 series as CSV (:data:`LOCAL_ERROR_COLUMNS`, a header line, NaN where a
    frame had no data); :class:`DatasetError` naming the file if it cannot."""
    path = Path(path)
    table = np.column_stack([getattr(series, name) for name in LOCAL_ERROR_COLUMNS])
    try:
        np.savetxt(path, table, delimiter=",", header=",".join(LOCAL_ERROR_COLUMNS), comments="", fmt="%.9g")
    except OSError as exc:
        raise DatasetError(path, f"cannot write ({exc.strerror or exc})") from None
    return path


__all__ = ["LOCAL_ERROR_COLUMNS", "write_cloud_ply", "write_dem_geotiff", "write_dem_outputs", "write_dem_png", "write_local_error_csv"]
