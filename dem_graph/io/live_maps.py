"""Saved live maps: the local maps the guidance had, every k-th frame, in one netCDF file.

``live_maps.nc`` (netCDF 3, written and read through xarray; any netCDF tool opens it) holds

- dimensions ``time`` (seconds, the frames' times), ``y`` (metres, to the left, first row the
  leftmost, as in a north-up grid) and ``x`` (metres, ahead of the body origin);
- one variable per layer, ``(time, y, x)`` float32: ``elevation`` (metres, relative to the body
  origin's height), ``variance``, ``count``, ``age_s`` and the traversability layers;
- per time, the heading frame in the world: ``x_world_m``, ``y_world_m``, ``z_world_m``, ``yaw_rad``.

While a run goes, :class:`LiveMapWriter` appends each saved map to a raw temporary file (nothing
is held in memory); :meth:`LiveMapWriter.close` turns what it saved into the netCDF file, at the
end of a run or where a run stopped.
"""

from __future__ import annotations

import json
import os
import tempfile
import weakref
from pathlib import Path

import numpy as np

from dem_graph.dem.layers import Dem
from dem_graph.dem.views import heading_frame
from dem_graph.errors import DatasetError, DemGraphError, one_line
from dem_graph.geometry.grid import GridGeometry

SAVED_LAYERS = ("elevation", "variance", "count", "age_s", "slope_deg", "step_height_m", "roughness_m")
_POSE_VARS = ("x_world_m", "y_world_m", "z_world_m", "yaw_rad")
NETCDF3_MAGIC = b"CDF"  # the first bytes of a netCDF 3 file (classic or 64-bit offset), the format written here


class LiveMapWriter:
    """Appends local maps of one geometry to a temporary file until :meth:`close` (see the module)."""

    def __init__(self, geometry: GridGeometry, layers: tuple[str, ...] = SAVED_LAYERS):
        self.geometry = geometry
        self.layers = tuple(layers)
        fd, raw = tempfile.mkstemp(prefix="dem_graph_live_maps_", suffix=".part")
        self._raw = Path(raw)
        self._file = os.fdopen(fd, "wb")
        self._cleanup = weakref.finalize(self, _remove, self._file, self._raw)  # a writer never closed leaves no file behind
        self._times: list[float] = []
        self._poses: list[tuple[float, float, float, float]] = []

    def __len__(self) -> int:
        return len(self._times)

    def append(self, dem: Dem) -> None:
        if dem.geometry != self.geometry:
            raise DemGraphError(f"a saved live map must have the writer's grid {self.geometry}, not {dem.geometry}")
        stack = np.stack([np.asarray(dem.layers[name], dtype=np.float32) for name in self.layers])
        stack.tofile(self._file)
        T = dem.meta["T_world_local"]
        self._times.append(float(dem.meta["t_s"]))
        self._poses.append((float(T[0, 3]), float(T[1, 3]), float(T[2, 3]), float(np.arctan2(T[1, 0], T[0, 0]))))

    def close(self, path: str | Path) -> Path | None:
        """Write what was saved as the netCDF file ``path`` (None when no map was saved); the writer is done."""
        self._file.flush()
        n = len(self._times)
        try:
            if n == 0:
                return None
            g = self.geometry
            data = np.fromfile(self._raw, dtype=np.float32).reshape(n, len(self.layers), g.n_rows, g.n_cols)
            return write_live_maps(path, np.array(self._times), data, self.layers, g, np.array(self._poses))
        finally:
            self._cleanup()


def _remove(file, raw: Path) -> None:
    file.close()
    raw.unlink(missing_ok=True)


def write_live_maps(path: str | Path, times_s: np.ndarray, data: np.ndarray, layers: tuple[str, ...], geometry: GridGeometry, poses: np.ndarray) -> Path:
    """``data`` (time, layer, rows, cols) as ``live_maps.nc`` (see the module)."""
    import xarray as xr

    path = Path(path)
    coords = {"time": ("time", np.asarray(times_s, dtype=float), {"units": "s"}), "y": ("y", geometry.cell_center_y_m(), {"units": "m"}), "x": ("x", geometry.cell_center_x_m(), {"units": "m"})}
    variables = {name: (("time", "y", "x"), data[:, i]) for i, name in enumerate(layers)}
    variables.update({name: ("time", poses[:, i]) for i, name in enumerate(_POSE_VARS)})
    ds = xr.Dataset(variables, coords=coords, attrs={"title": "dem_graph live local maps", "frame": "vehicle heading frame: x ahead, y left, z up; elevation relative to the body origin", "resolution_m": geometry.resolution_m, "layers": json.dumps(list(layers))})
    try:
        ds.to_netcdf(path, engine="scipy")
    except OSError as exc:
        raise DatasetError(path, f"cannot write ({exc.strerror or exc})") from None
    return path


def _open(path: Path):
    """The saved live maps, opened lazily (an ``xarray.Dataset``: close it); :class:`DatasetError` naming the file if it cannot be read."""
    import xarray as xr

    if not path.is_file():
        raise DatasetError(path, "no saved live maps (the run saved none: live_map.save_every_n_frames 0, or an older run)")
    try:
        with path.open("rb") as fh:
            magic = fh.read(3)
    except OSError as exc:
        raise DatasetError(path, f"cannot read ({exc.strerror or exc})") from None
    if magic != NETCDF3_MAGIC:
        raise DatasetError(path, "not a NetCDF live-maps file (it does not begin as a netCDF 3 file does: replaced or damaged)")
    try:
        return xr.open_dataset(path, engine="scipy")
    except Exception as exc:  # noqa: BLE001 - any reader failure is a corrupt file to the user
        raise DatasetError(path, f"not a readable live-maps file ({type(exc).__name__}: {one_line(exc, 160)})") from None


def read_live_maps(path: str | Path):
    """The saved live maps as an ``xarray.Dataset`` in memory; :class:`DatasetError` naming the file if it cannot be read."""
    with _open(Path(path)) as ds:
        return ds.load()


def live_map_at(path: str | Path, t_s: float) -> Dem:
    """The saved live map of the latest time at or before ``t_s`` (``meta['t_s']`` says which); only that map is read."""
    with _open(Path(path)) as ds:
        times = ds["time"].values
        i = int(np.searchsorted(times, t_s, side="right")) - 1
        if i < 0:
            raise DemGraphError(f"no live map was saved at or before {t_s:.3f} s (the first is at {times[0]:.3f} s)")
        x, y = ds["x"].values, ds["y"].values
        r = float(ds.attrs["resolution_m"])
        at = ds.isel(time=i)
        layers = {name: at[name].values.astype(np.float32) for name in json.loads(ds.attrs["layers"])}
        xw, yw, zw, yaw = (float(at[name].values) for name in _POSE_VARS)
    geometry = GridGeometry(float(x[0] - r / 2), float(y[0] + r / 2), r, len(y), len(x))
    if "age_s" in layers:
        layers["last_update_s"] = (float(times[i]) - layers["age_s"]).astype(np.float32)
    return Dem(geometry, layers, frame="local", meta={"t_s": float(times[i]), "T_world_local": heading_frame([xw, yw, zw], yaw)})


__all__ = ["LiveMapWriter", "SAVED_LAYERS", "live_map_at", "read_live_maps", "write_live_maps"]
