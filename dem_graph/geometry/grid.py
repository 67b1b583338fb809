"""Regular north-up grids in world metres, and elevation grids on them.

Row 0 is the northern-most row (largest y), column 0 the western-most (smallest x), as in a
GeoTIFF. Cell ``(row, col)`` has its centre at
``x = x_min_m + (col + 0.5) * resolution_m`` and ``y = y_max_m - (row + 0.5) * resolution_m``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dem_graph.errors import DemGraphError


@dataclass(frozen=True)
class GridGeometry:
    x_min_m: float
    y_max_m: float
    resolution_m: float
    n_rows: int
    n_cols: int

    def __post_init__(self):
        if not (self.resolution_m > 0 and self.n_rows > 0 and self.n_cols > 0):
            raise DemGraphError(f"invalid grid geometry {self}")

    @classmethod
    def covering(cls, x_min_m: float, y_min_m: float, x_max_m: float, y_max_m: float, resolution_m: float) -> GridGeometry:
        """The smallest grid with cells of ``resolution_m`` whose extent covers the given box."""
        n_cols = max(1, int(np.ceil((x_max_m - x_min_m) / resolution_m)))
        n_rows = max(1, int(np.ceil((y_max_m - y_min_m) / resolution_m)))
        return cls(float(x_min_m), float(y_min_m + n_rows * resolution_m), float(resolution_m), n_rows, n_cols)

    @property
    def shape(self) -> tuple[int, int]:
        return (self.n_rows, self.n_cols)

    @property
    def x_max_m(self) -> float:
        return self.x_min_m + self.n_cols * self.resolution_m

    @property
    def y_min_m(self) -> float:
        return self.y_max_m - self.n_rows * self.resolution_m

    def cell_center_x_m(self) -> np.ndarray:
        return self.x_min_m + (np.arange(self.n_cols) + 0.5) * self.resolution_m

    def cell_center_y_m(self) -> np.ndarray:
        return self.y_max_m - (np.arange(self.n_rows) + 0.5) * self.resolution_m

    def cell_centers_xy(self) -> tuple[np.ndarray, np.ndarray]:
        """(n_rows, n_cols) arrays of cell-centre x and y."""
        return np.meshgrid(self.cell_center_x_m(), self.cell_center_y_m())

    def fractional_index(self, x_m, y_m) -> tuple[np.ndarray, np.ndarray]:
        """Continuous (row, col) of world points, cell centres at integers."""
        col = (np.asarray(x_m, dtype=float) - self.x_min_m) / self.resolution_m - 0.5
        row = (self.y_max_m - np.asarray(y_m, dtype=float)) / self.resolution_m - 0.5
        return row, col

    def cell_index(self, x_m, y_m) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Integer (row, col) of the cells holding the points, and a mask of points inside the grid."""
        col_f = np.asarray(x_m, dtype=float) - self.x_min_m  # a new array: the in-place steps below are safe
        col_f /= self.resolution_m
        col_f = np.floor(col_f, out=col_f if col_f.ndim else None)
        row_f = self.y_max_m - np.asarray(y_m, dtype=float)
        row_f /= self.resolution_m
        row_f = np.floor(row_f, out=row_f if row_f.ndim else None)
        with np.errstate(invalid="ignore"):  # NaN coordinates: outside, whatever their integer
            inside = (row_f >= 0) & (row_f < self.n_rows) & (col_f >= 0) & (col_f < self.n_cols)
            return row_f.astype(np.int64), col_f.astype(np.int64), inside

    def affine(self):
        """The GeoTIFF geotransform as an ``affine.Affine`` (north-up, pixel corners)."""
        from affine import Affine

        return Affine(self.resolution_m, 0.0, self.x_min_m, 0.0, -self.resolution_m, self.y_max_m)


@dataclass(frozen=True)
class ElevationGrid:
    """Heights ``z`` (metres, world frame) on a :class:`GridGeometry`; NaN where unknown.

    Heights are samples at cell centres. Between them :meth:`height_at` interpolates over the same
    two triangles per cell that :meth:`triangle_mesh` builds, so a ray cast against the mesh and a
    height query agree exactly.
    """

    geometry: GridGeometry
    z_m: np.ndarray

    def __post_init__(self):
        z = np.asarray(self.z_m)
        object.__setattr__(self, "z_m", z)
        if z.shape != self.geometry.shape:
            raise DemGraphError(f"elevation array shape {z.shape} does not match grid shape {self.geometry.shape}")

    def height_at(self, x_m, y_m) -> np.ndarray:
        """Height of the triangulated surface at world (x, y); NaN outside the grid's centre lattice."""
        g = self.geometry
        row_f, col_f = g.fractional_index(x_m, y_m)
        row_f, col_f = np.asarray(row_f, dtype=float), np.asarray(col_f, dtype=float)
        inside = (row_f >= 0) & (row_f <= g.n_rows - 1) & (col_f >= 0) & (col_f <= g.n_cols - 1)
        r0 = np.clip(np.floor(row_f), 0, max(g.n_rows - 2, 0)).astype(np.int64)
        c0 = np.clip(np.floor(col_f), 0, max(g.n_cols - 2, 0)).astype(np.int64)
        r1 = np.minimum(r0 + 1, g.n_rows - 1)
        c1 = np.minimum(c0 + 1, g.n_cols - 1)
        fr = np.clip(row_f - r0, 0.0, 1.0)
        fc = np.clip(col_f - c0, 0.0, 1.0)
        z = self.z_m
        z00, z01, z10, z11 = z[r0, c0], z[r0, c1], z[r1, c0], z[r1, c1]
        # cells are split along the (r0,c1)-(r1,c0) diagonal: triangle A (r0,c0),(r0,c1),(r1,c0) when fr + fc <= 1
        lower = fr + fc <= 1.0
        h_a = z00 + fc * (z01 - z00) + fr * (z10 - z00)
        h_b = z11 + (1.0 - fc) * (z10 - z11) + (1.0 - fr) * (z01 - z11)
        h = np.where(lower, h_a, h_b)
        return np.where(inside, h, np.nan)

    def triangle_mesh_arrays(self) -> tuple[np.ndarray, np.ndarray]:
        """Vertices (N,3) float32 and triangle indices (M,3) uint32 of the surface through the cell centres."""
        g = self.geometry
        X, Y = g.cell_centers_xy()
        vertices = np.stack([X.ravel(), Y.ravel(), np.asarray(self.z_m, dtype=float).ravel()], axis=1).astype(np.float32)
        i = (np.arange(g.n_rows - 1)[:, None] * g.n_cols + np.arange(g.n_cols - 1)[None, :]).ravel()
        # counter-clockwise seen from above (+z): normals point up. Row increases southwards (-y).
        tri_a = np.stack([i, i + g.n_cols, i + 1], axis=1)
        tri_b = np.stack([i + 1, i + g.n_cols, i + g.n_cols + 1], axis=1)
        return vertices, np.concatenate([tri_a, tri_b]).astype(np.uint32)
