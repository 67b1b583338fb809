"""The two views of the DEM the users ask for.

- The global map: every measurement of the run fused on one north-up world grid.
- The local map at a time ``t``: what was measured up to ``t``, in the vehicle's local frame at
  ``t``, over the focus area the guidance needs at the vehicle's speed then
  (:class:`~dem_graph.frontend.focus.FocusArea`).

The local frame has its origin at the body, x along the body's heading and z up (the body frame
with its roll and pitch taken out). Heights must be measured along gravity for slopes and steps to
mean anything; on a tilted vehicle the body's own z is not vertical. Local heights are relative to
the body origin's height.
"""

from __future__ import annotations

import numpy as np

from dem_graph.dem.fusion import FusionConfig, covering_geometry, fuse
from dem_graph.dem.layers import Dem
from dem_graph.dem.returns import GroundReturns, PoseTrack
from dem_graph.dem.traversability import add_traversability
from dem_graph.geometry.grid import GridGeometry


def global_dem(returns: GroundReturns, config: FusionConfig | None = None, geometry: GridGeometry | None = None, traversability_window: int = 3) -> Dem:
    """Fuse every measurement on a world grid (by default the one covering them all), with traversability."""
    config = config or FusionConfig()
    geometry = geometry or covering_geometry(returns, config)
    return add_traversability(fuse(returns, geometry, config), traversability_window)


def heading_frame(position_m, yaw_rad: float) -> np.ndarray:
    """``T_world_local`` of a heading frame: origin at ``position_m``, x at ``yaw_rad`` from the
    world's x, z up."""
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    out = np.eye(4)
    out[:3, :3] = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
    out[:3, 3] = position_m
    return out


def local_frame(T_world_body: np.ndarray) -> np.ndarray:
    """``T_world_local``: at the body's position, x along its heading, z up."""
    T = np.asarray(T_world_body, dtype=float)
    forward = T[:3, 0]
    return heading_frame(T[:3, 3], np.arctan2(forward[1], forward[0]))


def local_to_world_xy(T_world_local: np.ndarray, x_local_m: np.ndarray, y_local_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World (x, y) of points at (x, y) in a heading frame (any shape)."""
    T = T_world_local
    return T[0, 3] + T[0, 0] * x_local_m + T[0, 1] * y_local_m, T[1, 3] + T[1, 0] * x_local_m + T[1, 1] * y_local_m


def speed_at(poses: PoseTrack, t_s: float, span_s: float = 0.5) -> float:
    """Mean speed over the ``span_s`` before ``t_s`` (or after it, at the start of the track), m/s."""
    t0 = max(poses.t_s[0], t_s - span_s)
    t1 = min(poses.t_s[-1], max(t_s, t0 + span_s))
    if t1 <= t0:
        return float("nan")
    p = poses.trajectory.at(np.array([t0, t1]))[:, :3, 3]
    return float(np.linalg.norm(p[1] - p[0]) / (t1 - t0))


def to_local(returns: GroundReturns, T_world_local: np.ndarray) -> GroundReturns:
    """``returns`` in the local frame (a rotation about z: heights and their variances keep their meaning)."""
    R, t = T_world_local[:3, :3], T_world_local[:3, 3]
    return GroundReturns((returns.xyz_m - t) @ R, returns.var_z_m2, returns.t_s, returns.source)


def local_dem(
    returns: GroundReturns,
    poses: PoseTrack,
    t_s: float,
    x_range_m: tuple[float, float],
    half_width_m: float,
    config: FusionConfig | None = None,
    history_s: float | None = None,
    traversability_window: int | None = 3,
) -> Dem:
    """The local DEM at ``t_s`` over ``x_range_m`` ahead and ``half_width_m`` to each side (local frame).

    Only measurements taken at or before ``t_s`` are fused (within ``history_s`` of it, when given,
    which bounds the work on a long run). ``traversability_window`` None: elevation layers only.
    """
    config = config or FusionConfig()
    T_world_local = local_frame(poses.at(np.array([t_s]))[0][0])
    t = returns.t_s
    known = t <= t_s
    if history_s is not None:
        known &= t >= t_s - history_s
    recent = returns.select(known)
    # a cheap cut in the world frame first: the circle holding the rectangle
    reach = np.hypot(max(abs(x_range_m[0]), abs(x_range_m[1])), half_width_m) + config.resolution_m
    near = np.sum((recent.xyz_m[:, :2] - T_world_local[:2, 3]) ** 2, axis=1) <= reach * reach
    local = to_local(recent.select(near), T_world_local)
    geometry = GridGeometry.covering(x_range_m[0], -half_width_m, x_range_m[1], half_width_m, config.resolution_m)
    dem = fuse(local, geometry, config)
    if traversability_window is not None:
        add_traversability(dem, traversability_window)
    dem.frame = "local"
    dem.meta = {"t_s": float(t_s), "T_world_local": T_world_local}
    return dem


__all__ = ["global_dem", "heading_frame", "local_dem", "local_frame", "local_to_world_xy", "speed_at", "to_local"]
