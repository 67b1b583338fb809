"""Incremental fusion: an elevation grid that takes ground measurements as they come and can take
them back, for the live map (:mod:`dem_graph.dem.live_map`).

Each cell keeps information sums over the measurements it holds,

    W = sum(1 / var_i),   WZ = sum(z_i / var_i),   n = number of measurements,

so its height is ``WZ / W`` and its variance ``1 / W``: the same inverse-variance weighted mean as
the batch fusion (:func:`~dem_graph.dem.fusion.fuse`), and adding or removing a measurement is one
addition or subtraction. A cell whose last measurement is removed is reset to exact zeros (no
rounding residue is left behind).

**The gate, one batch at a time.** Measurements come in batches (one laser scan, or the map points
of one frame). Every measurement of a batch is tested against its cell as it stood *before the
batch*: with ``n >= gate_min_count`` there, it is kept only if

    (z_i - h_cell)^2 <= gate_sigma^2 (var_i + var_cell + gate_floor_m^2)

(the batch fusion's gate, :mod:`dem_graph.dem.fusion`); a cell with fewer measurements takes every
measurement of the batch. The decision is made once and kept with the measurement: removing it
later takes back exactly what it added (a rejected one only leaves the cell's ``outliers`` count),
and a revision re-places it as a new measurement, gated again. Unlike the batch fusion's median
gate, this depends on the order of the batches: a cell whose first measurements are outliers
keeps them. What the map holds is always exactly the weighted mean of its kept measurements (the
batch fusion of them with the gate off), which the tests check to 1e-9.

**Memory.** Cells live in square tiles of ``tile_cells`` cells a side, made where a measurement
first lands: the grid follows the vehicle without ever being copied, and its memory grows with the
area mapped (48 bytes a cell), not with time. Every tile is part of the global map, which
:meth:`IncrementalDem.to_dem` turns into a :class:`~dem_graph.dem.layers.Dem` at any time.

``last_update_s`` is the time of the latest measurement a cell took; a removal does not take it back.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dem_graph.dem.fusion import FusionConfig
from dem_graph.dem.layers import Dem
from dem_graph.dem.returns import GroundReturns, ReturnSource
from dem_graph.errors import DemGraphError
from dem_graph.geometry.grid import GridGeometry

INCREMENTAL_LAYERS = ("elevation", "variance", "count", "laser_count", "outliers", "last_update_s")
_SUMS = ("w", "wz", "n", "n_laser", "n_out", "t_last")  # a tile's arrays, in this order


@dataclass(frozen=True)
class Placed:
    """Measurements as a batch put them in the grid: what it takes to remove them exactly."""

    ix: np.ndarray  # (N,) int64 global cell column, floor(x / resolution)
    iy: np.ndarray  # (N,) int64 global cell row, floor(y / resolution) (northwards)
    w: np.ndarray  # (N,) 1 / var
    wz: np.ndarray  # (N,) z / var
    laser: np.ndarray  # (N,) bool: a laser return (else a map point)
    kept: np.ndarray  # (N,) bool: through the gate, in the sums (else counted as an outlier)

    def __len__(self) -> int:
        return len(self.ix)

    @classmethod
    def empty(cls) -> Placed:
        z = np.zeros(0)
        i = np.zeros(0, dtype=np.int64)
        b = np.zeros(0, dtype=bool)
        return cls(i, i, z, z, b, b)


class IncrementalDem:
    """The global map as per-cell information sums in tiles (see the module)."""

    def __init__(self, config: FusionConfig | None = None, tile_cells: int = 32, gate_min_count: int = 3):
        if tile_cells < 1:
            raise DemGraphError(f"tile_cells must be at least 1, got {tile_cells}")
        self.config = config or FusionConfig()
        self.resolution_m = self.config.resolution_m
        self.tile_cells = int(tile_cells)
        self.gate_min_count = int(gate_min_count)
        self._tiles: dict[tuple[int, int], np.ndarray] = {}  # (tx, ty) -> (6, tile_cells**2) float64: _SUMS
        self.n_kept = 0  # measurements in the sums now
        self.n_rejected = 0  # measurements held as outliers now

    # --- cells and tiles ---------------------------------------------------------------------
    @property
    def n_tiles(self) -> int:
        return len(self._tiles)

    @property
    def nbytes(self) -> int:
        return sum(t.nbytes for t in self._tiles.values())

    def cell_of(self, x_m: np.ndarray, y_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Global integer cell (ix, iy) of world points."""
        r = self.resolution_m
        return np.floor(np.asarray(x_m, dtype=float) / r).astype(np.int64), np.floor(np.asarray(y_m, dtype=float) / r).astype(np.int64)

    def _groups(self, ix: np.ndarray, iy: np.ndarray):
        """(tile key, index of the cells in it, their slot in the tile) for each tile the cells touch."""
        T = self.tile_cells
        tx, ty = ix // T, iy // T
        slot = (iy - ty * T) * T + (ix - tx * T)
        if len(ix) == 0:
            return
        key = tx * (1 << 32) + (ty & 0xFFFFFFFF)
        if np.all(key == key[0]):  # the usual case: one scan in one tile
            yield (int(tx[0]), int(ty[0])), slice(None), slot
            return
        order = np.argsort(key, kind="stable")
        k = key[order]
        starts = np.flatnonzero(np.r_[True, k[1:] != k[:-1]])
        ends = np.r_[starts[1:], len(k)]
        for s, e in zip(starts, ends, strict=True):
            idx = order[s:e]
            yield (int(tx[idx[0]]), int(ty[idx[0]])), idx, slot[idx]

    def _tile(self, key: tuple[int, int], create: bool) -> np.ndarray | None:
        tile = self._tiles.get(key)
        if tile is None and create:
            tile = np.zeros((len(_SUMS), self.tile_cells**2))
            tile[5] = -np.inf
            self._tiles[key] = tile
        return tile

    # --- adding and removing -----------------------------------------------------------------
    def add(self, returns: GroundReturns) -> Placed:
        """Fuse one batch of measurements (gated against the cells as they stood before it); the
        returned :class:`Placed` takes them back with :meth:`remove`. Non-finite measurements are
        left out (they are not in the returned record either)."""
        xyz = np.asarray(returns.xyz_m, dtype=float).reshape(-1, 3)
        var = np.asarray(returns.var_z_m2, dtype=float)
        t = np.asarray(returns.t_s, dtype=float)
        ok = np.isfinite(xyz[:, 0] + xyz[:, 1] + xyz[:, 2] + var + t) & (var >= 0)
        if not np.all(ok):
            xyz, var, t = xyz[ok], var[ok], t[ok]
            laser = np.asarray(returns.source)[ok] == ReturnSource.LASER_RETURN
        else:
            laser = np.asarray(returns.source) == ReturnSource.LASER_RETURN
        if len(xyz) == 0:
            return Placed.empty()
        c = self.config
        var = np.maximum(var, c.min_variance_m2)
        w = 1.0 / var
        z = xyz[:, 2]
        wz = w * z
        ix, iy = self.cell_of(xyz[:, 0], xyz[:, 1])
        kept = np.ones(len(z), dtype=bool)
        size = self.tile_cells**2
        for key, idx, slot in self._groups(ix, iy):
            tile = self._tile(key, create=True)
            W, N = tile[0, slot], tile[2, slot]
            gated = N >= self.gate_min_count
            if np.any(gated):
                with np.errstate(invalid="ignore", divide="ignore"):
                    h = tile[1, slot] / W
                    d = z[idx] - h
                    ok_gate = d * d <= c.gate_sigma**2 * (var[idx] + 1.0 / W + c.gate_floor_m**2)
                k = ~gated | ok_gate
                kept[idx] = k
            else:
                k = np.ones(len(slot), dtype=bool)
            kw = k.astype(float)
            tile[0] += np.bincount(slot, weights=w[idx] * kw, minlength=size)
            tile[1] += np.bincount(slot, weights=wz[idx] * kw, minlength=size)
            tile[2] += np.bincount(slot, weights=kw, minlength=size)
            tile[3] += np.bincount(slot, weights=kw * laser[idx], minlength=size)
            tile[4] += np.bincount(slot, weights=1.0 - kw, minlength=size)
            np.maximum.at(tile[5], slot[k], t[idx][k])
        n_kept = int(kept.sum())
        self.n_kept += n_kept
        self.n_rejected += len(kept) - n_kept
        return Placed(ix, iy, w, wz, laser, kept)

    def remove(self, placed: Placed) -> None:
        """Take back a batch :meth:`add` placed (exactly what it added)."""
        if len(placed) == 0:
            return
        size = self.tile_cells**2
        for key, idx, slot in self._groups(placed.ix, placed.iy):
            tile = self._tile(key, create=False)
            if tile is None:
                raise DemGraphError(f"removing measurements from tile {key}, which holds none")
            kw = placed.kept[idx].astype(float)
            tile[0] -= np.bincount(slot, weights=placed.w[idx] * kw, minlength=size)
            tile[1] -= np.bincount(slot, weights=placed.wz[idx] * kw, minlength=size)
            tile[2] -= np.bincount(slot, weights=kw, minlength=size)
            tile[3] -= np.bincount(slot, weights=kw * placed.laser[idx], minlength=size)
            tile[4] -= np.bincount(slot, weights=1.0 - kw, minlength=size)
            emptied = tile[2] <= 0.5  # counts are whole numbers: no measurement left, whatever the rounding
            tile[0][emptied] = 0.0
            tile[1][emptied] = 0.0
            tile[2][emptied] = 0.0
            tile[3][emptied] = 0.0
        n_kept = int(placed.kept.sum())
        self.n_kept -= n_kept
        self.n_rejected -= len(placed) - n_kept

    # --- reading -----------------------------------------------------------------------------
    def _layers_from_sums(self, s: np.ndarray) -> dict[str, np.ndarray]:
        """Layers from sums (6, ...) (float64)."""
        has = s[2] > 0.5
        with np.errstate(invalid="ignore", divide="ignore"):
            elevation = np.where(has, s[1] / s[0], np.nan)
            variance = np.where(has, 1.0 / s[0], np.nan)
        return {
            "elevation": elevation,
            "variance": variance,
            "count": s[2].copy(),
            "laser_count": s[3].copy(),
            "outliers": s[4].copy(),
            "last_update_s": np.where(np.isfinite(s[5]) & has, s[5], np.nan),
        }

    def sample(self, x_m: np.ndarray, y_m: np.ndarray) -> dict[str, np.ndarray]:
        """The layers (:data:`INCREMENTAL_LAYERS`, float64) of the cells holding world points
        ``(x_m, y_m)`` (any shape): NaN heights and zero counts where no measurement is."""
        x = np.asarray(x_m, dtype=float)
        shape = x.shape
        ix, iy = self.cell_of(x.ravel(), np.asarray(y_m, dtype=float).ravel())
        sums = np.zeros((len(_SUMS), len(ix)))
        sums[5] = -np.inf
        for key, idx, slot in self._groups(ix, iy):
            tile = self._tiles.get(key)
            if tile is not None:
                sums[:, idx] = tile[:, slot]
        return {k: v.reshape(shape) for k, v in self._layers_from_sums(sums).items()}

    def covering_geometry(self, margin_cells: int = 0) -> GridGeometry:
        """The north-up grid over every tile with a measurement, cell edges on multiples of the resolution."""
        keys = [k for k, tile in self._tiles.items() if np.any(tile[2] > 0.5) or np.any(tile[4] > 0.5)]
        if not keys:
            raise DemGraphError("the live map holds no measurement yet: nothing to save")
        tx = np.array([k[0] for k in keys])
        ty = np.array([k[1] for k in keys])
        T, r = self.tile_cells, self.resolution_m
        x0, x1 = (tx.min() * T - margin_cells) * r, ((tx.max() + 1) * T + margin_cells) * r
        y0, y1 = (ty.min() * T - margin_cells) * r, ((ty.max() + 1) * T + margin_cells) * r
        n_cols, n_rows = int(round((x1 - x0) / r)), int(round((y1 - y0) / r))
        return GridGeometry(float(x0), float(y1), r, n_rows, n_cols)

    def to_dem(self, geometry: GridGeometry | None = None) -> Dem:
        """The global map as a :class:`Dem` (float32 layers) on ``geometry`` (default: covering every tile)."""
        geometry = geometry or self.covering_geometry()
        X, Y = geometry.cell_centers_xy()
        layers = self.sample(X, Y)
        dem = Dem(geometry, {k: v.astype(np.float32) for k, v in layers.items()}, n_measurements=self.n_kept + self.n_rejected, n_used=self.n_kept)
        return dem


__all__ = ["INCREMENTAL_LAYERS", "IncrementalDem", "Placed"]
