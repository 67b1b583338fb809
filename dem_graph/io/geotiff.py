"""Elevation grids and per-cell layers as north-up float32 GeoTIFFs.

Each layer is one float32 band whose description is the layer's name; bands are always looked up
by that name, never by position. Unknown cells are NaN (the file's nodata value). The transform is
:meth:`GridGeometry.affine`: pixel ``(row, col)`` covers
``[x_min_m + col * res, x_min_m + (col + 1) * res] x [y_max_m - (row + 1) * res, y_max_m - row * res]``,
so row 0 is the northern-most row. The grids live in a local metric world frame, so no CRS is
written; a CRS in a file that is read is ignored.

rasterio is imported inside the functions: importing this module is cheap.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from dem_graph.errors import DatasetError
from dem_graph.geometry.grid import ElevationGrid, GridGeometry
from dem_graph.optional import import_rasterio

ELEVATION_BAND = "elevation"


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


def write_elevation_geotiff(
    path: str | Path, grid: ElevationGrid | GridGeometry, bands: dict[str, np.ndarray] | None = None
) -> None:
    """Write float32 bands on ``grid`` to a GeoTIFF, each band described by its name.

    When ``grid`` is an :class:`ElevationGrid` its heights become the first band, ``"elevation"``,
    followed by ``bands``. Every band must have the grid's shape ``(n_rows, n_cols)``; values are
    stored as float32 with NaN as nodata, so they read back exactly only if they already are float32
    (the simulator's ground-truth elevation is). Raises :class:`DatasetError` naming the file when a
    band is invalid or the file cannot be written.
    """
    rasterio = import_rasterio()
    path = Path(path)
    geometry = grid.geometry if isinstance(grid, ElevationGrid) else grid
    if not isinstance(geometry, GridGeometry):
        raise DatasetError(path, f"expected an ElevationGrid or a GridGeometry, got {type(grid).__name__}")
    layers: dict[str, np.ndarray] = {}
    if isinstance(grid, ElevationGrid):
        layers[ELEVATION_BAND] = grid.z_m
    for name, values in (bands or {}).items():
        if not isinstance(name, str) or not name:
            raise DatasetError(path, f"band names must be non-empty strings, got {name!r}")
        if name in layers:
            raise DatasetError(path, f"band {name!r} is given twice (an ElevationGrid already provides it)")
        layers[name] = values
    if not layers:
        raise DatasetError(path, "no band to write")
    arrays = {}
    for name, values in layers.items():
        a = np.asarray(values)
        if a.shape != geometry.shape:
            raise DatasetError(path, f"band {name!r} has shape {a.shape}, the grid is {geometry.shape}")
        if not (np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer) or a.dtype == bool):
            raise DatasetError(path, f"band {name!r} is not numeric (dtype {a.dtype})")
        arrays[name] = np.ascontiguousarray(a, dtype=np.float32)

    profile = dict(
        driver="GTiff",
        width=geometry.n_cols,
        height=geometry.n_rows,
        count=len(arrays),
        dtype="float32",
        nodata=np.nan,
        transform=geometry.affine(),
        compress="deflate",
    )
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
            with rasterio.open(path, "w", **profile) as dst:
                for band, (name, a) in enumerate(arrays.items(), start=1):
                    dst.write(a, band)
                    dst.set_band_description(band, name)
    except rasterio.errors.RasterioError as exc:
        raise DatasetError(path, f"cannot write GeoTIFF ({_first_line(exc)})") from None


def read_elevation_geotiff(path: str | Path) -> tuple[GridGeometry, dict[str, np.ndarray]]:
    """Read a north-up GeoTIFF: its grid geometry and its bands as float32 arrays keyed by band name.

    Bands without a description are keyed ``"band_<n>"`` (1-based). Cells equal to the file's
    nodata value are returned as NaN. Raises :class:`DatasetError` naming the file when it is
    missing or not a readable GeoTIFF, is not north-up with square pixels, or repeats a band name.
    """
    rasterio = import_rasterio()
    path = Path(path)
    if not path.is_file():
        raise DatasetError(path, "file not found" if not path.exists() else "not a regular file")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
            with rasterio.open(path) as src:
                t = src.transform
                if not (t.b == 0.0 and t.d == 0.0 and t.a > 0.0 and t.e < 0.0):
                    raise DatasetError(path, f"not a north-up raster (transform {tuple(t)[:6]})")
                if t.a != -t.e:
                    raise DatasetError(path, f"pixels are not square ({t.a!r} x {-t.e!r} m)")
                geometry = GridGeometry(
                    x_min_m=float(t.c), y_max_m=float(t.f), resolution_m=float(t.a), n_rows=src.height, n_cols=src.width
                )
                nodata = src.nodata
                bands: dict[str, np.ndarray] = {}
                for band, description in enumerate(src.descriptions, start=1):
                    name = description if description else f"band_{band}"
                    if name in bands:
                        raise DatasetError(path, f"band name {name!r} appears twice")
                    a = src.read(band)
                    if nodata is not None and not np.isnan(nodata):
                        a = np.where(a == nodata, np.nan, a)
                    bands[name] = np.asarray(a, dtype=np.float32)
    except rasterio.errors.RasterioError as exc:
        raise DatasetError(path, f"not a readable GeoTIFF ({_first_line(exc)})") from None
    return geometry, bands


def write_elevation(path: str | Path, elevation: ElevationGrid) -> None:
    """Write an :class:`ElevationGrid` as a one-band GeoTIFF (band ``"elevation"``, float32).

    Heights round-trip exactly only if they already are float32, as the simulator's are.
    """
    write_elevation_geotiff(path, elevation)


def read_elevation(path: str | Path) -> ElevationGrid:
    """Read the ``"elevation"`` band of a GeoTIFF as an :class:`ElevationGrid` (float32 heights).

    Raises :class:`DatasetError` naming the file if it is missing, corrupt or has no such band.
    """
    geometry, bands = read_elevation_geotiff(path)
    if ELEVATION_BAND not in bands:
        raise DatasetError(path, f"no {ELEVATION_BAND!r} band (bands: {', '.join(sorted(bands)) or 'none'})")
    return ElevationGrid(geometry, bands[ELEVATION_BAND])
