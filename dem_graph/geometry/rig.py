"""The sensor rig: camera intrinsics, extrinsics, laser beams, rates and noise figures.

Loaded from and written to YAML (:func:`load_rig`, :func:`save_rig`), validated on load.
Extrinsics are ``T_body_cam`` and ``T_body_laser``; the paper's P_{L-C} is
:attr:`SensorRig.T_cam_laser`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Literal

import numpy as np
import yaml
from pydantic import BeforeValidator, Field, PlainSerializer, ValidationError, WithJsonSchema, field_validator, model_validator

from dem_graph.config_types import StrictModel, format_validation_error
from dem_graph.errors import ConfigError
from dem_graph.geometry.camera import PinholeCamera
from dem_graph.geometry.se3 import check_pose, invert, make_pose, rotation_from_rpy


def _to_pose(value) -> np.ndarray:
    # the field name is attached by pydantic's error location; check_pose gives the problem
    try:
        return check_pose(value, "transform")
    except Exception as exc:  # turned into a pydantic validation error with the field's location
        raise ValueError(str(exc)) from None


Pose4x4 = Annotated[
    np.ndarray,
    BeforeValidator(_to_pose),
    PlainSerializer(lambda T: [[float(x) for x in row] for row in np.asarray(T)], return_type=list),
    WithJsonSchema({"type": "array", "items": {"type": "array", "items": {"type": "number"}}}),
]
"""A 4x4 rigid transform written as a nested list (row-major) in YAML."""


class CameraSpec(StrictModel):
    width_px: int = Field(800, gt=0, description="image width, pixels")
    height_px: int = Field(600, gt=0, description="image height, pixels")
    fx_px: float = Field(560.0, gt=0, description="focal length along x, pixels")
    fy_px: float = Field(560.0, gt=0, description="focal length along y, pixels")
    cx_px: float = Field(399.5, description="principal point x, pixels (OpenCV: pixel centres at integers)")
    cy_px: float = Field(299.5, description="principal point y, pixels")
    distortion: tuple[float, float, float, float, float] = Field(
        (-0.05, 0.01, 0.0, 0.0, 0.0), description="OpenCV radial-tangential coefficients k1, k2, p1, p2, k3"
    )
    rate_hz: float = Field(25.0, gt=0, description="frame rate, Hz")
    noise_sigma_dn: float = Field(2.0, ge=0, description="image noise standard deviation, grey levels (0-255)")
    T_body_cam: Pose4x4 = Field(description="camera pose in the body frame (camera axes OpenCV: x right, y down, z forward)")

    @property
    def model(self) -> PinholeCamera:
        return PinholeCamera(self.width_px, self.height_px, self.fx_px, self.fy_px, self.cx_px, self.cy_px, tuple(self.distortion))


class PlanarBeams(StrictModel):
    """A planar scanner's beams in the laser's x-y plane, angles from +x towards +y (ROS LaserScan)."""

    kind: Literal["planar"] = "planar"
    angle_min_rad: float = Field(-np.pi / 2, description="angle of the first beam, radians")
    angle_increment_rad: float = Field(np.radians(0.5), gt=0, description="angle between beams, radians")
    count: int = Field(361, gt=0, description="number of beams")

    def directions(self) -> np.ndarray:
        a = self.angle_min_rad + self.angle_increment_rad * np.arange(self.count)
        return np.stack([np.cos(a), np.sin(a), np.zeros_like(a)], axis=1)


class DirectionBeams(StrictModel):
    """Any per-beam unit directions in the laser frame (for example one ring of a multi-beam lidar)."""

    kind: Literal["directions"] = "directions"
    directions_xyz: list[tuple[float, float, float]] = Field(description="unit direction of each beam, laser frame")

    @field_validator("directions_xyz")
    @classmethod
    def _unit(cls, v):
        d = np.asarray(v, dtype=float)
        if len(d) == 0:
            raise ValueError("at least one beam direction is needed")
        if not np.all(np.isfinite(d)) or np.any(np.abs(np.linalg.norm(d, axis=1) - 1.0) > 1e-6):
            raise ValueError("every beam direction must be a finite unit vector")
        return v

    @property
    def count(self) -> int:
        return len(self.directions_xyz)

    def directions(self) -> np.ndarray:
        return np.asarray(self.directions_xyz, dtype=float)


class LaserSpec(StrictModel):
    T_body_laser: Pose4x4 = Field(description="laser pose in the body frame")
    beams: Annotated[PlanarBeams | DirectionBeams, Field(discriminator="kind")] = Field(default_factory=PlanarBeams)
    range_min_m: float = Field(0.1, ge=0, description="shortest valid range, metres")
    range_max_m: float = Field(30.0, gt=0, description="longest valid range, metres")
    range_sigma_m: float = Field(0.02, ge=0, description="range noise standard deviation, metres")
    rate_hz: float = Field(12.5, gt=0, description="scan rate, Hz")

    @model_validator(mode="after")
    def _ranges(self):
        if self.range_max_m <= self.range_min_m:
            raise ValueError("range_max_m must be larger than range_min_m")
        return self

    def beam_directions(self) -> np.ndarray:
        """(B,3) unit beam directions in the laser frame."""
        return self.beams.directions()

    def valid_ranges(self, ranges_m: np.ndarray, range_max_m: float | None = None) -> np.ndarray:
        """Mask of the ranges that are returns: finite and inside the range limits (the upper one
        lowered to ``range_max_m`` if given). NaN is "no return"."""
        r = np.asarray(ranges_m)  # compared in its own precision (the simulator's are float32)
        top = self.range_max_m if range_max_m is None else min(self.range_max_m, range_max_m)
        with np.errstate(invalid="ignore"):
            return np.isfinite(r) & (r >= self.range_min_m) & (r <= top)


class OdometrySpec(StrictModel):
    """Wheel odometry: rate and noise densities per square root of distance travelled."""

    rate_hz: float = Field(50.0, gt=0, description="odometry rate, Hz")
    sigma_scale: float = Field(0.01, ge=0, description="standard deviation of the distance scale error (slip), fraction")
    sigma_forward_m_per_sqrt_m: float = Field(0.01, ge=0, description="forward white noise, m per sqrt(m)")
    sigma_lateral_m_per_sqrt_m: float = Field(0.01, ge=0, description="lateral white noise, m per sqrt(m)")
    sigma_vertical_m_per_sqrt_m: float = Field(0.02, ge=0, description="vertical white noise, m per sqrt(m)")
    sigma_yaw_rad_per_sqrt_m: float = Field(np.radians(0.5), ge=0, description="yaw noise, rad per sqrt(m)")
    sigma_roll_pitch_rad_per_sqrt_m: float = Field(np.radians(1.0), ge=0, description="roll and pitch noise, rad per sqrt(m)")
    min_distance_m: float = Field(0.01, gt=0, description="distance floor for the noise model (standing still), m")

    def white_noise_covariance(self, distance_m: float) -> np.ndarray:
        """6x6 covariance of the independent (white) part of one increment over ``distance_m``,
        gtsam order [rot xyz, trans xyz], body frame."""
        d = max(float(distance_m), self.min_distance_m)
        rp, yaw = self.sigma_roll_pitch_rad_per_sqrt_m**2 * d, self.sigma_yaw_rad_per_sqrt_m**2 * d
        fwd = self.sigma_forward_m_per_sqrt_m**2 * d
        lat, vert = self.sigma_lateral_m_per_sqrt_m**2 * d, self.sigma_vertical_m_per_sqrt_m**2 * d
        return np.diag([rp, rp, yaw, fwd, lat, vert])

    def increment_covariance(self, distance_m: float) -> np.ndarray:
        """6x6 covariance of one increment: the white part plus the slip (scale) error along x."""
        cov = self.white_noise_covariance(distance_m)
        cov[3, 3] += (self.sigma_scale * max(float(distance_m), self.min_distance_m)) ** 2
        return cov


class SensorRig(StrictModel):
    """Everything a dataset says about its sensors."""

    camera: CameraSpec
    laser: LaserSpec
    odometry: OdometrySpec | None = Field(None, description="wheel odometry, when the vehicle has it")
    T_cam_laser_covariance: list[list[float]] | None = Field(
        None, description="6x6 covariance of T_cam_laser from calibration, gtsam order [rot, trans], rad^2 and m^2"
    )

    @field_validator("T_cam_laser_covariance")
    @classmethod
    def _cov(cls, v):
        if v is None:
            return v
        c = np.asarray(v, dtype=float)
        if c.shape != (6, 6) or not np.all(np.isfinite(c)) or not np.allclose(c, c.T, atol=1e-12):
            raise ValueError("must be a finite symmetric 6x6 matrix")
        return v

    @property
    def T_cam_laser(self) -> np.ndarray:
        """The paper's P_{L-C}: maps laser-frame points into the camera frame."""
        return invert(self.camera.T_body_cam) @ self.laser.T_body_laser

    @property
    def T_body_cam(self) -> np.ndarray:
        return self.camera.T_body_cam

    @property
    def T_body_laser(self) -> np.ndarray:
        return self.laser.T_body_laser

    @property
    def camera_model(self) -> PinholeCamera:
        return self.camera.model


def camera_mount(position_body_m, pitch_down_rad: float) -> np.ndarray:
    """``T_body_cam`` of a forward-looking camera at ``position_body_m``, pitched down by ``pitch_down_rad``."""
    s, c = np.sin(pitch_down_rad), np.cos(pitch_down_rad)
    # columns: camera x (right), y (down), z (forward) expressed in the body frame
    R = np.array([[0.0, -s, c], [-1.0, 0.0, 0.0], [0.0, -c, -s]])
    return make_pose(R, position_body_m)


def laser_mount(position_body_m, pitch_down_rad: float, yaw_rad: float = 0.0, roll_rad: float = 0.0) -> np.ndarray:
    """``T_body_laser`` of a scanner at ``position_body_m`` whose scan plane is tilted down by ``pitch_down_rad``."""
    return make_pose(rotation_from_rpy(roll_rad, pitch_down_rad, yaw_rad), position_body_m)


def default_rig() -> SensorRig:
    """The paper's set-up: 800x600 camera at 25 Hz, a planar laser at 12.5 Hz hitting flat ground about 3 m ahead."""
    laser_height_m = 1.2
    return SensorRig(
        camera=CameraSpec(T_body_cam=camera_mount([0.9, 0.0, 1.6], np.radians(20.0))),
        laser=LaserSpec(T_body_laser=laser_mount([1.0, 0.0, laser_height_m], np.arctan2(laser_height_m, 3.0))),
        odometry=OdometrySpec(),
    )


def rig_from_dict(data: dict, source: str | Path | None = None) -> SensorRig:
    try:
        return SensorRig.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(f"invalid rig: {format_validation_error(exc)}", source) from None


def load_rig(path: str | Path) -> SensorRig:
    """Read and validate a rig YAML file. Raises :class:`ConfigError` naming the file and the problem."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError("rig file not found", path)
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        raise ConfigError(f"not valid YAML ({str(exc).splitlines()[0]})", path) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"cannot read the rig file ({exc})", path) from None
    if not isinstance(data, dict):
        raise ConfigError("a rig file must hold a mapping with 'camera' and 'laser'", path)
    return rig_from_dict(data, path)


def rig_to_dict(rig: SensorRig) -> dict:
    return rig.model_dump(mode="json", exclude_none=True)


def save_rig(rig: SensorRig, path: str | Path) -> None:
    Path(path).write_text(yaml.safe_dump(rig_to_dict(rig), sort_keys=False, default_flow_style=None))
