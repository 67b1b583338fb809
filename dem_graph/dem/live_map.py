"""The live map: laser scans fused as they arrive, moved when their poses are revised, and read as
the local DEM the guidance steers by.

A scan goes into the grid (:class:`~dem_graph.dem.incremental.IncrementalDem`) the moment it
arrives, every valid return of it, placed with the best pose known for its time (the caller's:
an extrapolation when no frame has reached that time yet). The scan stays in a revision log for
``window_s``: when the estimator revises poses (the next frame's pose, the smoother's window, the
graph process's results keyframes later), :meth:`LiveMap.revise` asks for the pose of every logged
scan and moves the returns of exactly the scans whose pose moved by more than the tolerance (out
of their old cells, into their new ones). Scans older than the window are frozen: the cost of a
revision is bounded by the window, not by the run.

The local map at a time is read from the grid over the focus area, in the vehicle's heading frame
(:func:`~dem_graph.dem.views.local_frame`): each local cell takes the world cell under its centre,
heights relative to the body origin, with each cell's age (seconds since its latest measurement)
and the traversability layers.
"""

from __future__ import annotations

import logging
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from dem_graph.dem.fusion import FusionConfig
from dem_graph.dem.incremental import IncrementalDem, Placed
from dem_graph.dem.layers import Dem
from dem_graph.dem.place_kernel import compile_kernel as compile_placement
from dem_graph.dem.returns import GroundReturns, ReturnSource, place_returns, returns_in_body
from dem_graph.dem.traversability import add_traversability
from dem_graph.dem.traversability import compile_kernel as compile_traversability
from dem_graph.dem.views import local_frame, local_to_world_xy
from dem_graph.errors import DemGraphError
from dem_graph.geometry.grid import GridGeometry
from dem_graph.geometry.rig import SensorRig

log = logging.getLogger(__name__)

PoseLookup = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]  # times (M,) -> poses (M,4,4), covariances (M,6,6)


@dataclass
class _LoggedScan:
    t_s: float
    p_body: np.ndarray  # (N,3) the valid returns in the body frame
    d_body: np.ndarray  # (N,3) their beam directions
    T_world_body: np.ndarray  # the pose they are placed with now
    placed: Placed


def pose_moved(T_old: np.ndarray, T_new: np.ndarray, tolerance_m: float, tolerance_rad: float) -> np.ndarray:
    """(M,) mask: pose pairs (M,4,4) whose translation or rotation differ by more than the tolerances."""
    dt = np.linalg.norm(T_new[:, :3, 3] - T_old[:, :3, 3], axis=1)
    R_rel_trace = np.einsum("nij,nij->n", T_old[:, :3, :3], T_new[:, :3, :3])  # trace(R_old^T R_new)
    angle = np.arccos(np.clip((R_rel_trace - 1.0) / 2.0, -1.0, 1.0))
    return (dt > tolerance_m) | (angle > tolerance_rad)


class LiveMap:
    """Scans in, revisions, local maps out (see the module)."""

    def __init__(
        self,
        rig: SensorRig,
        fusion: FusionConfig | None = None,
        window_s: float = 2.0,
        tolerance_m: float = 1e-3,
        tolerance_rad: float = 1e-4,
        tile_cells: int = 32,
        gate_min_count: int = 3,
    ):
        self.rig = rig
        self.fusion = fusion or FusionConfig()
        self.grid = IncrementalDem(self.fusion, tile_cells=tile_cells, gate_min_count=gate_min_count)
        self.window_s = float(window_s)
        self.tolerance_m = float(tolerance_m)
        self.tolerance_rad = float(tolerance_rad)
        self._log: deque[_LoggedScan] = deque()
        self.n_beams = len(rig.laser.beam_directions())
        self.counters = {"scans": 0, "returns": 0, "returns_moved": 0, "scans_moved": 0, "revisions": 0, "map_points": 0}
        compile_traversability()  # before the first local map, not in it
        compile_placement()  # before the first scan, not with it

    # --- measurements ------------------------------------------------------------------------
    def add_scan(self, t_s: float, ranges_m: np.ndarray, T_world_body: np.ndarray, covariance: np.ndarray) -> int:
        """Fuse every valid return of the scan at ``t_s``, placed with the pose ``T_world_body``
        (covariance 6x6); returns how many went in. A scan of the wrong length is refused
        (:class:`DemGraphError`); NaN, infinite and out-of-range beams are left out."""
        r = np.asarray(ranges_m, dtype=float).ravel()
        if len(r) != self.n_beams:
            raise DemGraphError(f"laser scan at {t_s:.6f} s has {len(r)} beams; the rig's laser has {self.n_beams}")
        beams = np.flatnonzero(self.rig.laser.valid_ranges(r))
        p_body, d_body = returns_in_body(r[beams], beams, self.rig)
        T = np.asarray(T_world_body, dtype=float)
        placed = self._place(t_s, p_body, d_body, T, np.asarray(covariance, dtype=float))
        self._log.append(_LoggedScan(float(t_s), p_body, d_body, T.copy(), placed))
        self.counters["scans"] += 1
        self.counters["returns"] += len(placed)
        return len(placed)

    def _place(self, t_s: float, p_body: np.ndarray, d_body: np.ndarray, T: np.ndarray, P: np.ndarray) -> Placed:
        n = len(p_body)
        if n == 0:
            return Placed.empty()
        xyz, var = place_returns(p_body, d_body, T[None], P[None], self.rig.laser.range_sigma_m)
        return self.grid.add(GroundReturns(xyz, var, np.full(n, t_s), np.full(n, ReturnSource.LASER_RETURN, dtype=np.uint8)))

    def add_points(self, xyz_m: np.ndarray, var_z_m2: np.ndarray, t_s: np.ndarray) -> Placed:
        """Fuse map points (world positions, height variances, times), as one batch; the
        returned record takes them back (``self.grid.remove``)."""
        xyz = np.asarray(xyz_m, dtype=float).reshape(-1, 3)
        placed = self.grid.add(GroundReturns(xyz, np.asarray(var_z_m2, dtype=float), np.asarray(t_s, dtype=float), np.full(len(xyz), ReturnSource.MAP_POINT, dtype=np.uint8)))
        self.counters["map_points"] += len(placed)
        return placed

    # --- revisions ---------------------------------------------------------------------------
    def newest_returns_world(self, n_scans: int) -> np.ndarray:
        """(N,3) world positions of the valid returns of the newest ``n_scans`` scans still open to
        revision, each placed with the pose its scan is held at now."""
        scans = list(self._log)[max(0, len(self._log) - int(n_scans)) :] if n_scans > 0 else []
        parts = [s.p_body @ s.T_world_body[:3, :3].T + s.T_world_body[:3, 3] for s in scans if len(s.p_body)]
        return np.concatenate(parts) if parts else np.zeros((0, 3))

    @property
    def logged_times_s(self) -> np.ndarray:
        """Times of the scans still open to revision."""
        return np.array([s.t_s for s in self._log])

    def revise(self, pose_at: PoseLookup) -> int:
        """Ask ``pose_at`` for the pose of every scan in the revision log; move the returns of the
        scans whose pose moved beyond the tolerance, out of the map and back in as one batch (gated
        together). Returns the number of returns moved."""
        if not self._log:
            return 0
        scans = list(self._log)
        T_new, P_new = pose_at(np.array([s.t_s for s in scans]))
        T_old = np.array([s.T_world_body for s in scans])
        index = np.flatnonzero(pose_moved(T_old, T_new, self.tolerance_m, self.tolerance_rad))
        self.counters["revisions"] += 1
        if len(index) == 0:
            return 0
        moved = [scans[i] for i in index]
        self.grid.remove(Placed.concatenate([s.placed for s in moved]))
        sizes = np.array([len(s.p_body) for s in moved])
        scan_of = np.repeat(np.arange(len(moved)), sizes)
        p_body = np.concatenate([s.p_body for s in moved])
        d_body = np.concatenate([s.d_body for s in moved])
        xyz, var = place_returns(p_body, d_body, T_new[index], P_new[index], self.rig.laser.range_sigma_m, pose_of=scan_of)
        t = np.repeat([s.t_s for s in moved], sizes)
        ok = np.all(np.isfinite(xyz), axis=1) & np.isfinite(var)
        if not np.all(ok):  # a pose with NaN in it: those scans leave the map rather than land anywhere
            log.warning("revised poses with NaN or infinite values: %d laser returns taken out of the live map", int((~ok).sum()))
            var = np.where(ok, var, np.nan)
        placed = self.grid.add(GroundReturns(xyz, var, t, np.full(len(t), ReturnSource.LASER_RETURN, dtype=np.uint8)))
        ends = np.cumsum(np.bincount(scan_of[ok], minlength=len(moved)))
        starts = ends - np.bincount(scan_of[ok], minlength=len(moved))
        for j, s in enumerate(moved):
            s.placed = placed.part(starts[j], ends[j])
            s.T_world_body = np.array(T_new[index[j]], dtype=float)
        n = len(placed)
        self.counters["scans_moved"] += len(moved)
        self.counters["returns_moved"] += n
        return n

    def freeze_before(self, t_s: float) -> None:
        """Scans before ``t_s`` leave the revision log (they stay in the map as they are); the
        caller freezes at ``window_s`` before its latest pose."""
        while self._log and self._log[0].t_s < t_s:
            self._log.popleft()

    # --- reading -----------------------------------------------------------------------------
    def local(self, T_world_body: np.ndarray, x_range_m: tuple[float, float], half_width_m: float, t_s: float, traversability_window: int | None = 3) -> Dem:
        """The local DEM at ``t_s`` from the pose ``T_world_body``: ``x_range_m`` ahead and
        ``half_width_m`` to each side in the heading frame, with ``age_s`` and (unless
        ``traversability_window`` is None) the traversability layers."""
        T_world_local = local_frame(T_world_body)
        geometry = GridGeometry.covering(x_range_m[0], -half_width_m, x_range_m[1], half_width_m, self.fusion.resolution_m)
        layers = self.grid.sample(*local_to_world_xy(T_world_local, *geometry.cell_centers_xy()))
        layers["elevation"] = layers["elevation"] - T_world_local[2, 3]
        layers["age_s"] = np.maximum(t_s - layers["last_update_s"], 0.0)  # times are kept in float32: a few microseconds
        dem = Dem(geometry, {k: v.astype(np.float32) for k, v in layers.items()}, frame="local", meta={"t_s": float(t_s), "T_world_local": T_world_local})
        dem.n_used = int(np.sum(layers["count"]))
        if traversability_window is not None:
            add_traversability(dem, traversability_window)
        return dem

    def global_dem(self, traversability_window: int | None = 3) -> Dem:
        """Everything mapped so far, on a north-up world grid (what ``map.tif`` holds)."""
        dem = self.grid.to_dem()
        if traversability_window is not None:
            add_traversability(dem, traversability_window)
        return dem


__all__ = ["LiveMap", "PoseLookup", "pose_moved"]
