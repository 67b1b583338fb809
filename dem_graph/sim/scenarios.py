"""Named scenarios: ready-made :class:`ScenarioConfig` values."""

from __future__ import annotations

from collections.abc import Callable

from pydantic import ValidationError

from dem_graph.config_types import format_validation_error
from dem_graph.errors import ConfigError
from dem_graph.geometry.rig import car_rig, default_rig
from dem_graph.sim.config import PathSpec, ScenarioConfig, TerrainSpec, TextureSpec


def _paper() -> ScenarioConfig:
    """The paper's set-up (section IV): 100 m at 1.5 m/s, 800x600 at 25 Hz, laser at 12.5 Hz hitting ~3 m ahead."""
    return ScenarioConfig(name="paper", length_m=100.0)


def _fast() -> ScenarioConfig:
    """As ``paper``, at 2 m/s."""
    return ScenarioConfig(name="fast", length_m=100.0, path=PathSpec(speed_mps=2.0))


def _demo() -> ScenarioConfig:
    """A 30 m drive with one turn: the README's demo, simulated in about a minute."""
    return ScenarioConfig(name="demo", length_m=30.0)


def _slope() -> ScenarioConfig:
    """Natural terrain on an 8 % slope."""
    return ScenarioConfig(name="slope", length_m=60.0, terrain=TerrainSpec(slope_percent=8.0))


def _flat() -> ScenarioConfig:
    """Perfectly flat ground (the flat-ground prior is true), textured; for exactness tests."""
    return ScenarioConfig(name="flat", length_m=30.0, terrain=TerrainSpec(kind="flat"))


def _smoke() -> ScenarioConfig:
    """A few metres at 320x240: for tests that must run in seconds."""
    rig = default_rig()
    s = 0.4
    cam = rig.camera.model_copy(update=dict(width_px=320, height_px=240, fx_px=560.0 * s, fy_px=560.0 * s, cx_px=159.5, cy_px=119.5))
    rig = rig.model_copy(update=dict(camera=cam))
    return ScenarioConfig(
        name="smoke",
        length_m=4.0,
        rig=rig,
        terrain=TerrainSpec(margin_m=6.0),
        path=PathSpec(first_straight_m=3.0, turn_radius_m=(6.0, 8.0)),
    )


def _car() -> ScenarioConfig:
    """A car at 7 m/s on a level road: a 16 Hz camera 1.4 m up, a 50 Hz bumper laser below its view, no odometry, no IMU."""
    road = TerrainSpec(
        undulation_amplitude_m=0.03, undulation_wavelengths_m=[10.0, 20.0, 40.0], roughness_m=0.004, bumps_per_100m2=0.1,
        bump_height_m=(0.03, 0.10), bump_radius_m=(0.8, 2.0), stones_per_100m2=1.0, stone_height_m=(0.03, 0.10), ruts_depth_m=0.0,
        ditch_depth_m=0.15, ditch_offset_m=-5.0, margin_m=16.0,
    )
    path = PathSpec(
        speed_mps=7.0, speed_variation=0.05, first_straight_m=25.0, straight_m=(30.0, 60.0), turn_radius_m=(30.0, 60.0), turn_angle_deg=(20.0, 45.0),
        wheelbase_m=2.7, track_m=1.55, tire_patch_m=0.12,
    )
    return ScenarioConfig(
        name="car", length_m=70.0, rig=car_rig(), with_odometry=False, with_imu=False, laser_time_offset_s=0.007, camera_encoding="bayer_gbrg8",
        terrain=road, texture=TextureSpec(grass_fraction=0.15, patch_size_m=4.0), path=path,
    )


SCENARIOS: dict[str, Callable[[], ScenarioConfig]] = {
    "paper": _paper,
    "fast": _fast,
    "demo": _demo,
    "slope": _slope,
    "flat": _flat,
    "smoke": _smoke,
    "car": _car,
}

DEFAULT_SCENARIO = "demo"


def scenario(
    name: str, seed: int | None = None, length_m: float | None = None, speed_mps: float | None = None, with_odometry: bool | None = None,
    with_imu: bool | None = None,
) -> ScenarioConfig:
    """The named scenario's configuration, with optional overrides."""
    if name not in SCENARIOS:
        raise ConfigError(f"unknown scenario '{name}'; choose one of: {', '.join(SCENARIOS)}")
    config = SCENARIOS[name]()
    update = {}
    if seed is not None:
        update["seed"] = seed
    if length_m is not None:
        update["length_m"] = length_m
    if with_odometry is not None:
        update["with_odometry"] = with_odometry
    if with_imu is not None:
        update["with_imu"] = with_imu
    if speed_mps is not None:
        update["path"] = {**config.path.model_dump(), "speed_mps": speed_mps}
    try:
        return ScenarioConfig.model_validate({**config.model_dump(), **update}) if update else config
    except ValidationError as exc:
        raise ConfigError(f"invalid scenario '{name}': {format_validation_error(exc)}") from None


def describe_scenarios() -> dict[str, str]:
    return {name: (fn.__doc__ or "").strip().splitlines()[0] for name, fn in SCENARIOS.items()}


__all__ = ["DEFAULT_SCENARIO", "SCENARIOS", "describe_scenarios", "scenario"]
