"""Saved live maps: the local maps the guidance had, every k-th frame, in one netCDF file.

``live_maps.nc`` (netCDF 3, written and read through xarray; any netCDF tool opens it) holds

- dimensions ``time`` (seconds, the frames' times), ``y`` (metres, to the left, first row the
  leftmost, as in a north-up grid) and ``x`` (metres, ahead of the body origin);
- one variable per layer, ``(time, y, x)`` float32: ``elevation`` (metres, relative to the body
  origin's height), ``variance``, ``count``, ``age_s`` and the traversability layers;
- per time, the heading frame in the world: ``x_world_m``, ``y_world_m``, ``z_world_m``, ``yaw_rad``.

While a run goes, :class:`LiveMapWriter` appends each saved map to a part file (nothing is held in
memory); :meth:`LiveMapWriter.close` turns it into the netCDF file at the end of a run or where a
run stopped, and removes it. A run with a run folder appends to ``RUN/live_maps.part``, beside the
``live_maps.nc`` it will become, so that a run killed outright (SIGKILL, the out-of-memory killer)
keeps every map saved until then (each is handed to the system as it is saved; only a crash of the
system itself can lose the last); a run without one (a notebook's) to a temporary file, removed
when the writer is closed or dropped.

A part file reads on its own. Its first line is a JSON header, padded with spaces to a multiple of
64 bytes: ``format`` (:data:`PART_FORMAT`), ``version`` (1), ``geometry`` (the
:class:`~dem_graph.geometry.grid.GridGeometry`'s fields) and ``layers`` (their names, in order).
Then one binary record per map, little-endian, written whole and flushed as the map is saved:
five float64 (``t_s``, then the pose ``x_world_m``, ``y_world_m``, ``z_world_m``, ``yaw_rad``) and
the layers as float32 ``(layer, row, col)``, C order. The header is written under another name and
renamed into place, so a part file always has a whole one; a kill in the middle of a record leaves
it cut short, and readers leave it out.

:func:`read_live_maps` and :func:`live_map_at` read ``live_maps.nc`` when it is there, and
otherwise the part file beside it (a run that did not end: killed, or still going), with a warning;
:func:`salvage_live_maps` turns a part file into the netCDF file.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import tempfile
import weakref
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dem_graph.dem.layers import Dem
from dem_graph.dem.views import heading_frame
from dem_graph.errors import DatasetError, DemGraphError, one_line
from dem_graph.geometry.grid import GridGeometry

log = logging.getLogger(__name__)

SAVED_LAYERS = ("elevation", "variance", "count", "age_s", "slope_deg", "step_height_m", "roughness_m")
_POSE_VARS = ("x_world_m", "y_world_m", "z_world_m", "yaw_rad")
NETCDF3_MAGIC = b"CDF"  # the first bytes of a netCDF 3 file (classic or 64-bit offset), the format written here
LIVE_MAPS_NC = "live_maps.nc"  # its name in a run folder
PART_SUFFIX = ".part"  # the part file's name: the netCDF file's, with this suffix (``live_maps.part``)
PART_FORMAT = "dem_graph live maps part"  # the header's ``format``
PART_VERSION = 1
_HEADER_ALIGN_BYTES = 64
_MAX_HEADER_BYTES = 1 << 16  # a header is a few hundred bytes: a first line longer than this is not one


def live_maps_part_path(path: str | Path) -> Path:
    """The part file of the netCDF file ``path`` (``RUN/live_maps.nc``: ``RUN/live_maps.part``)."""
    return Path(path).with_suffix(PART_SUFFIX)


def _record_dtype(n_layers: int, geometry: GridGeometry) -> np.dtype:
    """One map's record in a part file (see the module)."""
    return np.dtype([("t_s", "<f8"), ("pose", "<f8", (len(_POSE_VARS),)), ("maps", "<f4", (n_layers, geometry.n_rows, geometry.n_cols))])


def _header_bytes(geometry: GridGeometry, layers: tuple[str, ...]) -> bytes:
    """A part file's header line (see the module); floats written as repr, so they read back exactly."""
    header = {"format": PART_FORMAT, "version": PART_VERSION, "geometry": dataclasses.asdict(geometry), "layers": list(layers)}
    line = json.dumps(header).encode("utf-8")
    pad = -(len(line) + 1) % _HEADER_ALIGN_BYTES
    return line + b" " * pad + b"\n"


class LiveMapWriter:
    """Appends local maps of one geometry to a part file until :meth:`close` (see the module).

    ``path``: the netCDF file the maps will become (``RUN/live_maps.nc``); they are appended to its
    part file (``RUN/live_maps.part``), which outlives a run killed before :meth:`close`. None: a
    temporary file, removed when the writer is closed or dropped; :meth:`close` is then given the path."""

    def __init__(self, geometry: GridGeometry, layers: tuple[str, ...] = SAVED_LAYERS, path: str | Path | None = None):
        self.geometry = geometry
        self.layers = tuple(layers)
        self.path = None if path is None else Path(path)
        self._record = np.empty(1, _record_dtype(len(self.layers), geometry))
        header = _header_bytes(geometry, self.layers)
        if self.path is None:
            fd, raw = tempfile.mkstemp(prefix="dem_graph_live_maps_", suffix=PART_SUFFIX)
            self.part_path = Path(raw)
            self._file = os.fdopen(fd, "wb")
            self._cleanup = weakref.finalize(self, _release, self._file, self.part_path, True)  # a writer never closed leaves no file behind
            self._write(header)
        else:
            self.part_path = live_maps_part_path(self.path)
            new = self.part_path.with_name(f".{self.part_path.name}.new")
            try:
                new.write_bytes(header)
                os.replace(new, self.part_path)  # a part file always has its whole header
                self._file = self.part_path.open("ab")
            except OSError as exc:
                raise DatasetError(self.part_path, f"cannot write ({exc.strerror or exc})") from None
            self._cleanup = weakref.finalize(self, _release, self._file, self.part_path, False)  # kept: the maps of a run that did not end
        self._n = 0

    def __len__(self) -> int:
        return self._n

    def _write(self, data: bytes) -> None:
        try:
            self._file.write(data)
            self._file.flush()  # to the system as it is saved: a killed process loses none of it
        except OSError as exc:
            raise DatasetError(self.part_path, f"cannot write ({exc.strerror or exc})") from None

    def append(self, dem: Dem) -> None:
        """Append ``dem`` (a local map of the writer's grid, with ``meta['t_s']`` and ``meta['T_world_local']``)."""
        if dem.geometry != self.geometry:
            raise DemGraphError(f"a saved live map must have the writer's grid {self.geometry}, not {dem.geometry}")
        record = self._record
        for i, name in enumerate(self.layers):
            record["maps"][0, i] = dem.layers[name]
        T = dem.meta["T_world_local"]
        record["t_s"][0] = float(dem.meta["t_s"])
        record["pose"][0] = (T[0, 3], T[1, 3], T[2, 3], np.arctan2(T[1, 0], T[0, 0]))
        self._write(self._record.tobytes())  # one record, one write
        self._n += 1

    def close(self, path: str | Path | None = None) -> Path | None:
        """Write what was saved as the netCDF file ``path`` (default: the writer's), remove the part
        file, and return the path (None when no map was saved); the writer is done. If the netCDF
        file cannot be written, a run folder's part file is kept."""
        path = self.path if path is None else Path(path)
        if path is None:
            raise DemGraphError("a live-maps writer without a run folder is closed into a path: give one")
        self._file.close()
        try:
            return _finish(self.part_path, path)
        finally:
            self._cleanup()


def _release(file, part: Path, remove: bool) -> None:
    file.close()
    if remove:
        part.unlink(missing_ok=True)


@dataclass(frozen=True)
class _Part:
    """A part file as read: its header, its whole records (a read-only map of the file), and whether
    a record at its end was cut short (and left out)."""

    path: Path
    geometry: GridGeometry
    layers: tuple[str, ...]
    records: np.ndarray
    cut_short: bool


def _read_part(path: Path) -> _Part:
    """The part file ``path`` (see the module); :class:`DatasetError` naming it if it cannot be read."""
    try:
        with path.open("rb") as fh:
            head = fh.read(_MAX_HEADER_BYTES)
        size = path.stat().st_size
    except OSError as exc:
        raise DatasetError(path, f"cannot read ({exc.strerror or exc})") from None
    end = head.find(b"\n")
    if end < 0:
        raise DatasetError(path, "not a live-maps part file (it does not begin with its header line: damaged or replaced)")
    try:
        header = json.loads(head[:end])
    except ValueError as exc:
        raise DatasetError(path, f"damaged header (not JSON: {one_line(exc, 120)})") from None
    if not isinstance(header, dict) or header.get("format") != PART_FORMAT:
        raise DatasetError(path, f"not a live-maps part file (its header does not say format {PART_FORMAT!r})")
    if header.get("version") != PART_VERSION:
        raise DatasetError(path, f"a part file of version {header.get('version')!r}: this dem_graph reads version {PART_VERSION}")
    try:
        g = header["geometry"]
        geometry = GridGeometry(float(g["x_min_m"]), float(g["y_max_m"]), float(g["resolution_m"]), int(g["n_rows"]), int(g["n_cols"]))
        layers = tuple(header["layers"])
        if not layers or not all(isinstance(name, str) and name for name in layers) or len(set(layers)) < len(layers):
            raise ValueError(f"layers {header['layers']!r} are not distinct names")
    except (KeyError, TypeError, ValueError, DemGraphError) as exc:
        raise DatasetError(path, f"damaged header ({type(exc).__name__}: {one_line(exc, 160)})") from None
    dtype = _record_dtype(len(layers), geometry)
    n, rest = divmod(size - (end + 1), dtype.itemsize)
    try:
        records = np.memmap(path, dtype=dtype, mode="r", offset=end + 1, shape=(n,)) if n else np.zeros(0, dtype)
    except (OSError, ValueError) as exc:
        raise DatasetError(path, f"cannot read ({one_line(exc, 160)})") from None
    return _Part(path, geometry, layers, records, rest != 0)


def _finish(part_path: Path, path: Path) -> Path | None:
    """The part file's whole maps written as the netCDF file ``path``, then the part file removed
    (None, and the part file removed, when it holds no whole map)."""
    part = _read_part(part_path)
    if part.cut_short:
        log.warning("%s: a map cut short at its end (the run was stopped while writing it) is left out", part_path)
    r = part.records
    written = write_live_maps(path, r["t_s"], r["maps"], part.layers, part.geometry, r["pose"]) if len(r) else None
    del part, r  # the map of the file let go before the file is removed
    part_path.unlink(missing_ok=True)
    return written


def salvage_live_maps(path: str | Path) -> Path | None:
    """Turn the part file of ``path`` (``RUN/live_maps.nc``: ``RUN/live_maps.part``, from a run that
    did not end) into ``path``, and remove it: the maps it holds whole, a map cut short at its end
    left out (with a warning). Returns ``path``, or None if the part file held no whole map.
    :class:`DatasetError` naming the file if the part file is missing or cannot be read. Not for
    the part file of a run still going: its later maps would be lost."""
    path = Path(path)
    part = live_maps_part_path(path)
    if not part.is_file():
        raise DatasetError(part, "not found: no live maps to salvage (the run ended and wrote its netCDF file, or saved none)")
    return _finish(part, path)


def _dataset(times_s: np.ndarray, data: np.ndarray, layers: tuple[str, ...], geometry: GridGeometry, poses: np.ndarray):
    """``data`` (time, layer, rows, cols) as the ``xarray.Dataset`` ``live_maps.nc`` holds (see the module)."""
    import xarray as xr

    coords = {"time": ("time", np.asarray(times_s, dtype=float), {"units": "s"}), "y": ("y", geometry.cell_center_y_m(), {"units": "m"}), "x": ("x", geometry.cell_center_x_m(), {"units": "m"})}
    variables = {name: (("time", "y", "x"), data[:, i]) for i, name in enumerate(layers)}
    variables.update({name: ("time", poses[:, i]) for i, name in enumerate(_POSE_VARS)})
    return xr.Dataset(variables, coords=coords, attrs={"title": "dem_graph live local maps", "frame": "vehicle heading frame: x ahead, y left, z up; elevation relative to the body origin", "resolution_m": geometry.resolution_m, "layers": json.dumps(list(layers))})


def write_live_maps(path: str | Path, times_s: np.ndarray, data: np.ndarray, layers: tuple[str, ...], geometry: GridGeometry, poses: np.ndarray) -> Path:
    """``data`` (time, layer, rows, cols) as ``live_maps.nc`` (see the module), written under another
    name and renamed into place: a reader sees the whole file or none."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.part")
    try:
        _dataset(times_s, data, layers, geometry, poses).to_netcdf(tmp, engine="scipy")
        os.replace(tmp, path)
    except OSError as exc:
        raise DatasetError(path, f"cannot write ({exc.strerror or exc})") from None
    finally:
        tmp.unlink(missing_ok=True)  # (gone once renamed)
    return path


def _open_netcdf(path: Path):
    """``live_maps.nc``, opened lazily (an ``xarray.Dataset``: close it); :class:`DatasetError` naming the file if it cannot be read."""
    import xarray as xr

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


def _open_part(path: Path, copy: bool):
    """The part file's whole maps as the ``xarray.Dataset`` ``live_maps.nc`` would hold, with the one
    warning that they come from a run that did not end. ``copy``: in memory; otherwise over a
    read-only map of the file, so that only the maps used are read."""
    part = _read_part(path)
    n = len(part.records)
    if n == 0:
        raise DatasetError(path, "holds no whole live map: the run stopped before its first was written")
    cut = "; a map cut short at its end is left out" if part.cut_short else ""
    log.warning("%s: the run did not end (killed, or still going): its %d live maps come from the part file written as it went%s", path, n, cut)
    r = np.array(part.records) if copy else part.records
    return _dataset(r["t_s"], r["maps"], part.layers, part.geometry, r["pose"])


def _open(path: Path, copy: bool = False):
    """The saved live maps of ``path`` as an ``xarray.Dataset`` (close it): the netCDF file, opened
    lazily; a part file given as such; or, with no netCDF file, its part file beside it.
    :class:`DatasetError` naming the file if none can be read."""
    if path.suffix == PART_SUFFIX:
        return _open_part(path, copy)
    if path.is_file():
        return _open_netcdf(path)
    part = live_maps_part_path(path)
    if part.is_file():
        return _open_part(part, copy)
    raise DatasetError(path, "no saved live maps (the run saved none: live_map.save_every_n_frames 0, or an older run)")


def read_live_maps(path: str | Path):
    """The saved live maps of ``path`` (``live_maps.nc``, else its part file: see the module) as an
    ``xarray.Dataset`` in memory; :class:`DatasetError` naming the file if they cannot be read."""
    with _open(Path(path), copy=True) as ds:
        return ds.load()


def live_map_at(path: str | Path, t_s: float) -> Dem:
    """The saved live map of the latest time at or before ``t_s`` (``meta['t_s']`` says which), from
    ``path`` as :func:`read_live_maps` reads it; only that map is read."""
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


__all__ = ["LIVE_MAPS_NC", "LiveMapWriter", "PART_FORMAT", "SAVED_LAYERS", "live_map_at", "live_maps_part_path", "read_live_maps", "salvage_live_maps", "write_live_maps"]
