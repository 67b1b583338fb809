"""A DEM: named per-cell layers on a north-up grid, and its ``.npz`` form.

Layers (float32, NaN where a cell has no data, counts 0):

- ``elevation``: fused height, metres (world z, or local z for a local map);
- ``variance``: its variance, m^2;
- ``count``: measurements fused into the cell, ``laser_count`` of which laser returns (the others
  are map points); ``outliers``: measurements the gate rejected;
- ``min``, ``max``: lowest and highest fused measurement, metres;
- ``last_update_s``: time of the latest fused measurement, seconds;
- traversability, when computed (:mod:`dem_graph.dem.traversability`): ``slope_deg``,
  ``step_height_m``, ``roughness_m``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dem_graph.errors import DatasetError
from dem_graph.geometry.grid import ElevationGrid, GridGeometry

FUSED_LAYERS = ("elevation", "variance", "count", "min", "max", "last_update_s", "outliers", "laser_count")
_GEOMETRY_KEYS = ("x_min_m", "y_max_m", "resolution_m", "n_rows", "n_cols")


@dataclass
class Dem:
    geometry: GridGeometry
    layers: dict[str, np.ndarray]
    n_measurements: int = 0  # measurements given to the fusion
    n_used: int = 0  # of which fused into a cell (inside the grid, finite, through the gate)
    frame: str = "world"  # "world", or "local" for a map in the vehicle's heading frame
    meta: dict = field(default_factory=dict)

    @classmethod
    def empty(cls, geometry: GridGeometry, n_measurements: int = 0) -> Dem:
        layers = {name: np.full(geometry.shape, 0.0 if name in ("count", "outliers", "laser_count") else np.nan, dtype=np.float32) for name in FUSED_LAYERS}
        return cls(geometry, layers, n_measurements=n_measurements, n_used=0)

    @property
    def elevation(self) -> np.ndarray:
        return self.layers["elevation"]

    @property
    def variance(self) -> np.ndarray:
        return self.layers["variance"]

    @property
    def covered(self) -> np.ndarray:
        """Mask of cells with a fused height."""
        return np.isfinite(self.layers["elevation"])

    def elevation_grid(self) -> ElevationGrid:
        return ElevationGrid(self.geometry, self.layers["elevation"])

    def save_npz(self, path: str | Path) -> Path:
        """Every layer, the grid's geometry and the map's frame in one compressed ``.npz``."""
        path = Path(path)
        g = self.geometry
        arrays = {f"layer_{k}": v for k, v in self.layers.items()}
        arrays.update(
            x_min_m=g.x_min_m, y_max_m=g.y_max_m, resolution_m=g.resolution_m, n_rows=g.n_rows, n_cols=g.n_cols,
            frame=np.array(self.frame), n_measurements=self.n_measurements, n_used=self.n_used,
        )
        try:
            with path.open("wb") as fh:
                np.savez_compressed(fh, **arrays)
        except OSError as exc:
            raise DatasetError(path, f"cannot write ({exc.strerror or exc})") from None
        return path

    @classmethod
    def load_npz(cls, path: str | Path) -> Dem:
        path = Path(path)
        if not path.is_file():
            raise DatasetError(path, "file not found")
        try:
            with np.load(path, allow_pickle=False) as data:
                missing = [k for k in _GEOMETRY_KEYS if k not in data]
                if missing:
                    raise DatasetError(path, f"not a DEM file: no {', '.join(missing)}")
                g = GridGeometry(float(data["x_min_m"]), float(data["y_max_m"]), float(data["resolution_m"]), int(data["n_rows"]), int(data["n_cols"]))
                layers = {k[len("layer_"):]: np.asarray(data[k]) for k in data.files if k.startswith("layer_")}
                frame = str(data["frame"]) if "frame" in data else "world"
                n_meas = int(data["n_measurements"]) if "n_measurements" in data else 0
                n_used = int(data["n_used"]) if "n_used" in data else 0
        except (OSError, ValueError, EOFError) as exc:
            raise DatasetError(path, f"not a readable .npz file ({str(exc).splitlines()[0] if str(exc) else type(exc).__name__})") from None
        for name, a in layers.items():
            if a.shape != g.shape:
                raise DatasetError(path, f"layer {name!r} has shape {a.shape}, the grid is {g.shape}")
        return cls(g, layers, n_measurements=n_meas, n_used=n_used, frame=frame)


__all__ = ["Dem", "FUSED_LAYERS"]
