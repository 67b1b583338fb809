"""Settings every estimator shares, so GM, PTPM and the graph run with the same front end.

- :class:`MotionConfig`: how the pose is predicted between frames (odometry or constant velocity).
- :class:`FalseMatchConfig` and :class:`FalseMatches`: replace a fraction of the tracker's matches by
  wrong ones, for robustness studies.
- :class:`SharedSettings`: the front end, the motion model and the false matches, as one block.
"""

from __future__ import annotations

from collections import Counter
from typing import Literal

import numpy as np
from pydantic import Field

from dem_graph.config_types import StrictModel
from dem_graph.frontend.frontend import FrontendConfig


class MotionConfig(StrictModel):
    model: Literal["auto", "odometry", "constant_velocity"] = Field(
        "auto", description="auto: odometry when the dataset has it, constant velocity otherwise"
    )
    sigma_angular_acc_radps2: float = Field(1.5, gt=0, description="constant-velocity model: angular acceleration noise, rad/s^2/sqrt(Hz)")
    sigma_linear_acc_mps2: float = Field(1.5, gt=0, description="constant-velocity model: linear acceleration noise, m/s^2/sqrt(Hz)")
    initial_speed_mps: float = Field(0.0, description="constant-velocity model: initial forward speed, m/s")
    initial_sigma_speed_mps: float = Field(1.0, gt=0, description="constant-velocity model: initial speed uncertainty, m/s")
    initial_speed_from_dataset: bool = Field(
        False, description="constant-velocity model: start at the dataset's own estimate of the speed when it has one (KITTI: from its first two lidar scans) instead of initial_speed_mps"
    )
    wait_for_odometry: bool = Field(True, description="hold a frame until the odometry covering its time arrives (instead of extrapolating)")
    initial_sigma_pose: float = Field(1e-4, gt=0, description="initial pose uncertainty (radians and metres); the estimate is anchored at the initial pose")

    def uses_odometry(self, has_odometry: bool) -> bool:
        return self.model == "odometry" or (self.model == "auto" and has_odometry)


class FalseMatchConfig(StrictModel):
    fraction: float = Field(0.0, ge=0, le=1, description="replace this fraction of matches by wrong ones (robustness studies)")
    offset_px: float = Field(12.0, ge=0, description="distance of a wrong match from the true one, pixels")
    seed: int = Field(0, ge=0, description="random seed of the wrong matches")


class FalseMatches:
    """Replaces a tracked pixel by one ``offset_px`` away in a random direction, with probability
    ``fraction``; counts what the estimator then does with it."""

    def __init__(self, config: FalseMatchConfig, counters: Counter):
        self.config = config
        self.counters = counters
        self._rng = np.random.default_rng(config.seed)

    @property
    def enabled(self) -> bool:
        """False when :meth:`apply` returns every match unchanged (and draws nothing)."""
        return self.config.fraction > 0

    def apply(self, uv_found: np.ndarray | None, uv_predicted: np.ndarray) -> tuple[np.ndarray | None, bool]:
        """``(pixel, injected)``: the match, or a wrong one near it (near the prediction if the tracker found nothing)."""
        if self.config.fraction <= 0 or self._rng.random() >= self.config.fraction:
            return uv_found, False
        a = self._rng.uniform(0, 2 * np.pi)
        base = uv_found if uv_found is not None else uv_predicted
        return base + self.config.offset_px * np.array([np.cos(a), np.sin(a)]), True

    def record(self, accepted: bool) -> bool:
        """Count an injected match as accepted or rejected by the estimator; returns ``accepted``."""
        self.counters["injected"] += 1
        self.counters["injected_accepted" if accepted else "injected_rejected"] += 1
        return accepted


class SharedSettings(StrictModel):
    frontend: FrontendConfig = Field(default_factory=FrontendConfig, description="point management and tracking")
    motion: MotionConfig = Field(default_factory=MotionConfig, description="prediction between frames")
    false_matches: FalseMatchConfig = Field(default_factory=FalseMatchConfig, description="wrong matches injected for robustness studies")


__all__ = ["FalseMatchConfig", "FalseMatches", "MotionConfig", "SharedSettings"]
