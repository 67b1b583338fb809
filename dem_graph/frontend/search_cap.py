"""The tracker's search cap for a vehicle's speed and camera rate (the formula of
:mod:`dem_graph.pipeline.derived`), and how it follows the speed the estimator measures.

A search region larger than ``frontend.tracker.max_search_half_size_px`` is refused. The regions
grow with the image motion between frames, so the cap is scaled by the image motion of the nearest
ground the camera sees for the step driven between two frames, relative to the same motion on the
paper's rig at 1.5 m/s and 25 Hz (which gives the default, 40 px).
"""

from __future__ import annotations

import functools
import math

import numpy as np

from dem_graph.frontend.tracker import TrackerConfig
from dem_graph.geometry.ground_view import nearest_visible_ground_m
from dem_graph.geometry.rig import SensorRig, default_rig
from dem_graph.geometry.se3 import invert, transform_points

REFERENCE_SPEED_MPS = 1.5
"""The speed the defaults were set for, m/s (the paper's robot)."""
REFERENCE_RATE_HZ = 25.0
"""The camera rate the defaults were set for, Hz (the paper's camera)."""
DEFAULT_SEARCH_HALF_SIZE_PX: int = TrackerConfig.model_fields["max_search_half_size_px"].default
RAISE_ABOVE = 1.25
"""The cap follows the measured speed only where the formula asks for this much more than the cap
in force, and then with this margin on the speed: a vehicle near the speed the cap was made for
keeps it as it is."""


def step_per_frame_m(speed_mps: float, rate_hz: float) -> float:
    """The distance driven between two camera frames, metres."""
    return speed_mps / rate_hz


class GroundMotionPx:
    """The rig's part of the formula, made once: the nearest ground the camera sees and the camera
    that projects it, so that a frame asking for the cap at its speed only projects two points."""

    def __init__(self, rig: SensorRig):
        self.x_m = nearest_visible_ground_m(rig)
        self.rate_hz = rig.camera.rate_hz
        self._camera = rig.camera_model
        self._T_cam_body = invert(rig.T_body_cam)

    def for_step(self, step_m: float) -> float:
        """How far (pixels) the flat ground straight ahead at the nearest distance the camera sees
        moves in the image when the body drives ``step_m`` forward; nan when the camera sees no ground."""
        if not self.x_m > 0.0:
            return math.nan
        ground_body = np.array([[self.x_m, 0.0, 0.0], [self.x_m - step_m, 0.0, 0.0]])  # the point, before and after the step
        uv_px, in_front = self._camera.project(transform_points(self._T_cam_body, ground_body))
        if not in_front.all():
            return math.nan
        return float(np.linalg.norm(uv_px[1] - uv_px[0]))

    def search_half_size_px(self, speed_mps: float, rate_hz: float | None = None) -> int:
        """The search cap at ``speed_mps`` with a camera at ``rate_hz`` (default: the rig's): the
        module's formula; the default when the camera sees no ground ahead."""
        motion_px = self.for_step(step_per_frame_m(speed_mps, self.rate_hz if rate_hz is None else rate_hz))
        if not math.isfinite(motion_px):
            return DEFAULT_SEARCH_HALF_SIZE_PX
        return max(DEFAULT_SEARCH_HALF_SIZE_PX, round(DEFAULT_SEARCH_HALF_SIZE_PX * motion_px / _reference_motion_px()))

    def cap_for_speed(self, cap_px: int, speed_mps: float) -> int:
        """The cap to search with at the measured ``speed_mps``: ``cap_px`` unless the formula at that
        speed asks for more than :data:`RAISE_ABOVE` times it, then the formula at :data:`RAISE_ABOVE`
        times the speed. Never below ``cap_px``."""
        if not (math.isfinite(speed_mps) and speed_mps > 0):
            return cap_px
        if self.search_half_size_px(speed_mps) <= RAISE_ABOVE * cap_px:
            return cap_px
        return max(cap_px, self.search_half_size_px(RAISE_ABOVE * speed_mps))


@functools.cache
def _reference_motion_px() -> float:
    """The reference rig's image motion at the reference step (the formula's denominator)."""
    return GroundMotionPx(default_rig()).for_step(step_per_frame_m(REFERENCE_SPEED_MPS, REFERENCE_RATE_HZ))


def nearest_ground_motion_px(rig: SensorRig, step_m: float) -> float:
    """:meth:`GroundMotionPx.for_step` of ``rig``."""
    return GroundMotionPx(rig).for_step(step_m)


def derived_search_half_size_px(rig: SensorRig, speed_mps: float, rate_hz: float) -> int:
    """:meth:`GroundMotionPx.search_half_size_px` of ``rig``."""
    return GroundMotionPx(rig).search_half_size_px(speed_mps, rate_hz)


def cap_for_speed(rig: SensorRig, cap_px: int, speed_mps: float) -> int:
    """:meth:`GroundMotionPx.cap_for_speed` of ``rig`` (a front end keeps one :class:`GroundMotionPx`)."""
    return GroundMotionPx(rig).cap_for_speed(cap_px, speed_mps)


__all__ = [
    "DEFAULT_SEARCH_HALF_SIZE_PX", "GroundMotionPx", "RAISE_ABOVE", "REFERENCE_RATE_HZ", "REFERENCE_SPEED_MPS", "cap_for_speed", "derived_search_half_size_px",
    "nearest_ground_motion_px", "step_per_frame_m",
]
