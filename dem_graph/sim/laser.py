"""Laser scans by ray casting the terrain, with range noise and no-returns."""

from __future__ import annotations

import numpy as np

from dem_graph.geometry.rig import LaserSpec
from dem_graph.sim.raycast import TerrainScene


def cast_scan(scene: TerrainScene, T_world_laser: np.ndarray, laser: LaserSpec, rng: np.random.Generator | None) -> np.ndarray:
    """Ranges (float32, metres) of every beam from pose ``T_world_laser``; NaN where nothing is hit
    within the range limits. Gaussian range noise of ``laser.range_sigma_m`` when ``rng`` is given."""
    dirs_world = laser.beam_directions() @ T_world_laser[:3, :3].T
    hits = scene.cast(np.broadcast_to(T_world_laser[:3, 3], dirs_world.shape), dirs_world)
    ranges = hits.t_hit_m.copy()
    if rng is not None and laser.range_sigma_m > 0:
        ranges += laser.range_sigma_m * rng.standard_normal(len(ranges))
    ranges[~laser.valid_ranges(ranges)] = np.nan
    return ranges.astype(np.float32)
