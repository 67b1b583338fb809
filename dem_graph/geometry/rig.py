"""The sensor rig: camera intrinsics, extrinsics, laser beams, rates and noise figures.

Loaded from and written to YAML (:func:`load_rig`, :func:`save_rig`), validated on load.
Extrinsics are ``T_body_cam`` and ``T_body_laser``; the paper's P_{L-C} is
:attr:`SensorRig.T_cam_laser`.

Every value a run uses is checked where the models are made, once, whatever the source (a rig
file, a bag's rig and tf, a KITTI calibration): focal lengths, rates and noise figures finite and
positive, the principal point inside the image, the distortion finite, the transforms rigid, the
laser's range limits and beams sound. A bad value is a :class:`ConfigError` naming the source and
the field, as in ``rig.yaml: camera.cx_px is nan; it must be a finite pixel coordinate inside the image``.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated, Literal, TypeVar

import numpy as np
import yaml
from pydantic import (
    AfterValidator,
    BaseModel,
    BeforeValidator,
    Field,
    PlainSerializer,
    ValidationError,
    ValidationInfo,
    WithJsonSchema,
    field_validator,
)

from dem_graph.config_types import StrictModel
from dem_graph.errors import ConfigError
from dem_graph.geometry.camera import PinholeCamera
from dem_graph.geometry.se3 import check_pose, invert, make_pose, rotation_from_rpy


def _to_pose(value) -> np.ndarray:
    # the field name is attached by pydantic's error location; check_pose gives the problem
    try:
        return check_pose(value, "")
    except ConfigError as exc:  # turned into a pydantic validation error with the field's location
        raise ValueError(exc.problem.strip()) from None


def _refuse(value, requirement: str):
    """The error of a field whose ``value`` breaks ``requirement`` (read after the field's name)."""
    return ValueError(f"is {value!r}; it must be {requirement}")


def _finite(requirement: str, minimum: float = -math.inf, strictly: bool = False):
    """A validator: the value is finite and at least (``strictly``: above) ``minimum``, else refused
    with ``requirement``."""

    def check(value: float) -> float:
        low_ok = value > minimum if strictly else value >= minimum
        if not (math.isfinite(value) and low_ok):
            raise _refuse(value, requirement)
        return value

    return AfterValidator(check)


PositiveFloat = Annotated[float, _finite("a finite number above 0", 0.0, strictly=True)]
"""A finite float above 0 (rates, focal lengths)."""
NonNegativeFloat = Annotated[float, _finite("a finite number, 0 or more", 0.0)]
"""A finite float of 0 or more (noise figures)."""
FiniteFloat = Annotated[float, _finite("a finite number")]
"""Any finite float (angles)."""


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
    fx_px: PositiveFloat = Field(560.0, description="focal length along x, pixels")
    fy_px: PositiveFloat = Field(560.0, description="focal length along y, pixels")
    cx_px: float = Field(399.5, description="principal point x, pixels (OpenCV: pixel centres at integers), inside the image")
    cy_px: float = Field(299.5, description="principal point y, pixels, inside the image")
    distortion: tuple[float, float, float, float, float] = Field(
        (-0.05, 0.01, 0.0, 0.0, 0.0), description="OpenCV radial-tangential coefficients k1, k2, p1, p2, k3"
    )
    rate_hz: PositiveFloat = Field(25.0, description="frame rate, Hz")
    noise_sigma_dn: NonNegativeFloat = Field(2.0, description="image noise standard deviation, grey levels (0-255)")
    T_body_cam: Pose4x4 = Field(description="camera pose in the body frame (camera axes OpenCV: x right, y down, z forward)")

    @field_validator("cx_px", "cy_px")
    @classmethod
    def _inside_image(cls, value: float, info: ValidationInfo) -> float:
        size_px = info.data.get("width_px" if info.field_name == "cx_px" else "height_px")
        inside = math.isfinite(value) and (size_px is None or -0.5 <= value <= size_px - 0.5)
        if not inside:
            span = "" if size_px is None else f" (-0.5 to {size_px - 0.5:g})"
            raise _refuse(value, f"a finite pixel coordinate inside the image{span}")
        return value

    @field_validator("distortion")
    @classmethod
    def _finite_distortion(cls, value: tuple) -> tuple:
        for name, k in zip(("k1", "k2", "p1", "p2", "k3"), value):
            if not math.isfinite(k):
                raise ValueError(f"has {name} = {k!r}; every coefficient must be a finite number")
        return value

    @property
    def model(self) -> PinholeCamera:
        return PinholeCamera(self.width_px, self.height_px, self.fx_px, self.fy_px, self.cx_px, self.cy_px, tuple(self.distortion))


class PlanarBeams(StrictModel):
    """A planar scanner's beams in the laser's x-y plane, angles from +x towards +y (ROS LaserScan)."""

    kind: Literal["planar"] = "planar"
    angle_min_rad: FiniteFloat = Field(-np.pi / 2, description="angle of the first beam, radians")
    angle_increment_rad: PositiveFloat = Field(np.radians(0.5), description="angle between beams, radians")
    count: int = Field(361, gt=0, description="number of beams")

    @field_validator("count")
    @classmethod
    def _at_most_a_turn(cls, value: int, info: ValidationInfo) -> int:
        step_rad = info.data.get("angle_increment_rad")
        if step_rad is not None and (value - 1) * step_rad > 2.0 * np.pi + 1e-9:
            raise ValueError(f"is {value}; {value} beams every {step_rad:g} rad span more than a full turn")
        return value

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
    range_min_m: NonNegativeFloat = Field(0.1, description="shortest valid range, metres")
    range_max_m: PositiveFloat = Field(30.0, description="longest valid range, metres, above range_min_m")
    range_sigma_m: NonNegativeFloat = Field(0.02, description="range noise standard deviation, metres")
    rate_hz: PositiveFloat = Field(12.5, description="scan rate, Hz")

    @field_validator("range_max_m")
    @classmethod
    def _above_range_min(cls, value: float, info: ValidationInfo) -> float:
        range_min_m = info.data.get("range_min_m")
        if range_min_m is not None and value <= range_min_m:
            raise _refuse(value, f"larger than range_min_m = {range_min_m!r}")
        return value

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

    rate_hz: PositiveFloat = Field(50.0, description="odometry rate, Hz")
    sigma_scale: NonNegativeFloat = Field(0.01, description="standard deviation of the distance scale error (slip), fraction")
    sigma_forward_m_per_sqrt_m: NonNegativeFloat = Field(0.01, description="forward white noise, m per sqrt(m)")
    sigma_lateral_m_per_sqrt_m: NonNegativeFloat = Field(0.01, description="lateral white noise, m per sqrt(m)")
    sigma_vertical_m_per_sqrt_m: NonNegativeFloat = Field(0.02, description="vertical white noise, m per sqrt(m)")
    sigma_yaw_rad_per_sqrt_m: NonNegativeFloat = Field(np.radians(0.5), description="yaw noise, rad per sqrt(m)")
    sigma_roll_pitch_rad_per_sqrt_m: NonNegativeFloat = Field(np.radians(1.0), description="roll and pitch noise, rad per sqrt(m)")
    min_distance_m: PositiveFloat = Field(0.01, description="distance floor for the noise model (standing still), m")

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

    def covariance_of(self, T_prev_curr: np.ndarray) -> np.ndarray:
        """:meth:`increment_covariance` for the increment ``T_prev_curr``: its length is the norm of its translation."""
        return self.increment_covariance(float(np.linalg.norm(np.asarray(T_prev_curr)[:3, 3])))


# The simulated IMU's default part: the Bosch BMI270 (datasheet BST-BMI270-DS000, as quoted by
# docs.luxonis.com/hardware/platform/sensors/imu/bmi270): accelerometer noise density 0.16 mg/sqrt(Hz),
# gyroscope 0.007 deg/s/sqrt(Hz) (performance mode). The datasheet gives no bias random walk; the
# defaults below are assumptions of the usual order for such parts, not datasheet figures.
_G_MPS2 = 9.80665


class ImuSpec(StrictModel):
    """A 3-axis gyroscope and accelerometer: rate, mounting and the continuous-time noise model
    (white noise densities and bias random walks, per axis, the convention of Kalibr and gtsam)."""

    part: str = Field("Bosch BMI270", description="the part the noise figures come from (documentation only)")
    rate_hz: PositiveFloat = Field(200.0, description="sample rate, Hz")
    T_body_imu: Pose4x4 = Field(default_factory=lambda: np.eye(4), description="IMU pose in the body frame")
    gyro_noise_density: NonNegativeFloat = Field(
        math.radians(0.007), description="gyroscope white noise, rad/s/sqrt(Hz) (BMI270 datasheet: 0.007 deg/s/sqrt(Hz))"
    )
    accel_noise_density: NonNegativeFloat = Field(
        0.16e-3 * _G_MPS2, description="accelerometer white noise, m/s^2/sqrt(Hz) (BMI270 datasheet: 0.16 mg/sqrt(Hz))"
    )
    gyro_bias_random_walk: NonNegativeFloat = Field(2.0e-5, description="gyroscope bias random walk, rad/s^2/sqrt(Hz) (assumed)")
    accel_bias_random_walk: NonNegativeFloat = Field(3.0e-4, description="accelerometer bias random walk, m/s^3/sqrt(Hz) (assumed)")
    gyro_bias_sigma: NonNegativeFloat = Field(
        math.radians(0.05), description="gyroscope bias at the start, standard deviation, rad/s (after a standstill calibration; assumed)"
    )
    accel_bias_sigma: NonNegativeFloat = Field(0.02, description="accelerometer bias at the start, standard deviation, m/s^2 (assumed)")
    gravity_mps2: PositiveFloat = Field(_G_MPS2, description="gravity's magnitude, along the world's -z, m/s^2")


class SensorRig(StrictModel):
    """Everything a dataset says about its sensors."""

    camera: CameraSpec
    laser: LaserSpec
    odometry: OdometrySpec | None = Field(None, description="wheel odometry, when the vehicle has it")
    imu: ImuSpec | None = Field(None, description="an inertial measurement unit, when the vehicle has one")
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
    def T_body_imu(self) -> np.ndarray:
        if self.imu is None:
            raise ValueError("the rig has no IMU")
        return self.imu.T_body_imu

    @property
    def camera_model(self) -> PinholeCamera:
        return self.camera.model


def camera_mount(position_body_m, pitch_down_rad: float) -> np.ndarray:
    """``T_body_cam`` of a forward-looking camera at ``position_body_m``, pitched down by ``pitch_down_rad``."""
    s, c = np.sin(pitch_down_rad), np.cos(pitch_down_rad)
    # columns: camera x (right), y (down), z (forward) expressed in the body frame
    R = np.array([[0.0, -s, c], [-1.0, 0.0, 0.0], [0.0, -c, -s]])
    return make_pose(R, position_body_m)


def camera_remounted(rig: SensorRig, raise_m: float, pitch_down_more_rad: float) -> SensorRig:
    """``rig`` with its camera raised by ``raise_m`` and pitched further down by ``pitch_down_more_rad``
    (a camera of :func:`camera_mount`'s kind), the laser moved with it (``T_cam_laser`` kept, as a
    laser-camera calibration gives it): a rig whose camera mount was guessed wrong, for studies."""
    T_body_cam = np.asarray(rig.T_body_cam, dtype=float)
    pitch_down_rad = float(np.arcsin(-T_body_cam[2, 2]))
    T_new = camera_mount(T_body_cam[:3, 3] + [0.0, 0.0, raise_m], pitch_down_rad + pitch_down_more_rad)
    camera = rig.camera.model_copy(update={"T_body_cam": T_new})
    laser = rig.laser.model_copy(update={"T_body_laser": T_new @ rig.T_cam_laser})
    return rig.model_copy(update={"camera": camera, "laser": laser})


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
        # at the body origin, its board turned a quarter turn: gtsam's lever-arm correction leaves out
        # the angular acceleration's term, which the terrain's vibration would make centimetres a second
        imu=ImuSpec(T_body_imu=make_pose(rotation_from_rpy(0.0, 0.0, np.pi / 2), [0.0, 0.0, 0.0])),
    )


def car_rig() -> SensorRig:
    """A car's pushbroom rig: a 640x480 camera at 16 Hz, 1.4 m up and pitched 2 degrees down, seeing
    the road from 3.9 m ahead (its vertical field of view 35.5 degrees, as a stereo head's cropped to
    the road); a 50 Hz, 541-beam laser over 270 degrees on the front bumper, 0.8 m ahead of the
    camera and 0.33 m above the road, its line meeting the road 1.7 m ahead of it (2.5 m ahead of
    the body origin): below the camera's view. No odometry, no IMU. The body origin is on the road
    under the camera."""
    laser_height_m, laser_ahead_m = 0.33, 1.7
    return SensorRig(
        camera=CameraSpec(
            width_px=640, height_px=480, fx_px=750.0, fy_px=750.0, cx_px=319.5, cy_px=239.5, distortion=(0.0, 0.0, 0.0, 0.0, 0.0),
            rate_hz=16.0, T_body_cam=camera_mount([0.0, 0.0, 1.4], np.radians(2.0)),
        ),
        laser=LaserSpec(
            T_body_laser=laser_mount([0.8, 0.0, laser_height_m], np.arctan2(laser_height_m, laser_ahead_m)),
            beams=PlanarBeams(angle_min_rad=-np.radians(135.0), angle_increment_rad=np.radians(0.5), count=541),
            range_max_m=50.0, range_sigma_m=0.02, rate_hz=50.0,
        ),
    )


Model = TypeVar("Model", bound=BaseModel)


_UNION_TAGS: dict[str, set[str]] = {"beams": {m.model_fields["kind"].default for m in (PlanarBeams, DirectionBeams)}}
"""The tags of each tagged union's members, by the union field's name."""


def _field_path(loc: tuple) -> str:
    """A pydantic location as the file's field path: without the member's tag pydantic puts after a
    tagged union's field (``laser.beams.planar.count`` is ``laser.beams.count`` in the file)."""
    parts: list[str] = []
    for x in (str(x) for x in loc if x != ""):
        if not (parts and x in _UNION_TAGS.get(parts[-1], ())):
            parts.append(x)
    return ".".join(parts)


def _problem(error: dict, field_prefix: str) -> str:
    """One pydantic error as ``field problem``: a check of this module reads on after the field's name."""
    loc = _field_path((field_prefix, *error["loc"])) or "(top level)"
    if error["type"] == "value_error":
        return f"{loc} {error['ctx']['error']}"
    return f"{loc}: {error['msg']}"


def validated(model: type[Model], data: dict, source: str | Path | None = None, field_prefix: str = "") -> Model:
    """``model`` made from ``data``. A bad value is a :class:`ConfigError` naming ``source`` and the
    field (``field_prefix`` put before its path, e.g. "camera" for a :class:`CameraSpec`)."""
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        raise ConfigError("; ".join(_problem(e, field_prefix) for e in exc.errors()), source) from None


def rig_from_dict(data: dict, source: str | Path | None = None) -> SensorRig:
    """A validated rig from a mapping; a bad value is a :class:`ConfigError` naming ``source`` and the field."""
    return validated(SensorRig, data, source)


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
