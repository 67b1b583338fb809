"""What of the flat ground each sensor sees, from the rig alone: the nearest ground in the camera's
image, where the laser's line meets the ground, and how much of that line the camera sees.

The ground here is the body frame's z = 0 plane (the body origin is on the ground under the
vehicle). The paper's method ties a laser return to the image point it falls on, so it needs the
laser's line inside the image; a laser on a bumper, hitting the road below the camera's view, is
only of use to an estimator that keeps a landmark after it has left the image and ties it to the
scan that passes over its ground later (:mod:`dem_graph.estimators.laser_ties`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dem_graph.geometry.rig import SensorRig
from dem_graph.geometry.se3 import invert, transform_points

IN_VIEW_FRACTION = 0.2
"""At least this fraction of the laser's ground hits inside the image: the laser is "in view"."""


def nearest_visible_ground_m(rig: SensorRig) -> float:
    """Forward distance (body frame) of the flat ground seen by the bottom centre of the image; 0 when
    that pixel looks at or above the horizon."""
    cam = rig.camera_model
    bearing = cam.bearings_from_pixels(np.array([[cam.cx_px, cam.height_px - 1.0]]))[0]
    d_body = rig.T_body_cam[:3, :3] @ bearing
    o = rig.T_body_cam[:3, 3]
    if d_body[2] >= -1e-6:
        return 0.0
    lam = -o[2] / d_body[2]
    return float(o[0] + lam * d_body[0])


def laser_ground_hits(rig: SensorRig) -> np.ndarray:
    """(N, 3) body-frame points where the laser's beams meet the flat ground ahead (x > 0) within the
    laser's valid ranges."""
    R, o = rig.T_body_laser[:3, :3], rig.T_body_laser[:3, 3]
    d = rig.laser.beam_directions() @ R.T
    down = d[:, 2] < -1e-9
    if o[2] <= 0.0 or not down.any():
        return np.zeros((0, 3))
    r = -o[2] / d[down, 2]
    hits = o + r[:, None] * d[down]
    keep = (r >= rig.laser.range_min_m) & (r <= rig.laser.range_max_m) & (hits[:, 0] > 0.0)
    return hits[keep]


@dataclass(frozen=True)
class LaserView:
    """Where the laser's line meets the flat ground against the ground the camera sees."""

    beams: int  # the laser's beams
    on_ground: int  # of which meet the flat ground ahead within range
    in_image: int  # of which fall inside the image
    laser_ahead_m: float  # forward distance of the line's hit straight ahead (the beam nearest the body's x axis); nan: none
    camera_nearest_m: float  # the nearest ground the camera sees straight ahead (bottom centre of the image)

    @property
    def in_view(self) -> bool:
        """Enough of the laser's ground in the image for the paper's method (:data:`IN_VIEW_FRACTION`)."""
        return self.on_ground > 0 and self.in_image >= IN_VIEW_FRACTION * self.on_ground

    def line(self) -> str:
        """One line, as ``bag-info`` and ``run`` print it."""
        if self.on_ground == 0:
            return f"laser: none of its {self.beams} beams meets the flat ground ahead within its range: its returns are not the ground the camera sees"
        where = f"laser: its line meets the flat ground {self.laser_ahead_m:.2f} m ahead ({self.on_ground} of {self.beams} beams); the camera sees the ground from {self.camera_nearest_m:.2f} m ahead"
        share = 100.0 * self.in_image / self.on_ground
        if self.in_view:
            return f"{where}: {share:.0f} % of the laser's ground is in the image"
        side = "nearer than" if self.laser_ahead_m < self.camera_nearest_m else "outside"
        return (
            f"{where}: the laser's line is {side} the camera's view ({share:.0f} % of it in the image): no return falls on an image point "
            "(the EKF baselines cannot use it; the graph ties it to the landmarks over its ground, isam2.laser_ties)"
        )


def laser_view(rig: SensorRig) -> LaserView:
    """The :class:`LaserView` of ``rig``."""
    hits = laser_ground_hits(rig)
    beams = len(rig.laser.beam_directions())
    camera_nearest_m = nearest_visible_ground_m(rig)
    if not len(hits):
        return LaserView(beams, 0, 0, float("nan"), camera_nearest_m)
    cam = rig.camera_model
    uv, in_front = cam.project(transform_points(invert(rig.T_body_cam), hits))
    in_image = int(np.count_nonzero(in_front & cam.in_image(uv)))
    ahead = float(hits[np.argmin(np.abs(hits[:, 1])), 0])
    return LaserView(beams, len(hits), in_image, ahead, camera_nearest_m)


__all__ = ["IN_VIEW_FRACTION", "LaserView", "laser_ground_hits", "laser_view", "nearest_visible_ground_m"]
