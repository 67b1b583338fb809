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

from dataclasses import dataclass
from typing import TYPE_CHECKING

from dem_graph.frontend.focus import FocusConfig
from dem_graph.frontend.search_cap import (
    DEFAULT_SEARCH_HALF_SIZE_PX,
    REFERENCE_RATE_HZ,
    REFERENCE_SPEED_MPS,
    derived_search_half_size_px,
    nearest_ground_motion_px,
    step_per_frame_m,
)
from dem_graph.geometry.rig import SensorRig

if TYPE_CHECKING:
    from dem_graph.pipeline.config import RunConfig

DEFAULT_NOMINAL_SPEED_MPS: float = FocusConfig.model_fields["nominal_speed_mps"].default


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
        tracker.search_cap_follows_speed = False  # a cap given is the cap searched with
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
