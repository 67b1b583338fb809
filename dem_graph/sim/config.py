"""Typed configuration of the simulator: terrain, ground texture, vehicle path and scenario.

Every field has a default, a unit in its name or description, and is validated on load.
"""

from __future__ import annotations

from pydantic import Field, model_validator

from dem_graph.config_types import StrictModel
from dem_graph.geometry.rig import SensorRig, default_rig


class TerrainSpec(StrictModel):
    kind: str = Field("natural", pattern="^(natural|flat|slope|sinusoid)$", description="natural relief, or an analytic surface for tests")
    resolution_m: float = Field(0.04, gt=0.005, le=0.2, description="heightfield cell size, metres (ground truth resolution)")
    margin_m: float = Field(14.0, ge=0, description="terrain extent beyond the driven path, metres")
    undulation_amplitude_m: float = Field(0.25, ge=0, description="standard deviation of the gentle relief, metres")
    undulation_wavelengths_m: list[float] = Field([5.0, 10.0, 20.0], description="feature sizes of the gentle relief, metres")
    slope_percent: float = Field(0.0, description="overall slope, percent (rise per run)")
    slope_azimuth_deg: float = Field(30.0, description="direction of steepest ascent, degrees from +x towards +y")
    roughness_m: float = Field(0.008, ge=0, description="standard deviation of the fine roughness, metres")
    roughness_wavelength_m: float = Field(0.12, gt=0, description="feature size of the fine roughness, metres")
    bumps_per_100m2: float = Field(1.5, ge=0, description="mounds per 100 square metres")
    bump_height_m: tuple[float, float] = Field((0.05, 0.30), description="mound height range, metres")
    bump_radius_m: tuple[float, float] = Field((0.4, 1.2), description="mound radius range, metres")
    stones_per_100m2: float = Field(12.0, ge=0, description="stones per 100 square metres")
    stone_height_m: tuple[float, float] = Field((0.05, 0.30), description="stone height range, metres")
    stone_density_on_track: float = Field(0.1, ge=0, le=1, description="stone density within the wheel corridor, as a fraction")
    ruts_depth_m: float = Field(0.06, ge=0, description="depth of the two wheel ruts along the path, metres (0: none)")
    ruts_width_m: float = Field(0.30, gt=0, description="width of each rut, metres")
    ditch_depth_m: float = Field(0.35, ge=0, description="depth of the ditch beside the path, metres (0: none)")
    ditch_width_m: float = Field(1.2, gt=0, description="width of the ditch, metres")
    ditch_offset_m: float = Field(-3.0, description="lateral offset of the ditch from the path, metres (positive: left)")
    sinusoid_amplitude_m: float = Field(0.2, ge=0, description="'sinusoid' kind: amplitude, metres")
    sinusoid_wavelength_m: float = Field(6.0, gt=0, description="'sinusoid' kind: wavelength, metres")


class TextureSpec(StrictModel):
    texel_m: float = Field(0.01, gt=0.001, le=0.1, description="finest texture cell, metres")
    grass_fraction: float = Field(0.45, ge=0, le=1, description="fraction of the ground covered by grass")
    patch_size_m: float = Field(3.0, gt=0, description="typical size of soil and grass patches, metres")
    soil_albedo: float = Field(0.45, gt=0, lt=1, description="mean reflectance of soil")
    grass_albedo: float = Field(0.28, gt=0, lt=1, description="mean reflectance of grass")
    contrast: float = Field(1.0, ge=0, description="scale of the fine texture's contrast (1: default)")


class LightingSpec(StrictModel):
    sun_elevation_deg: float = Field(50.0, gt=0, le=90, description="sun elevation above the horizon, degrees")
    sun_azimuth_deg: float = Field(120.0, description="sun azimuth, degrees from +x towards +y")
    ambient: float = Field(0.35, ge=0, le=1, description="share of diffuse sky light")
    exposure: float = Field(1.1, gt=0, description="grey levels per unit radiance, times 255")
    vignetting: float = Field(0.15, ge=0, lt=1, description="brightness loss in the image corners, fraction")
    sky_dn: float = Field(215.0, ge=0, le=255, description="grey level of the sky")


class PathSpec(StrictModel):
    speed_mps: float = Field(1.5, gt=0, description="mean speed, m/s")
    speed_variation: float = Field(0.08, ge=0, lt=1, description="relative amplitude of slow speed changes")
    first_straight_m: float = Field(8.0, ge=0, description="straight run at the start, metres")
    straight_m: tuple[float, float] = Field((6.0, 15.0), description="length range of straights between turns, metres")
    turn_radius_m: tuple[float, float] = Field((8.0, 20.0), description="turn radius range, metres")
    turn_angle_deg: tuple[float, float] = Field((30.0, 90.0), description="turn angle range, degrees")
    wheelbase_m: float = Field(1.4, gt=0, description="distance between axles, metres")
    track_m: float = Field(1.1, gt=0, description="distance between left and right wheels, metres")
    tire_patch_m: float = Field(0.08, gt=0, description="terrain smoothing under a tyre (standard deviation), metres")


class ScenarioConfig(StrictModel):
    """A complete simulated data set: world, vehicle, sensors, duration."""

    name: str = Field("custom", description="scenario name")
    seed: int = Field(0, ge=0, description="random seed: the same seed gives the same dataset")
    length_m: float = Field(100.0, gt=0, description="distance driven, metres")
    rig: SensorRig = Field(default_factory=default_rig)
    with_odometry: bool = Field(True, description="simulate wheel odometry")
    with_imu: bool = Field(True, description="simulate the rig's IMU (when it has one)")
    laser_time_offset_s: float = Field(0.013, description="laser clock offset from the camera's first frame, seconds")
    odometry_time_offset_s: float = Field(0.005, description="odometry clock offset, seconds")
    ground_truth_rate_hz: float = Field(200.0, gt=0, description="rate of the ground-truth trajectory, Hz")
    terrain: TerrainSpec = Field(default_factory=TerrainSpec)
    texture: TextureSpec = Field(default_factory=TextureSpec)
    lighting: LightingSpec = Field(default_factory=LightingSpec)
    path: PathSpec = Field(default_factory=PathSpec)
    straight_path: bool = Field(False, description="drive a straight line (analytic tests)")
    camera_encoding: str = Field(
        "mono8", pattern="^(mono8|bayer_(rggb|bggr|gbrg|grbg)8)$",
        description="how a bag written from the log (simulate --bag) carries the images: mono8, or a colour camera's raw Bayer mosaic (bayer_gbrg8, ...) of the grey scene",
    )

    @model_validator(mode="after")
    def _check(self):
        if not 0 <= self.laser_time_offset_s < 1.0 / self.rig.laser.rate_hz:
            raise ValueError("laser_time_offset_s must lie within one laser period")
        return self

    @property
    def duration_s(self) -> float:
        return self.length_m / self.path.speed_mps
