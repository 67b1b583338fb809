"""A DEM: named per-cell layers on a north-up grid (its files: :mod:`dem_graph.io.dem_files`).

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

import numpy as np

from dem_graph.geometry.grid import ElevationGrid, GridGeometry

FUSED_LAYERS = ("elevation", "variance", "count", "min", "max", "last_update_s", "outliers", "laser_count")


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


__all__ = ["Dem", "FUSED_LAYERS"]
