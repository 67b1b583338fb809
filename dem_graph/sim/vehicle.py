"""The driven path, the speed profile, and the vehicle's 6-DoF pose following the terrain."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import gaussian_filter1d

from dem_graph.geometry.grid import ElevationGrid
from dem_graph.geometry.se3 import make_pose, rotation_from_rpy
from dem_graph.sim.config import PathSpec

_DS_M = 0.02  # arc-length step of the path samples
_DT_S = 0.002  # time step of the speed integration


@dataclass(frozen=True)
class DrivenPath:
    """A planar path sampled by arc length, with smooth (clothoid-like) curvature changes."""

    s_m: np.ndarray
    xy_m: np.ndarray
    heading_rad: np.ndarray

    @property
    def length_m(self) -> float:
        return float(self.s_m[-1])

    def at(self, s_m) -> tuple[np.ndarray, np.ndarray]:
        """Position (…,2) and heading at arc length(s) ``s_m``."""
        s = np.asarray(s_m, dtype=float)
        x = np.interp(s, self.s_m, self.xy_m[:, 0])
        y = np.interp(s, self.s_m, self.xy_m[:, 1])
        return np.stack([x, y], axis=-1), np.interp(s, self.s_m, self.heading_rad)


def generate_path(spec: PathSpec, length_m: float, rng: np.random.Generator, straight: bool = False) -> DrivenPath:
    """A path of at least ``length_m`` starting at the origin heading +x: a straight, then turns and straights."""
    segments: list[tuple[float, float]] = [(spec.first_straight_m, 0.0)]  # (length, curvature)
    total = spec.first_straight_m
    side = rng.choice([-1.0, 1.0])
    while total < length_m + 5.0 and not straight:
        radius = rng.uniform(*spec.turn_radius_m)
        angle = np.radians(rng.uniform(*spec.turn_angle_deg))
        segments.append((radius * angle, side / radius))
        side = -side if rng.random() < 0.7 else side
        straight_len = rng.uniform(*spec.straight_m)
        segments.append((straight_len, 0.0))
        total += radius * angle + straight_len
    if straight:
        segments = [(length_m + 5.0, 0.0)]
        total = length_m + 5.0
    n = int(np.ceil(total / _DS_M)) + 1
    s = np.arange(n) * _DS_M
    curvature = np.zeros(n)
    start = 0.0
    for seg_len, kappa in segments:
        curvature[(s >= start) & (s < start + seg_len)] = kappa
        start += seg_len
    # clothoid-like transitions: smooth the curvature over about 1.5 m
    curvature = gaussian_filter1d(curvature, 1.5 / _DS_M, mode="nearest")
    heading = np.concatenate([[0.0], np.cumsum(0.5 * (curvature[1:] + curvature[:-1]) * _DS_M)])
    dx = np.cos(heading)
    dy = np.sin(heading)
    x = np.concatenate([[0.0], np.cumsum(0.5 * (dx[1:] + dx[:-1]) * _DS_M)])
    y = np.concatenate([[0.0], np.cumsum(0.5 * (dy[1:] + dy[:-1]) * _DS_M)])
    return DrivenPath(s, np.stack([x, y], axis=1), heading)


@dataclass(frozen=True)
class SpeedProfile:
    """Arc length travelled as a function of time, from a slowly varying speed."""

    t_s: np.ndarray
    s_m: np.ndarray

    @classmethod
    def generate(cls, spec: PathSpec, length_m: float, rng: np.random.Generator) -> SpeedProfile:
        duration = 1.3 * length_m / (spec.speed_mps * (1.0 - spec.speed_variation)) + 1.0
        t = np.arange(0.0, duration, _DT_S)
        phase = rng.uniform(0, 2 * np.pi, size=2)
        v = spec.speed_mps * (
            1.0 + spec.speed_variation * (0.7 * np.sin(2 * np.pi * t / 23.0 + phase[0]) + 0.3 * np.sin(2 * np.pi * t / 9.0 + phase[1]))
        )
        s = np.concatenate([[0.0], np.cumsum(0.5 * (v[1:] + v[:-1]) * _DT_S)])
        return cls(t, s)

    def s_at(self, t_s) -> np.ndarray:
        return np.interp(t_s, self.t_s, self.s_m)

    def time_at_distance(self, s_m: float) -> float:
        return float(np.interp(s_m, self.s_m, self.t_s))


class VehicleMotion:
    """The body pose ``T_world_body(t)``: the path in x, y, yaw; z, roll and pitch from the wheels' contacts.

    The body origin is the centre of the four wheel contacts at ground level; the contacts are
    ``(+-wheelbase/2, +-track/2, 0)`` in the body frame. Roll and pitch come from the mean heights of
    the left/right and front/rear contacts on the terrain smoothed by the tyre patch, z from the
    mean of all four; the remaining twist (one wheel off the contact plane) is the suspension's.
    """

    def __init__(self, path: DrivenPath, speed: SpeedProfile, contact_surface: ElevationGrid, spec: PathSpec):
        self.path = path
        self.speed = speed
        self.contact_surface = contact_surface
        self.spec = spec
        half_l, half_w = spec.wheelbase_m / 2, spec.track_m / 2
        self.contacts_body = np.array([[half_l, half_w, 0.0], [half_l, -half_w, 0.0], [-half_l, half_w, 0.0], [-half_l, -half_w, 0.0]])

    def T_world_body(self, t_s) -> np.ndarray:
        """(M,4,4) poses at the times ``t_s`` (or (4,4) for a scalar)."""
        t = np.atleast_1d(np.asarray(t_s, dtype=float))
        xy, yaw = self.path.at(self.speed.s_at(t))
        roll = np.zeros_like(t)
        pitch = np.zeros_like(t)
        z = np.zeros_like(t)
        for _ in range(3):  # contact positions depend on roll and pitch: a few fixed-point iterations
            R = rotation_from_rpy(roll, pitch, yaw)
            contacts_xy = xy[:, None, :] + np.einsum("mij,kj->mki", R[:, :2, :], self.contacts_body)
            h = self.contact_surface.height_at(contacts_xy[..., 0], contacts_xy[..., 1])  # (M,4): FL, FR, RL, RR
            front, rear = h[:, :2].mean(axis=1), h[:, 2:].mean(axis=1)
            left, right = h[:, [0, 2]].mean(axis=1), h[:, [1, 3]].mean(axis=1)
            pitch = np.arctan2(rear - front, self.spec.wheelbase_m)
            roll = np.arctan2(left - right, self.spec.track_m)
            z = h.mean(axis=1)
        # the origin sits on the contact plane: shift so the mean contact (body z=0) is at mean height
        R = rotation_from_rpy(roll, pitch, yaw)
        T = make_pose(R, np.concatenate([xy, z[:, None]], axis=1))
        return T[0] if np.ndim(t_s) == 0 else T

    def contact_heights(self, T_world_body: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(M,4) world heights of the wheel contacts under poses, and of the terrain below them."""
        T = T_world_body if T_world_body.ndim == 3 else T_world_body[None]
        pts = np.einsum("mij,kj->mki", T[:, :3, :3], self.contacts_body) + T[:, None, :3, 3]
        return pts[..., 2], self.contact_surface.height_at(pts[..., 0], pts[..., 1])
