"""The focus area: the ground the guidance needs, from the vehicle's speed and limits (the paper, III-B).

A rectangle on the local ground (the body frame's z = 0 plane) ahead of the vehicle: from the
nearest ground the camera sees well to the stopping distance at the current speed plus a margin,
across the corridor the vehicle may drive. It is divided into cells of the wanted density; the
front end keeps about one point per cell. Back-projected into the image with the flat-ground
assumption, it is the image region where points are seeded.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydantic import Field

from dem_graph.config_types import StrictModel
from dem_graph.geometry.ground_view import nearest_visible_ground_m
from dem_graph.geometry.rig import SensorRig
from dem_graph.geometry.se3 import invert, transform_points


class FocusConfig(StrictModel):
    reaction_time_s: float = Field(1.0, ge=0, description="guidance reaction time, seconds")
    braking_decel_mps2: float = Field(1.0, gt=0, description="braking deceleration, m/s^2")
    margin_m: float = Field(1.0, ge=0, description="extra look-ahead beyond the stopping distance, metres")
    front_offset_m: float = Field(1.0, ge=0, description="distance from the body origin to the vehicle's front, metres")
    corridor_width_m: float = Field(3.0, gt=0, description="width of the corridor the guidance may use, metres")
    cell_size_m: float = Field(0.3, gt=0, description="one point wanted per cell of this size, metres")
    near_margin_m: float = Field(0.4, ge=0, description="start this far beyond the nearest ground the camera sees, metres")
    min_depth_m: float = Field(1.5, gt=0, description="shortest extent of the focus area along the path, metres")
    max_distance_m: float = Field(15.0, gt=0, description="never look further than this ahead of the body origin, metres")
    nominal_speed_mps: float = Field(1.5, gt=0, description="speed assumed before the estimator knows it, m/s; left at 1.5, a run takes vehicle.speed_mps")


@dataclass(frozen=True)
class FocusArea:
    x_near_m: float
    x_far_m: float
    half_width_m: float
    cell_size_m: float

    @classmethod
    def for_speed(cls, config: FocusConfig, rig: SensorRig, speed_mps: float | None) -> FocusArea:
        near = nearest_visible_ground_m(rig) + config.near_margin_m
        if speed_mps == np.inf:  # the speed not known yet, about to be measured: the whole depth the area may take
            return cls(near, max(config.max_distance_m, near + config.min_depth_m), config.corridor_width_m / 2.0, config.cell_size_m)
        v = config.nominal_speed_mps if speed_mps is None or not np.isfinite(speed_mps) else abs(float(speed_mps))
        stopping = config.front_offset_m + v * config.reaction_time_s + v * v / (2.0 * config.braking_decel_mps2) + config.margin_m
        far = min(max(near + config.min_depth_m, stopping), config.max_distance_m)
        return cls(near, far, config.corridor_width_m / 2.0, config.cell_size_m)

    @property
    def shape(self) -> tuple[int, int]:
        """(cells along x, cells along y)."""
        return (max(1, int(np.ceil((self.x_far_m - self.x_near_m) / self.cell_size_m))), max(1, int(np.ceil(2 * self.half_width_m / self.cell_size_m))))

    def cell_centers_body(self) -> np.ndarray:
        """(M,3) cell centres on the body's ground plane, row-major (x then y)."""
        nx, ny = self.shape
        x = self.x_near_m + (np.arange(nx) + 0.5) * self.cell_size_m
        y = -self.half_width_m + (np.arange(ny) + 0.5) * self.cell_size_m
        X, Y = np.meshgrid(x, y, indexing="ij")
        return np.stack([X.ravel(), Y.ravel(), np.zeros(X.size)], axis=1)

    def cell_of(self, points_body: np.ndarray) -> np.ndarray:
        """Flat cell index of body-frame points, -1 outside the area."""
        nx, ny = self.shape
        p = np.atleast_2d(points_body)
        i = np.floor((p[:, 0] - self.x_near_m) / self.cell_size_m).astype(int)
        j = np.floor((p[:, 1] + self.half_width_m) / self.cell_size_m).astype(int)
        inside = (i >= 0) & (i < nx) & (j >= 0) & (j < ny)
        return np.where(inside, i * ny + j, -1)

    def contains(self, points_body: np.ndarray) -> np.ndarray:
        return self.cell_of(points_body) >= 0

    def image_polygon(self, rig: SensorRig, samples_per_edge: int = 8) -> np.ndarray:
        """The area's outline back-projected into the image (flat ground), (K,2) pixels."""
        x0, x1, w = self.x_near_m, self.x_far_m, self.half_width_m
        s = np.linspace(0.0, 1.0, samples_per_edge, endpoint=False)
        edges = [
            np.stack([x0 + (x1 - x0) * s, np.full_like(s, -w)], 1),
            np.stack([np.full_like(s, x1), -w + 2 * w * s], 1),
            np.stack([x1 - (x1 - x0) * s, np.full_like(s, w)], 1),
            np.stack([np.full_like(s, x0), w - 2 * w * s], 1),
        ]
        ground = np.concatenate(edges)
        ground = np.concatenate([ground, np.zeros((len(ground), 1))], axis=1)
        uv, _ = rig.camera_model.project(transform_points(invert(rig.T_body_cam), ground))
        return uv
