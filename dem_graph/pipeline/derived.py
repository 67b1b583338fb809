"""Settings derived from the vehicle's speed and the camera's frame rate, where the user left them.

Two defaults hold only for the vehicle they were set for, the paper's robot (:func:`~dem_graph.geometry.rig.default_rig`:
1.5 m/s, a 25 Hz camera, 6 cm driven between frames):

- ``frontend.tracker.max_search_half_size_px`` (40 px): a search region larger than this is refused.
  The regions grow with the image motion between frames (the prediction's error is a fraction of
  it), so the cap is scaled by the image motion of the nearest ground the camera sees (the bottom
  centre of the image, where ground points move fastest) for the step driven between two frames,
  relative to the same motion on the reference rig at the reference step::

      step_m          = vehicle.speed_mps / camera.rate_hz
      half_size_px    = max(40, round(40 * motion_px(rig, step_m) / motion_px(default_rig, 1.5 / 25)))

  ``motion_px(rig, step_m)``: how far, in pixels, the flat ground straight ahead at the nearest
  visible distance moves in the image when the body drives ``step_m`` forward (the rig's own
  intrinsics, distortion, mount and camera height). Never below the reference: a slower vehicle's
  regions are smaller anyway, and a cap only refuses. The reference rig at 1.5 m/s and 25 Hz gives
  exactly 40; KITTI's camera at 12 m/s and 9.6 Hz 129 (drive 0013's, 9.66 Hz: 130).
- ``frontend.focus.nominal_speed_mps`` (1.5 m/s): the focus area's speed before the estimator has
  measured one: the vehicle's speed.

The camera's rate is the rig's (``camera.rate_hz``: read from the log's image time stamps for KITTI
and ROS bags, the folder's ``rig.yaml`` otherwise); the speed is ``vehicle.speed_mps``, whose
default is the reference speed: the paper's rig at 25 Hz (the simulator's ``paper``, ``demo``,
``smoke``) keeps every default as it was, and so does any rig whose nearest ground moves less.

A setting is derived only while the layered configuration still holds its default value: a value
given in the dataset's run settings or a configuration file always wins, and a value that restates
the default counts as not given, as in the rest of the layering (:mod:`dem_graph.pipeline.config`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from dem_graph.frontend.focus import FocusConfig
from dem_graph.frontend.tracker import TrackerConfig
from dem_graph.geometry.ground_view import nearest_visible_ground_m
from dem_graph.geometry.rig import SensorRig, default_rig
from dem_graph.geometry.se3 import invert, transform_points

if TYPE_CHECKING:
    from dem_graph.pipeline.config import RunConfig

REFERENCE_SPEED_MPS = 1.5
"""The speed the defaults were set for, m/s (the paper's robot)."""
REFERENCE_RATE_HZ = 25.0
"""The camera rate the defaults were set for, Hz (the paper's camera)."""
DEFAULT_SEARCH_HALF_SIZE_PX: int = TrackerConfig.model_fields["max_search_half_size_px"].default
DEFAULT_NOMINAL_SPEED_MPS: float = FocusConfig.model_fields["nominal_speed_mps"].default


def step_per_frame_m(speed_mps: float, rate_hz: float) -> float:
    """The distance driven between two camera frames, metres."""
    return speed_mps / rate_hz


def nearest_ground_motion_px(rig: SensorRig, step_m: float) -> float:
    """How far (pixels) the flat ground straight ahead at the nearest distance the camera sees moves
    in the image when the body drives ``step_m`` forward; nan when the camera sees no ground."""
    x_m = nearest_visible_ground_m(rig)
    if not x_m > 0.0:
        return math.nan
    ground_body = np.array([[x_m, 0.0, 0.0], [x_m - step_m, 0.0, 0.0]])  # the point, before and after the step
    uv_px, in_front = rig.camera_model.project(transform_points(invert(rig.T_body_cam), ground_body))
    if not in_front.all():
        return math.nan
    return float(np.linalg.norm(uv_px[1] - uv_px[0]))


def derived_search_half_size_px(rig: SensorRig, speed_mps: float, rate_hz: float) -> int:
    """The search cap for ``rig`` at ``speed_mps`` with a camera at ``rate_hz`` (the module's
    formula); the default when the camera sees no ground ahead."""
    motion_px = nearest_ground_motion_px(rig, step_per_frame_m(speed_mps, rate_hz))
    reference_px = nearest_ground_motion_px(default_rig(), step_per_frame_m(REFERENCE_SPEED_MPS, REFERENCE_RATE_HZ))
    if not math.isfinite(motion_px):
        return DEFAULT_SEARCH_HALF_SIZE_PX
    return max(DEFAULT_SEARCH_HALF_SIZE_PX, round(DEFAULT_SEARCH_HALF_SIZE_PX * motion_px / reference_px))


@dataclass(frozen=True)
class Derivation:
    """What :func:`derive_from_vehicle` set, from what: the settings derived (dotted name -> value)
    and those left as given."""

    speed_mps: float
    rate_hz: float
    derived: dict[str, float]
    given: dict[str, float]

    def text(self) -> str:
        """One line: the inputs, the step per frame, and what was derived or kept."""
        step_m = step_per_frame_m(self.speed_mps, self.rate_hz)
        parts = [f"{name} {value:g}" for name, value in self.derived.items()]
        parts += [f"{name} {value:g} as given" for name, value in self.given.items()]
        return (
            f"from vehicle.speed_mps {self.speed_mps:g} m/s and the camera's {self.rate_hz:.3g} Hz ({100 * step_m:.3g} cm per frame): "
            + ", ".join(parts)
        )


def derive_from_vehicle(config: RunConfig, rig: SensorRig) -> Derivation:
    """Set on ``config`` (in place) the settings the vehicle's speed and the camera's rate decide,
    those that still hold their default value, and say what was done."""
    speed_mps, rate_hz = config.vehicle.speed_mps, rig.camera.rate_hz
    derived: dict[str, float] = {}
    given: dict[str, float] = {}
    tracker, focus = config.frontend.tracker, config.frontend.focus
    if tracker.max_search_half_size_px == DEFAULT_SEARCH_HALF_SIZE_PX:
        tracker.max_search_half_size_px = derived_search_half_size_px(rig, speed_mps, rate_hz)
        derived["frontend.tracker.max_search_half_size_px"] = tracker.max_search_half_size_px
    else:
        given["frontend.tracker.max_search_half_size_px"] = tracker.max_search_half_size_px
    if focus.nominal_speed_mps == DEFAULT_NOMINAL_SPEED_MPS:
        focus.nominal_speed_mps = speed_mps
        derived["frontend.focus.nominal_speed_mps"] = focus.nominal_speed_mps
    else:
        given["frontend.focus.nominal_speed_mps"] = focus.nominal_speed_mps
    return Derivation(speed_mps, rate_hz, derived, given)


__all__ = [
    "DEFAULT_NOMINAL_SPEED_MPS",
    "DEFAULT_SEARCH_HALF_SIZE_PX",
    "Derivation",
    "REFERENCE_RATE_HZ",
    "REFERENCE_SPEED_MPS",
    "derive_from_vehicle",
    "derived_search_half_size_px",
    "nearest_ground_motion_px",
    "step_per_frame_m",
]
