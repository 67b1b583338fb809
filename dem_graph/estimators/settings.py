"""Settings every estimator shares, so GM, PTPM and the graph run with the same front end.

- :class:`MotionConfig`: how the pose is predicted between frames (odometry or constant velocity).
- :class:`FalseMatchConfig`: replace a fraction of the tracker's matches by wrong ones, for
  robustness studies (:class:`~dem_graph.estimators.false_matches.FalseMatches` does it).
- :class:`SharedSettings`: the front end, the motion model and the false matches, as one block.
"""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from dem_graph.config_types import StrictModel
from dem_graph.frontend.frontend import FrontendConfig


class MotionConfig(StrictModel):
    model: Literal["auto", "odometry", "constant_velocity"] = Field(
        "auto", description="auto: odometry when the dataset has it, constant velocity otherwise"
    )
    sigma_angular_acc_radps2: float = Field(1.5, gt=0, description="constant-velocity model: angular acceleration noise, rad/s^2/sqrt(Hz)")
    sigma_linear_acc_mps2: float = Field(1.5, gt=0, description="constant-velocity model: linear acceleration noise, m/s^2/sqrt(Hz)")
    initial_speed_mps: float = Field(
        0.0,
        description="constant-velocity model: initial forward speed, m/s; 0: not known, measured from the ground on the second frame "
        "(frontend.ground_motion), which any other value (given, or the dataset's own) is taken as instead",
    )
    initial_sigma_speed_mps: float = Field(1.0, gt=0, description="constant-velocity model: initial speed uncertainty, m/s")
    initial_speed_from_dataset: bool = Field(
        False, description="constant-velocity model: start at the dataset's own estimate of the speed when it has one (KITTI: from its first two lidar scans) instead of initial_speed_mps"
    )
    wait_for_odometry: bool = Field(True, description="hold a frame until the odometry covering its time arrives (instead of extrapolating)")
    initial_sigma_pose: float = Field(1e-4, gt=0, description="initial pose uncertainty (radians and metres); the estimate is anchored at the initial pose")
    use_imu: bool = Field(True, description="use the dataset's IMU when it has one (the rig's imu section); false (--no-imu): ignore its samples")

    @property
    def speed_known_at_start(self) -> bool:
        """Whether the run starts at a speed it was given or the dataset measured (not 0, the unknown)."""
        return self.initial_speed_mps != 0.0

    def uses_odometry(self, has_odometry: bool) -> bool:
        return self.model == "odometry" or (self.model == "auto" and has_odometry)


class FalseMatchConfig(StrictModel):
    fraction: float = Field(0.0, ge=0, le=1, description="replace this fraction of matches by wrong ones (robustness studies)")
    offset_px: float = Field(12.0, ge=0, description="distance of a wrong match from the true one, pixels")
    seed: int = Field(0, ge=0, description="random seed of the wrong matches")


class SharedSettings(StrictModel):
    frontend: FrontendConfig = Field(default_factory=FrontendConfig, description="point management and tracking")
    motion: MotionConfig = Field(default_factory=MotionConfig, description="prediction between frames")
    false_matches: FalseMatchConfig = Field(default_factory=FalseMatchConfig, description="wrong matches injected for robustness studies")


__all__ = ["FalseMatchConfig", "MotionConfig", "SharedSettings"]
