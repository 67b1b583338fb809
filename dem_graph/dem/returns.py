"""Ground measurements for the DEM: every laser return and every map point, in the world frame, each
with its own height variance (the paper's Eq. 4, with the uncertainty carried along).

A laser return is placed with the estimated body pose at its scan's own time (rotation slerp and
linear translation between the two nearest estimated poses) and ``T_body_laser``. Its height
variance is the range noise and the pose covariance at that time, propagated to first order:

    p_world = R_world_body (R_body_laser r d + t_body_laser) + t_world_body
    var_z   = J P J^T + (a . R_body_laser d)^2 sigma_r^2,   a = R_world_body^T e_z,  J = [p_body x a, a]

with ``P`` the 6x6 pose covariance in gtsam's order [rotation, translation] as a right perturbation
(``T Exp(xi)``), interpolated linearly between the two poses. Returns are vectorised over the
whole log: no Python loop over scans or beams.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from enum import IntEnum
from functools import cached_property

import numpy as np

from dem_graph.dem.place_kernel import place
from dem_graph.errors import DemGraphError
from dem_graph.geometry.rig import SensorRig
from dem_graph.geometry.trajectory import Trajectory

log = logging.getLogger(__name__)



class ReturnSource(IntEnum):
    """What a ground measurement is (its value is the ``source`` column of ``cloud.ply``)."""

    LASER_RETURN = 0  # one beam of a scan, placed with the pose at the scan's time
    MAP_POINT = 1  # a point the estimator tracked (laser or camera seeded), at its last estimate



@dataclass(frozen=True)
class PoseTrack:
    """Estimated body poses with their covariances, queryable at any time inside their span."""

    t_s: np.ndarray  # (N,)
    T_world_body: np.ndarray  # (N, 4, 4)
    covariance: np.ndarray  # (N, 6, 6) [rotation, translation], right perturbation

    def __post_init__(self):
        n = len(np.atleast_1d(self.t_s))
        if np.shape(self.T_world_body) != (n, 4, 4) or np.shape(self.covariance) != (n, 6, 6):
            raise DemGraphError(
                f"pose track arrays disagree: {n} times, poses {np.shape(self.T_world_body)}, covariances {np.shape(self.covariance)}"
            )
        if n == 0:
            raise DemGraphError("the pose track is empty: no pose to place the laser returns with")
        if not (np.all(np.isfinite(self.T_world_body)) and np.all(np.isfinite(self.covariance))):
            raise DemGraphError("the pose track holds NaN or infinite values")
        self.trajectory  # validates the times (strictly increasing)  # noqa: B018

    @cached_property
    def trajectory(self) -> Trajectory:
        """The poses as a :class:`Trajectory` (built once: every query interpolates through it)."""
        return Trajectory.from_poses(self.t_s, self.T_world_body)

    def covers(self, t_s: np.ndarray) -> np.ndarray:
        t = np.asarray(t_s, dtype=float)
        return (t >= self.t_s[0]) & (t <= self.t_s[-1])

    def at(self, t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Poses (M,4,4) and covariances (M,6,6) at the times ``t_s`` (inside the span)."""
        t = np.atleast_1d(np.asarray(t_s, dtype=float))
        T = self.trajectory.at(t)
        if len(self.t_s) == 1:
            return T.reshape(-1, 4, 4), np.repeat(self.covariance, len(t), axis=0)
        hi = np.clip(np.searchsorted(self.t_s, t, side="right"), 1, len(self.t_s) - 1)
        lo = hi - 1
        a = np.clip((t - self.t_s[lo]) / (self.t_s[hi] - self.t_s[lo]), 0.0, 1.0)[:, None, None]
        P = (1.0 - a) * self.covariance[lo] + a * self.covariance[hi]
        return T.reshape(-1, 4, 4), P


@dataclass(frozen=True)
class GroundReturns:
    """World-frame ground measurements: position, height variance, time and source (laser or map point)."""

    xyz_m: np.ndarray  # (N, 3) world
    var_z_m2: np.ndarray  # (N,)
    t_s: np.ndarray  # (N,) when measured (a map point: when it was created)
    source: np.ndarray  # (N,) uint8: ReturnSource

    def __len__(self) -> int:
        return len(self.t_s)

    @classmethod
    def empty(cls) -> GroundReturns:
        return cls(np.zeros((0, 3)), np.zeros(0), np.zeros(0), np.zeros(0, dtype=np.uint8))

    @classmethod
    def concatenate(cls, parts: list[GroundReturns]) -> GroundReturns:
        parts = [p for p in parts if len(p)]
        if not parts:
            return cls.empty()
        out = cls(
            np.concatenate([p.xyz_m for p in parts]),
            np.concatenate([p.var_z_m2 for p in parts]),
            np.concatenate([p.t_s for p in parts]),
            np.concatenate([p.source for p in parts]),
        )
        order = np.argsort(out.t_s, kind="stable")
        return out.select(order)

    def select(self, index: np.ndarray) -> GroundReturns:
        return GroundReturns(self.xyz_m[index], self.var_z_m2[index], self.t_s[index], self.source[index])

    def until(self, t_s: float) -> GroundReturns:
        """The measurements taken at or before ``t_s`` (what was known then)."""
        return self.select(self.t_s <= t_s)


def returns_in_body(ranges_m: np.ndarray, beam_idx: np.ndarray, rig: SensorRig) -> tuple[np.ndarray, np.ndarray]:
    """Returns (ranges of beams ``beam_idx``) in the body frame: points (N,3) and beam directions (N,3)."""
    T_body_laser = rig.T_body_laser
    d_body = (rig.laser.beam_directions() @ T_body_laser[:3, :3].T)[beam_idx]
    return np.asarray(ranges_m, dtype=float)[:, None] * d_body + T_body_laser[:3, 3], d_body


def place_returns(
    p_body: np.ndarray, d_body: np.ndarray, T_world_body: np.ndarray, P: np.ndarray, range_sigma_m: float, pose_of: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """World positions (N,3) and height variances (N,) of body-frame returns (N,3) with their beam
    directions (N,3) (the module's equations). Each is placed with its pose (N,4,4) and pose
    covariance (N,6,6), or all with one (1,4,4), (1,6,6); or, given ``pose_of`` (N,), return i
    with pose ``pose_of[i]`` of (M,4,4), (M,6,6). One compiled loop
    (:func:`~dem_graph.dem.place_kernel.place`)."""
    T = np.ascontiguousarray(T_world_body, dtype=float).reshape(-1, 4, 4)
    P = np.ascontiguousarray(P, dtype=float).reshape(-1, 6, 6)
    p = np.ascontiguousarray(p_body, dtype=float).reshape(-1, 3)
    if pose_of is None:
        pose_of = np.zeros(len(p), dtype=np.int64) if len(T) == 1 else np.arange(len(p), dtype=np.int64)
    pose_of = np.ascontiguousarray(pose_of, dtype=np.int64)
    if len(pose_of) != len(p) or len(T) != len(P) or (len(pose_of) and (pose_of.min() < 0 or pose_of.max() >= len(T))):
        raise DemGraphError(f"placing {len(p)} returns with {len(T)} poses, {len(P)} covariances and {len(pose_of)} pose indices: they disagree")
    return place(p, np.ascontiguousarray(d_body, dtype=float).reshape(-1, 3), T, P, pose_of, float(range_sigma_m))


def laser_returns_world(scan_t_s: np.ndarray, ranges_m: np.ndarray, rig: SensorRig, poses: PoseTrack) -> GroundReturns:
    """Every valid laser return of every scan, placed with the pose at its scan's time.

    Beams without a return (NaN), outside the rig's range limits or from scans outside the pose
    track's span are left out; how many is logged.
    """
    scan_t_s = np.asarray(scan_t_s, dtype=float)
    ranges_m = np.asarray(ranges_m, dtype=float)
    laser = rig.laser
    d_laser = laser.beam_directions()
    if ranges_m.ndim != 2 or ranges_m.shape != (len(scan_t_s), len(d_laser)):
        raise DemGraphError(f"laser ranges have shape {ranges_m.shape}; expected ({len(scan_t_s)} scans, {len(d_laser)} beams)")
    if len(scan_t_s) == 0:
        return GroundReturns.empty()
    in_span = poses.covers(scan_t_s)
    if not np.all(in_span):
        # usual at the ends of a log (a scan after the last frame); the count says if it is more
        log.info("%d of %d scans lie outside the estimated trajectory's time span: left out of the DEM", int((~in_span).sum()), len(scan_t_s))
    valid = laser.valid_ranges(ranges_m) & in_span[:, None]
    n_invalid = int((~valid[in_span]).sum())
    if n_invalid:
        log.info("%d laser beams without a usable return (NaN or out of range) left out", n_invalid)
    scan_idx, beam_idx = np.nonzero(valid)
    if len(scan_idx) == 0:
        return GroundReturns.empty()
    T_scan, P_scan = poses.at(scan_t_s[in_span])
    # index of each valid return's scan among the scans in span
    span_pos = np.cumsum(in_span) - 1
    p_body, d_body = returns_in_body(ranges_m[scan_idx, beam_idx], beam_idx, rig)
    xyz, var = place_returns(p_body, d_body, T_scan, P_scan, laser.range_sigma_m, pose_of=span_pos[scan_idx])
    return GroundReturns(xyz, var, scan_t_s[scan_idx], np.full(len(var), ReturnSource.LASER_RETURN, dtype=np.uint8))


def map_point_returns(xyz_m: np.ndarray, covariance: np.ndarray, created_t_s: np.ndarray) -> GroundReturns:
    """The estimator's map points as ground measurements, their height variance from their covariance."""
    xyz = np.asarray(xyz_m, dtype=float).reshape(-1, 3)
    cov = np.asarray(covariance, dtype=float).reshape(-1, 3, 3)
    t = np.asarray(created_t_s, dtype=float).reshape(-1)
    if not (len(xyz) == len(cov) == len(t)):
        raise DemGraphError(f"map point arrays disagree: {len(xyz)} positions, {len(cov)} covariances, {len(t)} times")
    return GroundReturns(xyz, cov[:, 2, 2].copy(), t, np.full(len(t), ReturnSource.MAP_POINT, dtype=np.uint8))


__all__ = ["GroundReturns", "PoseTrack", "ReturnSource", "laser_returns_world", "map_point_returns", "place_returns", "returns_in_body"]
