"""One ray-casting scene (open3d) holding the terrain and optional marker objects."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dem_graph.geometry.grid import ElevationGrid
from dem_graph.optional import import_open3d


@dataclass(frozen=True)
class Marker:
    """An object added to the scene (for example a sphere used to check projection), with a flat reflectance."""

    vertices: np.ndarray  # (N,3) world metres
    triangles: np.ndarray  # (M,3)
    albedo: float = 1.0


def sphere_marker(center_xyz_m, radius_m: float, albedo: float = 1.0, resolution: int = 24) -> Marker:
    o3d = import_open3d()
    mesh = o3d.geometry.TriangleMesh.create_sphere(radius=radius_m, resolution=resolution)
    vertices = np.asarray(mesh.vertices) + np.asarray(center_xyz_m, dtype=float)
    return Marker(vertices, np.asarray(mesh.triangles), albedo)


@dataclass(frozen=True)
class RayHits:
    t_hit_m: np.ndarray  # (N,) distance along the unit ray; inf where nothing is hit
    normals_world: np.ndarray  # (N,3) unit surface normals
    object_id: np.ndarray  # (N,) 0 terrain, k>=1 marker k-1, -1 nothing

    @property
    def hit(self) -> np.ndarray:
        return np.isfinite(self.t_hit_m)


class TerrainScene:
    """The terrain's triangulation plus markers, ready for ray casting."""

    def __init__(self, elevation: ElevationGrid, markers: tuple[Marker, ...] = ()):
        o3d = import_open3d()
        self._o3d = o3d
        self.scene = o3d.t.geometry.RaycastingScene()
        vertices, triangles = elevation.triangle_mesh_arrays()
        ids = [self._add(vertices, triangles)]
        for m in markers:
            ids.append(self._add(np.asarray(m.vertices, dtype=np.float32), np.asarray(m.triangles, dtype=np.uint32)))
        self.markers = tuple(markers)
        # open3d's geometry ids -> our object ids (0 terrain, 1.. markers)
        self._id_map = np.full(max(ids) + 2, -1, dtype=np.int64)
        for ours, theirs in enumerate(ids):
            self._id_map[theirs] = ours

    def _add(self, vertices: np.ndarray, triangles: np.ndarray) -> int:
        mesh = self._o3d.t.geometry.TriangleMesh()
        mesh.vertex.positions = self._o3d.core.Tensor(np.ascontiguousarray(vertices, dtype=np.float32))
        mesh.triangle.indices = self._o3d.core.Tensor(np.ascontiguousarray(triangles, dtype=np.uint32))
        return int(self.scene.add_triangles(mesh))

    def cast(self, origins_world: np.ndarray, directions_world: np.ndarray) -> RayHits:
        """Cast rays (unit directions) and return the first hit of each."""
        rays = np.empty((len(directions_world), 6), dtype=np.float32)
        rays[:, :3] = origins_world
        rays[:, 3:] = directions_world
        return self.cast_packed(rays)

    def cast_packed(self, rays: np.ndarray) -> RayHits:
        """Cast (N,6) float32 rays ``[origin, unit direction]`` (world frame)."""
        result = self.scene.cast_rays(self._o3d.core.Tensor.from_numpy(rays))
        t_hit = result["t_hit"].numpy()
        if self.markers:
            gid = result["geometry_ids"].numpy().astype(np.int64)
            object_id = np.where(np.isfinite(t_hit), self._id_map[np.clip(gid, 0, len(self._id_map) - 1)], -1)
        else:
            object_id = np.where(np.isfinite(t_hit), 0, -1)
        return RayHits(t_hit, result["primitive_normals"].numpy(), object_id)
