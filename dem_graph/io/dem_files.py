"""A DEM's files: ``dem.tif``, ``dem.npz`` and ``cloud.ply`` (the picture, ``dem.png``, is drawn by
:mod:`dem_graph.viz.dem_figure`).

- ``dem.tif``: north-up float32 GeoTIFF in world (or local) metres, one band per layer, each band
  described by its layer's name (``elevation``, ``variance``, ``count`` first), nodata NaN
  (:mod:`dem_graph.io.geotiff`).
- ``dem.npz``: every layer, the grid's geometry and the map's frame (:func:`write_dem_npz`,
  :func:`read_dem_npz`).
- ``cloud.ply``: the measurements that were fused, with ``var_z_m2``, ``t_s`` and ``source``
  (:class:`~dem_graph.dem.returns.ReturnSource`: 0 laser return, 1 map point).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dem_graph.dem.layers import Dem
from dem_graph.dem.returns import GroundReturns
from dem_graph.errors import DatasetError
from dem_graph.geometry.grid import GridGeometry
from dem_graph.io.geotiff import write_elevation_geotiff
from dem_graph.io.npz import read_npz
from dem_graph.io.ply import write_points_ply

_FIRST = ("variance", "count")
_GEOMETRY_KEYS = ("x_min_m", "y_max_m", "resolution_m", "n_rows", "n_cols")


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


def write_dem_npz(path: str | Path, dem: Dem) -> Path:
    """Every layer, the grid's geometry and the map's frame in one compressed ``.npz``."""
    path = Path(path)
    g = dem.geometry
    arrays = {f"layer_{k}": v for k, v in dem.layers.items()}
    arrays.update(
        x_min_m=g.x_min_m, y_max_m=g.y_max_m, resolution_m=g.resolution_m, n_rows=g.n_rows, n_cols=g.n_cols,
        frame=np.array(dem.frame), n_measurements=dem.n_measurements, n_used=dem.n_used,
    )
    try:
        with path.open("wb") as fh:
            np.savez_compressed(fh, **arrays)
    except OSError as exc:
        raise DatasetError(path, f"cannot write ({exc.strerror or exc})") from None
    return path


def read_dem_npz(path: str | Path) -> Dem:
    """A DEM written by :func:`write_dem_npz`; :class:`DatasetError` naming the file if it is not one."""
    path = Path(path)
    data = read_npz(path, _GEOMETRY_KEYS, ("frame", "n_measurements", "n_used"), prefix="layer_")
    try:
        g = GridGeometry(float(data["x_min_m"]), float(data["y_max_m"]), float(data["resolution_m"]), int(data["n_rows"]), int(data["n_cols"]))
        layers = {k[len("layer_"):]: np.asarray(data[k]) for k in data if k.startswith("layer_")}
        frame = str(data["frame"]) if "frame" in data else "world"
        n_meas = int(data["n_measurements"]) if "n_measurements" in data else 0
        n_used = int(data["n_used"]) if "n_used" in data else 0
    except (TypeError, ValueError) as exc:
        raise DatasetError(path, f"not a DEM file ({exc})") from None
    for name, a in layers.items():
        if a.shape != g.shape:
            raise DatasetError(path, f"layer {name!r} has shape {a.shape}, the grid is {g.shape}")
    return Dem(g, layers, n_measurements=n_meas, n_used=n_used, frame=frame)


__all__ = ["read_dem_npz", "write_cloud_ply", "write_dem_geotiff", "write_dem_npz"]
