"""The vehicle's motion between two frames from the ground itself, for a start without odometry.

Without odometry or an IMU, the constant-velocity model starts at ``motion.initial_speed_mps`` (0
by default), and a vehicle that already moves (a car at 7 m/s, 0.44 m a frame at 16 Hz) is then
outside every search region: nothing is tracked, and nothing ever corrects the model. The ground
ahead, though, is seen in both images. :class:`GroundMotion` warps the ground ahead of each image
onto a top view of the flat ground (the body frame's z = 0 plane, from the rig's camera mount) and
finds the shift between two top views by phase correlation: the body's translation over the
ground between the frames, in metres, at any speed the view's length allows. Its scale is the
flat-ground guess's (the camera's height and pitch): the tracking and the laser refine it later.

The estimators take it on their first frames (and again after a frame in which nothing was
tracked) as the forward and lateral speed of their constant-velocity model, in place of the guess
they held, with the measurement's uncertainty; the search regions then follow from the estimate.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from pydantic import Field

from dem_graph.config_types import StrictModel
from dem_graph.geometry.ground_view import nearest_visible_ground_m
from dem_graph.geometry.rig import SensorRig
from dem_graph.geometry.se3 import invert, transform_points


class GroundMotionConfig(StrictModel):
    """Settings of :class:`GroundMotion`."""

    enabled: bool = Field(True, description="without odometry, measure the speed from the ground on the first frames (and after a frame that tracked nothing)")
    length_m: float = Field(8.0, gt=0.5, description="the top view's extent along the ground ahead, metres, from near_margin_m beyond the nearest ground the camera sees")
    half_width_m: float = Field(2.0, gt=0.2, description="the top view's half width across, metres (less where the image is narrower)")
    near_margin_m: float = Field(0.3, ge=0, description="the top view starts this far beyond the nearest ground the camera sees, metres")
    cell_m: float = Field(0.0, ge=0, description="the top view's cell, metres; 0: the ground's footprint of a pixel at the view's near edge, doubled (at least 1 cm)")
    min_response: float = Field(0.08, gt=0, le=1, description="least phase-correlation peak (0-1) of a shift taken as measured")
    max_shift_fraction: float = Field(0.4, gt=0, lt=1, description="a shift larger than this fraction of the view's length is refused (the views barely overlap)")
    sigma_scale_fraction: float = Field(0.1, ge=0, description="the uncertainty of a shift, a fraction of it: the flat-ground guess (the camera's height and pitch; rough ground, the body pitching)")


@dataclass(frozen=True)
class GroundShift:
    """The body's translation over the ground between two frames, in the first frame's body axes."""

    forward_m: float
    lateral_m: float  # positive: to the left
    sigma_m: float  # one standard deviation of each component
    response: float  # the phase correlation's peak (0-1)
    dt_s: float  # the time between the two frames

    def velocity(self) -> tuple[np.ndarray, np.ndarray]:
        """The body's linear velocity (3,) m/s, and its 3x3 covariance (the vertical speed is not
        measured: 0 with the forward component's uncertainty)."""
        v = np.array([self.forward_m, self.lateral_m, 0.0]) / self.dt_s
        return v, np.eye(3) * (self.sigma_m / self.dt_s) ** 2


class GroundMotion:
    """The top view of the ground ahead, made once from the rig, and :meth:`shift` between two frames."""

    def __init__(self, config: GroundMotionConfig, rig: SensorRig):
        self.config = config
        self.problem: str | None = None  # why the view could not be made (the camera sees no ground), or None
        cam = rig.camera_model
        near = nearest_visible_ground_m(rig)
        if not near > 0.0:
            self.problem = "the camera sees no ground ahead"
            return
        x0 = near + config.near_margin_m
        cell = config.cell_m or max(0.01, 2.0 * _along_footprint_m(rig, x0))
        rows = int(config.length_m / cell)
        cols = 2 * int(config.half_width_m / cell)
        x = x0 + (np.arange(rows)[::-1] + 0.5) * cell  # the top row farthest: the image's own up
        y = (np.arange(cols)[::-1] - cols / 2 + 0.5) * cell  # the left column at +y: the image's own left
        X, Y = np.meshgrid(x, y, indexing="ij")
        ground = np.stack([X.ravel(), Y.ravel(), np.zeros(X.size)], axis=1)
        uv, in_front = cam.project(transform_points(invert(rig.T_body_cam), ground))
        valid = (in_front & cam.in_image(uv, margin_px=1.0)).reshape(rows, cols)
        keep_cols = valid.all(axis=0)
        if keep_cols.sum() < 16 or rows < 16:
            self.problem = f"the top view of the ground ahead is too small ({rows} x {int(keep_cols.sum())} cells of {cell:g} m)"
            return
        j = np.flatnonzero(keep_cols)
        keep = slice(j[0], j[-1] + 1)
        uv = uv.reshape(rows, cols, 2)[:, keep]
        self.map_u = np.ascontiguousarray(uv[..., 0], dtype=np.float32)
        self.map_v = np.ascontiguousarray(uv[..., 1], dtype=np.float32)
        self.cell_m = cell
        self.shape = self.map_u.shape
        self.length_m = rows * cell
        self._window = cv2.createHanningWindow((self.shape[1], self.shape[0]), cv2.CV_64F)

    def top_view(self, image: np.ndarray) -> np.ndarray:
        """The ground ahead in ``image`` on the top view's cells (float64, zero mean)."""
        grey = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) if image.ndim == 3 else image
        view = cv2.remap(grey, self.map_u, self.map_v, cv2.INTER_LINEAR).astype(np.float64)
        return view - view.mean()

    def shift(self, view_before: np.ndarray, view_after: np.ndarray, dt_s: float) -> GroundShift | str:
        """The body's translation between the frames of two :meth:`top_view` images ``dt_s`` apart,
        or why none was measured (one clause)."""
        (du, dv), response = cv2.phaseCorrelate(view_before, view_after, self._window)
        # a ground point d ahead moves d towards the vehicle: down the view's rows (rows run from far
        # to near), and across its columns against the lateral motion (columns run from left to right)
        forward_m, lateral_m = dv * self.cell_m, du * self.cell_m
        if not (math.isfinite(response) and response >= self.config.min_response):
            return f"the two views of the ground do not correlate (peak {response:.3f} < ground_motion.min_response = {self.config.min_response:g})"
        if math.hypot(forward_m, lateral_m) > self.config.max_shift_fraction * self.length_m:
            return f"the ground moved {math.hypot(forward_m, lateral_m):.2f} m, beyond what two views of {self.length_m:.1f} m share"
        sigma = 0.3 * self.cell_m + self.config.sigma_scale_fraction * math.hypot(forward_m, lateral_m)
        return GroundShift(forward_m, lateral_m, sigma, float(response), float(dt_s))


def _along_footprint_m(rig: SensorRig, x_m: float) -> float:
    """How far along the ground straight ahead one image row spans at ``x_m`` ahead, metres."""
    cam = rig.camera_model
    pts = np.array([[x_m, 0.0, 0.0], [x_m + 0.01, 0.0, 0.0]])
    uv, in_front = cam.project(transform_points(invert(rig.T_body_cam), pts))
    rows_px = abs(float(uv[1, 1] - uv[0, 1]))
    return 0.01 / rows_px if in_front.all() and rows_px > 0 else 0.02


__all__ = ["GroundMotion", "GroundMotionConfig", "GroundShift"]
