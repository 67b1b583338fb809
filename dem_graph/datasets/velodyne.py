"""A multi-beam Velodyne as a single-line laser, and the reference ground surface from all its beams.

KITTI stores each Velodyne HDL-64E revolution as float32 ``x, y, z, reflectance`` per point, in the
lidar frame (x forward, y left, z up), without the ring (laser) number. The points are stored ring
after ring, each ring swept once around starting and ending facing forward, with the azimuth
``atan2(y, x)`` increasing. So a ring ends where the azimuth taken in [0, 360) degrees falls back by
more than half a turn: :func:`split_rings` cuts the scan there. When that does not give the expected
number of rings (a scan stored otherwise), it falls back to the elevation angle
``atan2(z, hypot(x, y))``: each point goes to the ring whose elevation (from a scan that did split)
is nearest.

A ring is a cone of (nearly) constant elevation, not a plane. :class:`RingLaser` turns it into the
fixed beams :class:`~dem_graph.geometry.rig.DirectionBeams` can hold: azimuth bins of
``azimuth_step_deg`` across the camera's field of view, each beam's direction
``(cos el cos az, cos el sin az, sin el)`` with the ring's median elevation ``el``; a bin's range is
the 3-D distance of the ring's point nearest the bin's centre (NaN when none is within half a bin).

A revolution takes 0.1 s; at 13 m/s the vehicle moves 1.3 m meanwhile. Points are not corrected
for that motion (the odometry benchmark's scans are not either): they are used as if taken at the
frame's time. As the rings start and end facing forward, the two halves of the camera's field of
view may be swept up to a revolution apart: on a flat road that moves returns along the road, not
in height.

:func:`reference_surface` builds the ground truth terrain: every point of every scan placed with the
ground-truth poses, binned into cells; per cell the median of the points within ``band_m`` of the
lowest one, then cells more than ``max_above_ground_m`` above the 20th percentile of their
neighbourhood (cars, rails, vegetation) are dropped.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dem_graph.errors import DatasetError
from dem_graph.geometry.grid import ElevationGrid, GridGeometry
from dem_graph.geometry.rig import DirectionBeams
from dem_graph.geometry.se3 import transform_points

log = logging.getLogger(__name__)

VELODYNE_RINGS = 64
_POINT_BYTES = 16  # float32 x, y, z, reflectance


def read_velodyne_bin(path: str | Path) -> np.ndarray:
    """(N,4) float32 ``x, y, z, reflectance`` of one KITTI Velodyne scan (metres, lidar frame).

    Raises :class:`DatasetError` naming the file when it is missing or its size is not a whole
    number of points (a truncated file).
    """
    path = Path(path)
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise DatasetError(path, "Velodyne scan not found") from None
    except OSError as exc:
        raise DatasetError(path, f"cannot read the Velodyne scan ({exc.strerror or exc})") from None
    if len(data) % _POINT_BYTES:
        raise DatasetError(path, f"{len(data)} bytes is not a whole number of 16-byte points (float32 x, y, z, reflectance): truncated?")
    return np.frombuffer(data, dtype=np.float32).reshape(-1, 4)


def azimuth_deg(points: np.ndarray) -> np.ndarray:
    """Azimuth of lidar-frame points, degrees in (-180, 180], from +x towards +y."""
    return np.degrees(np.arctan2(points[:, 1], points[:, 0]))


def elevation_deg(points: np.ndarray) -> np.ndarray:
    """Elevation of lidar-frame points above the x-y plane, degrees."""
    return np.degrees(np.arctan2(points[:, 2], np.hypot(points[:, 0], points[:, 1])))


def split_by_azimuth(points: np.ndarray) -> np.ndarray:
    """Ring number of each point from the stored order: a new ring wherever the azimuth in [0, 360)
    falls back by more than 180 degrees."""
    a = np.mod(azimuth_deg(points), 360.0)
    starts = np.diff(a) < -180.0
    return np.concatenate([[0], np.cumsum(starts)]).astype(np.int64)


def split_rings(points: np.ndarray, ring_elevations_deg: np.ndarray | None = None, rings: int = VELODYNE_RINGS) -> tuple[np.ndarray, str]:
    """Ring number (0 = highest) of every point, and how it was found (``"azimuth"`` or ``"elevation"``).

    ``ring_elevations_deg`` (one per ring, from a scan that split by azimuth) is the fall-back's
    reference; without it a scan that does not split into ``rings`` rings is an error.
    """
    if len(points) == 0:
        return np.zeros(0, dtype=np.int64), "azimuth"
    ring = split_by_azimuth(points)
    if ring[-1] + 1 == rings:
        return ring, "azimuth"
    if ring_elevations_deg is None:
        raise RingSplitError(f"the scan splits into {ring[-1] + 1} rings by azimuth, not {rings}, and no reference elevations are known")
    el = elevation_deg(points)
    ref = np.asarray(ring_elevations_deg, dtype=float)
    return np.argmin(np.abs(el[:, None] - ref[None, :]), axis=1).astype(np.int64), "elevation"


class RingSplitError(ValueError):
    """A scan whose rings cannot be told apart (turned into a DatasetError naming the file)."""


def ring_elevations_deg(points: np.ndarray, ring: np.ndarray, rings: int = VELODYNE_RINGS) -> np.ndarray:
    """Median elevation of each ring, degrees (NaN for an empty ring)."""
    el = elevation_deg(points)
    out = np.full(rings, np.nan)
    for k in range(rings):
        sel = ring == k
        if sel.any():
            out[k] = np.median(el[sel])
    return out


@dataclass(frozen=True)
class RingLaser:
    """One ring of the Velodyne as fixed beams: ``ring``'s median elevation, azimuth bins across
    ``[-half_fov_deg, half_fov_deg]`` every ``azimuth_step_deg``."""

    ring: int
    elevation_deg: float
    half_fov_deg: float
    azimuth_step_deg: float

    @property
    def azimuths_deg(self) -> np.ndarray:
        n = int(np.floor(2.0 * self.half_fov_deg / self.azimuth_step_deg)) + 1
        return -self.half_fov_deg + self.azimuth_step_deg * np.arange(n)

    def beams(self) -> DirectionBeams:
        az, el = np.radians(self.azimuths_deg), np.radians(self.elevation_deg)
        d = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.full_like(az, np.sin(el))], axis=1)
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        return DirectionBeams(directions_xyz=[tuple(map(float, v)) for v in d])

    def ranges_m(self, points: np.ndarray, ring: np.ndarray) -> np.ndarray:
        """(B,) float32 ranges of the ring's points binned by azimuth; NaN where a bin holds none."""
        centres = self.azimuths_deg
        out = np.full(len(centres), np.nan, dtype=np.float32)
        p = points[ring == self.ring, :3].astype(float)
        if len(p) == 0:
            return out
        az = azimuth_deg(p)
        k = np.rint((az - centres[0]) / self.azimuth_step_deg).astype(np.int64)
        inside = (k >= 0) & (k < len(centres))
        k, p, az = k[inside], p[inside], az[inside]
        offset = np.abs(az - centres[k])
        keep = offset <= self.azimuth_step_deg / 2.0
        k, p, offset = k[keep], p[keep], offset[keep]
        order = np.lexsort((offset, k))  # per bin, the point nearest its centre first
        k, p = k[order], p[order]
        first = np.concatenate([[True], k[1:] != k[:-1]]) if len(k) else np.zeros(0, dtype=bool)
        out[k[first]] = np.linalg.norm(p[first], axis=1).astype(np.float32)
        return out


def choose_ring(points: np.ndarray, ring: np.ndarray, half_fov_deg: float, ground_distance_m: float, rings: int = VELODYNE_RINGS) -> int:
    """The ring whose returns inside the field of view lie, in median, nearest ``ground_distance_m``
    ahead (horizontal distance), among the rings pointing below the horizon."""
    az = azimuth_deg(points)
    el = elevation_deg(points)
    in_view = np.abs(az) <= half_fov_deg
    best, best_gap = -1, np.inf
    for k in range(rings):
        sel = in_view & (ring == k)
        if sel.sum() < 10 or np.median(el[sel]) >= 0:
            continue
        gap = abs(float(np.median(np.hypot(points[sel, 0], points[sel, 1]))) - ground_distance_m)
        if gap < best_gap:
            best, best_gap = k, gap
    if best < 0:
        raise RingSplitError("no ring points below the horizon inside the camera's field of view")
    return best


def reference_surface(
    clouds_world: list[np.ndarray],
    resolution_m: float = 0.2,
    band_m: float = 0.3,
    neighbourhood_m: float = 2.0,
    max_above_ground_m: float = 0.25,
    bounds_xy_m: tuple[float, float, float, float] | None = None,
) -> ElevationGrid:
    """The ground under the points of ``clouds_world`` ((N,3) world metres each) as an elevation grid.

    Per cell of ``resolution_m``: the median height of the points within ``band_m`` of the lowest (the
    median, not the lowest: with thousands of noisy returns per cell the lowest is an outlier).
    Then, per block of ``neighbourhood_m``, cells more than ``max_above_ground_m`` above the
    block's (and its eight neighbours') 20th percentile of cell heights are dropped (NaN): cars,
    rails and vegetation standing on the road. ``bounds_xy_m`` = (x_min, y_min, x_max, y_max) limits the
    grid (default: the points' extent).
    """
    pts = np.concatenate([np.asarray(c, dtype=float).reshape(-1, 3) for c in clouds_world]) if clouds_world else np.zeros((0, 3))
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    if bounds_xy_m is not None:
        x0, y0, x1, y1 = bounds_xy_m
        pts = pts[(pts[:, 0] >= x0) & (pts[:, 0] < x1) & (pts[:, 1] >= y0) & (pts[:, 1] < y1)]
    if len(pts) == 0:
        raise ValueError("no points to build a reference surface from")
    if bounds_xy_m is None:
        x0, y0 = pts[:, :2].min(axis=0)
        x1, y1 = pts[:, :2].max(axis=0) + 1e-6
    geometry = GridGeometry.covering(x0, y0, x1, y1, resolution_m)
    row, col, inside = geometry.cell_index(pts[:, 0], pts[:, 1])
    flat = (row[inside] * geometry.n_cols + col[inside]).astype(np.int64)
    z = pts[inside, 2]
    n_cells = geometry.n_rows * geometry.n_cols
    lowest = np.full(n_cells, np.inf)
    np.minimum.at(lowest, flat, z)
    near = z <= lowest[flat] + band_m
    flat, z = flat[near], z[near]
    order = np.lexsort((z, flat))  # by cell, then height
    flat, z = flat[order], z[order]
    start = np.flatnonzero(np.concatenate([[True], flat[1:] != flat[:-1]]))
    count = np.diff(np.concatenate([start, [len(flat)]]))
    lo, hi = start + (count - 1) // 2, start + count // 2  # the middle one or two of each cell
    height = np.full(n_cells, np.nan)
    height[flat[start]] = 0.5 * (z[lo] + z[hi])
    height = height.reshape(geometry.shape)
    # drop what stands above the local ground
    block = max(1, int(round(neighbourhood_m / resolution_m)))
    nbr, nbc = -(-geometry.n_rows // block), -(-geometry.n_cols // block)
    padded = np.full((nbr * block, nbc * block), np.nan)
    padded[: geometry.n_rows, : geometry.n_cols] = height
    blocks = padded.reshape(nbr, block, nbc, block).transpose(0, 2, 1, 3).reshape(nbr, nbc, block * block)
    ground = np.full((nbr, nbc), np.nan)
    for i in range(nbr):
        for j in range(nbc):
            vals = blocks[max(0, i - 1) : i + 2, max(0, j - 1) : j + 2].ravel()
            vals = vals[np.isfinite(vals)]
            if len(vals):
                ground[i, j] = np.percentile(vals, 20.0)
    ground_cells = np.repeat(np.repeat(ground, block, axis=0), block, axis=1)[: geometry.n_rows, : geometry.n_cols]
    with np.errstate(invalid="ignore"):
        height[height > ground_cells + max_above_ground_m] = np.nan
    return ElevationGrid(geometry, height.astype(np.float32))


def scan_in_world(points: np.ndarray, T_world_lidar: np.ndarray) -> np.ndarray:
    """(N,3) world positions of a scan's points."""
    return transform_points(T_world_lidar, points[:, :3].astype(float))


def _voxel_downsample(points: np.ndarray, voxel_m: float, range_min_m: float, range_max_m: float) -> np.ndarray:
    """One point per occupied voxel (the first stored), of the points between the two ranges."""
    p = np.asarray(points, dtype=float)[:, :3]
    r = np.linalg.norm(p, axis=1)
    p = p[(r > range_min_m) & (r < range_max_m)]
    _, first = np.unique(np.floor(p / voxel_m).astype(np.int64), axis=0, return_index=True)
    return p[np.sort(first)]


def register_scans(points_from: np.ndarray, points_to: np.ndarray, iterations: int = 30, voxel_m: float = 0.3, range_max_m: float = 40.0) -> tuple[np.ndarray, int]:
    """``T_to_from``, the pose of scan ``points_from``'s lidar in scan ``points_to``'s frame, by
    point-to-plane ICP from the identity (motion between consecutive scans), and the number of
    point pairs used in the last iteration. Points are thinned to one per ``voxel_m`` cube; only
    pairs on locally planar patches within 1 m (0.5 m after ten iterations) count."""
    from scipy.spatial import cKDTree

    from dem_graph.geometry.lie import so3_exp

    src = _voxel_downsample(points_from, voxel_m, 3.0, range_max_m)
    dst = _voxel_downsample(points_to, voxel_m, 3.0, range_max_m)
    tree = cKDTree(dst)
    _, neighbours = tree.query(dst, k=10)
    q = dst[neighbours] - dst[neighbours].mean(axis=1, keepdims=True)
    eigenvalues, eigenvectors = np.linalg.eigh(np.einsum("nki,nkj->nij", q, q))
    normal = eigenvectors[:, :, 0]
    planar = eigenvalues[:, 0] / (eigenvalues.sum(axis=1) + 1e-12) < 0.05
    T = np.eye(4)
    used = 0
    for it in range(iterations):
        moved = src @ T[:3, :3].T + T[:3, 3]
        distance, j = tree.query(moved)
        pair = (distance < (1.0 if it < 10 else 0.5)) & planar[j]
        used = int(pair.sum())
        if used < 6:
            break
        a, n = moved[pair], normal[j[pair]]
        residual = np.einsum("ni,ni->n", a - dst[j[pair]], n)
        J = np.hstack([np.cross(a, n), n])
        step = -np.linalg.solve(J.T @ J + 1e-6 * np.eye(6), J.T @ residual)
        dT = np.eye(4)
        dT[:3, :3] = so3_exp(step[:3])
        dT[:3, 3] = step[3:]
        T = dT @ T
    return T, used


__all__ = [
    "RingLaser",
    "VELODYNE_RINGS",
    "azimuth_deg",
    "choose_ring",
    "elevation_deg",
    "read_velodyne_bin",
    "reference_surface",
    "register_scans",
    "ring_elevations_deg",
    "scan_in_world",
    "split_by_azimuth",
    "split_rings",
]
