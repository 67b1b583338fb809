"""Seeded heightfields: natural relief along a driven path, and analytic surfaces for tests.

The heightfield (an :class:`ElevationGrid`) is the ground truth; the renderer and the laser
ray-cast its triangulation.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.ndimage import gaussian_filter
from scipy.spatial import cKDTree

from dem_graph.geometry.grid import ElevationGrid, GridGeometry
from dem_graph.sim.config import TerrainSpec
from dem_graph.sim.noise import fractal_noise, smooth_noise
from dem_graph.sim.vehicle import DrivenPath


@dataclass(frozen=True)
class Terrain:
    """The ground truth surface, and what else the texture needs to know about it."""

    elevation: ElevationGrid
    stone_cover: np.ndarray  # (rows, cols) in [0, 1]: how much of each cell is stone (for the texture)

    @property
    def geometry(self) -> GridGeometry:
        return self.elevation.geometry


def path_frame(path: DrivenPath, x_m: np.ndarray, y_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Arc length of the nearest path point and signed lateral offset (positive: left of the path)."""
    step = max(1, int(round(0.05 / float(path.s_m[1] - path.s_m[0]))))
    s, xy, heading = path.s_m[::step], path.xy_m[::step], path.heading_rad[::step]
    _, idx = cKDTree(xy).query(np.stack([x_m.ravel(), y_m.ravel()], axis=1), workers=-1)
    d = np.stack([x_m.ravel(), y_m.ravel()], axis=1) - xy[idx]
    lateral = -np.sin(heading[idx]) * d[:, 0] + np.cos(heading[idx]) * d[:, 1]
    return s[idx].reshape(x_m.shape), lateral.reshape(x_m.shape)


def _path_frame_on_grid(path: DrivenPath, geometry: GridGeometry, coarsening: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """:func:`path_frame` at every cell, computed on a grid ``coarsening`` times coarser and interpolated
    (both are smooth near the path, where ruts and ditch need them)."""
    coarse = GridGeometry(geometry.x_min_m, geometry.y_max_m, geometry.resolution_m * coarsening, -(-geometry.n_rows // coarsening) + 1, -(-geometry.n_cols // coarsening) + 1)
    Xc, Yc = coarse.cell_centers_xy()
    s_c, lat_c = path_frame(path, Xc, Yc)
    # fine cell centres in coarse fractional indices
    X, Y = geometry.cell_center_x_m(), geometry.cell_center_y_m()
    rows, cols = coarse.fractional_index(np.zeros_like(Y), Y)[0], coarse.fractional_index(X, np.zeros_like(X))[1]
    map_x = np.broadcast_to(cols.astype(np.float32)[None, :], geometry.shape)
    map_y = np.broadcast_to(rows.astype(np.float32)[:, None], geometry.shape)
    out = []
    for a in (s_c, lat_c):
        out.append(cv2.remap(a.astype(np.float32), np.ascontiguousarray(map_x), np.ascontiguousarray(map_y), cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).astype(np.float64))
    return out[0], out[1]


def _analytic_heights(spec: TerrainSpec, X: np.ndarray, Y: np.ndarray) -> np.ndarray:
    if spec.kind == "flat":
        return np.zeros_like(X)
    if spec.kind == "slope":
        a = np.radians(spec.slope_azimuth_deg)
        return spec.slope_percent / 100.0 * (np.cos(a) * X + np.sin(a) * Y)
    if spec.kind == "sinusoid":
        k = 2 * np.pi / spec.sinusoid_wavelength_m
        return spec.sinusoid_amplitude_m * np.sin(k * X) * np.cos(0.5 * k * Y)
    raise ValueError(spec.kind)


def _add_blobs(z: np.ndarray, geometry: GridGeometry, centers_xy, heights, radii, power: float, cover: np.ndarray | None = None):
    """Add rounded blobs ``h * (1 - (r/R)^2)^power`` in place (stones: power 0.5, mounds: power 2)."""
    res = geometry.resolution_m
    for (cx, cy), h, radius in zip(centers_xy, heights, radii):
        row_c, col_c = geometry.fractional_index(cx, cy)
        half = int(np.ceil(radius / res)) + 1
        r0, r1 = max(int(row_c) - half, 0), min(int(row_c) + half + 1, geometry.n_rows)
        c0, c1 = max(int(col_c) - half, 0), min(int(col_c) + half + 1, geometry.n_cols)
        if r0 >= r1 or c0 >= c1:
            continue
        rows = np.arange(r0, r1)[:, None]
        cols = np.arange(c0, c1)[None, :]
        dist2 = ((rows - row_c) ** 2 + (cols - col_c) ** 2) * res * res / (radius * radius)
        inside = np.clip(1.0 - dist2, 0.0, None)
        z[r0:r1, c0:c1] += h * inside**power
        if cover is not None:
            cover[r0:r1, c0:c1] = np.maximum(cover[r0:r1, c0:c1], (inside > 0).astype(np.float32))


def generate_terrain(spec: TerrainSpec, path: DrivenPath, rng: np.random.Generator) -> Terrain:
    """A heightfield covering the path plus ``spec.margin_m``, with the relief ``spec`` describes."""
    lo = path.xy_m.min(axis=0) - spec.margin_m
    hi = path.xy_m.max(axis=0) + spec.margin_m
    geometry = GridGeometry.covering(lo[0], lo[1], hi[0], hi[1], spec.resolution_m)
    X, Y = geometry.cell_centers_xy()
    cover = np.zeros(geometry.shape, dtype=np.float32)
    if spec.kind != "natural":
        z = _analytic_heights(spec, X, Y)
        return Terrain(ElevationGrid(geometry, z.astype(np.float32)), cover)

    res = spec.resolution_m
    z = spec.undulation_amplitude_m * fractal_noise(geometry.shape, res, list(spec.undulation_wavelengths_m), rng).astype(np.float64)
    a = np.radians(spec.slope_azimuth_deg)
    z += spec.slope_percent / 100.0 * (np.cos(a) * X + np.sin(a) * Y)
    z += spec.roughness_m * smooth_noise(geometry.shape, res, spec.roughness_wavelength_m, rng)

    s_near, lateral = _path_frame_on_grid(path, geometry)
    area_100m2 = (geometry.x_max_m - geometry.x_min_m) * (geometry.y_max_m - geometry.y_min_m) / 100.0

    # ruts: two grooves where the wheels run (the track is used by the vehicle every day)
    if spec.ruts_depth_m > 0:
        half_track = 0.55
        for side in (-1.0, 1.0):
            u = (lateral - side * half_track) / (spec.ruts_width_m / 2)
            z -= spec.ruts_depth_m * np.where(np.abs(u) < 1, np.cos(0.5 * np.pi * u) ** 2, 0.0)
    # a ditch beside part of the path: smooth U-shaped channel, fading in and out along the path
    if spec.ditch_depth_m > 0:
        u = (lateral - spec.ditch_offset_m) / (spec.ditch_width_m / 2)
        along = np.clip(np.minimum(s_near - 10.0, path.length_m - 10.0 - s_near) / 3.0, 0.0, 1.0)
        z -= spec.ditch_depth_m * along * np.where(np.abs(u) < 1, np.cos(0.5 * np.pi * u) ** 2, 0.0)

    # mounds
    n_bumps = rng.poisson(spec.bumps_per_100m2 * area_100m2)
    centers = rng.uniform([geometry.x_min_m, geometry.y_min_m], [geometry.x_max_m, geometry.y_max_m], size=(n_bumps, 2))
    _add_blobs(z, geometry, centers, rng.uniform(*spec.bump_height_m, n_bumps), rng.uniform(*spec.bump_radius_m, n_bumps), 2.0)

    # stones, rarer on the wheel corridor
    n_stones = rng.poisson(spec.stones_per_100m2 * area_100m2)
    centers = rng.uniform([geometry.x_min_m, geometry.y_min_m], [geometry.x_max_m, geometry.y_max_m], size=(n_stones, 2))
    _, lat_c = path_frame(path, centers[:, 0], centers[:, 1])
    keep = (np.abs(lat_c) > 1.2) | (rng.random(n_stones) < spec.stone_density_on_track)
    centers = centers[keep]
    heights = rng.uniform(*spec.stone_height_m, len(centers))
    radii = heights * rng.uniform(1.0, 1.8, len(centers))
    _add_blobs(z, geometry, centers, heights, radii, 0.6, cover)
    cover = gaussian_filter(cover, 0.5)
    return Terrain(ElevationGrid(geometry, z.astype(np.float32)), cover)


def contact_surface(elevation: ElevationGrid, tire_patch_m: float) -> ElevationGrid:
    """The terrain as a tyre feels it: smoothed over the contact patch."""
    sigma_cells = tire_patch_m / elevation.geometry.resolution_m
    return ElevationGrid(elevation.geometry, gaussian_filter(np.asarray(elevation.z_m, dtype=np.float64), sigma_cells, mode="nearest"))
