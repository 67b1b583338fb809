"""The settings a vehicle's speed and its camera's frame rate decide (dem_graph/pipeline/derived.py):
the search cap from the image motion of the nearest ground between two frames, the focus area's
starting speed from the vehicle's; the paper's robot keeps every default, a value given anywhere wins."""

from __future__ import annotations

import logging
import math

import numpy as np
import pytest

from dem_graph.geometry.rig import CameraSpec, SensorRig, camera_mount, default_rig
from dem_graph.pipeline import RunConfig, run_config
from dem_graph.pipeline.derived import (
    DEFAULT_SEARCH_HALF_SIZE_PX,
    REFERENCE_RATE_HZ,
    REFERENCE_SPEED_MPS,
    derived_search_half_size_px,
    nearest_ground_motion_px,
)


def _pinhole_rig(f_px: float, size_px: tuple[int, int], height_m: float, pitch_deg: float) -> SensorRig:
    """The default rig with an undistorted camera of focal ``f_px`` at ``height_m``, pitched down ``pitch_deg``."""
    width, height = size_px
    camera = CameraSpec(
        width_px=width,
        height_px=height,
        fx_px=f_px,
        fy_px=f_px,
        cx_px=(width - 1) / 2,
        cy_px=(height - 1) / 2,
        distortion=(0.0, 0.0, 0.0, 0.0, 0.0),
        rate_hz=10.0,
        T_body_cam=camera_mount([0.5, 0.0, height_m], math.radians(pitch_deg)),
    )
    return default_rig().model_copy(update={"camera": camera})


def _pinhole_motion_px(f_px: float, size_px: tuple[int, int], height_m: float, pitch_deg: float, step_m: float) -> float:
    """The truth, by hand: the bottom centre pixel's ray meets the ground at D; after the step the
    point is D - step ahead, at row cy + f tan(atan(h / (D - step)) - pitch)."""
    cy = (size_px[1] - 1) / 2
    pitch = math.radians(pitch_deg)
    D = height_m / math.tan(pitch + math.atan((size_px[1] - 1 - cy) / f_px))
    return f_px * math.tan(math.atan(height_m / (D - step_m)) - pitch) - (size_px[1] - 1 - cy)


def test_the_image_motion_of_the_nearest_ground_is_the_pinhole_formula():
    for f_px, size, h_m, pitch_deg, step_m in ((500.0, (640, 480), 1.2, 15.0, 0.3), (718.0, (1242, 375), 1.65, 0.5, 1.2)):
        rig = _pinhole_rig(f_px, size, h_m, pitch_deg)
        assert nearest_ground_motion_px(rig, step_m) == pytest.approx(_pinhole_motion_px(f_px, size, h_m, pitch_deg, step_m), abs=1e-6)


def test_the_reference_robot_keeps_the_defaults(smoke_log):
    """1.5 m/s at 25 Hz on the paper's rig gives exactly the default 40 px; the smoke rig (a 224 px
    focal length: its ground moves 0.4 times as far) stays at the default too, never under it; and a
    run's whole configuration on a simulated log is the defaults, bit for bit."""
    assert derived_search_half_size_px(default_rig(), REFERENCE_SPEED_MPS, REFERENCE_RATE_HZ) == DEFAULT_SEARCH_HALF_SIZE_PX == 40
    assert derived_search_half_size_px(smoke_log.rig, 1.5, smoke_log.rig.camera.rate_hz) == 40
    assert run_config(smoke_log).model_dump(mode="json") == RunConfig().model_dump(mode="json")


def test_a_car_gets_the_search_its_motion_needs():
    """A KITTI-like camera (718 px, 1242x375, 1.65 m high, level) at 12 m/s and 10 Hz: 40 px times
    its nearest ground's motion over the reference's (hand formula above; the reference rig is
    distorted, so its motion is the function's, checked on undistorted rigs above); more at a
    lower rate, the default at a crawl."""
    car = _pinhole_rig(718.0, (1242, 375), 1.65, 0.0)
    reference_px = nearest_ground_motion_px(default_rig(), REFERENCE_SPEED_MPS / REFERENCE_RATE_HZ)
    expected = round(40 * _pinhole_motion_px(718.0, (1242, 375), 1.65, 0.0, 1.2) / reference_px)
    assert derived_search_half_size_px(car, 12.0, 10.0) == expected
    assert 100 < expected < 160  # 1.2 m a frame moves the ground 6.5 m ahead by about 47 px, the reference's 15 px
    assert derived_search_half_size_px(car, 12.0, 5.0) > expected
    assert derived_search_half_size_px(car, 0.5, 10.0) == 40


def test_a_value_given_wins_and_a_restated_default_is_derived(smoke_log, tmp_path, caplog):
    fast = tmp_path / "fast.yaml"
    fast.write_text("vehicle:\n  speed_mps: 6.0\nfrontend:\n  tracker:\n    max_search_half_size_px: 40\n")  # restates the default
    with caplog.at_level(logging.INFO, logger="dem_graph.pipeline.config"):
        config = run_config(smoke_log, fast)
    assert config.frontend.tracker.max_search_half_size_px == derived_search_half_size_px(smoke_log.rig, 6.0, 25.0) > 40
    assert config.frontend.focus.nominal_speed_mps == 6.0
    lines = [r.getMessage() for r in caplog.records if "vehicle.speed_mps" in r.getMessage()]
    assert lines == [
        f"settings from vehicle.speed_mps 6 m/s and the camera's 25 Hz (24 cm per frame): frontend.tracker.max_search_half_size_px "
        f"{config.frontend.tracker.max_search_half_size_px}, frontend.focus.nominal_speed_mps 6"
    ]
    given = tmp_path / "given.yaml"
    given.write_text(
        "vehicle:\n  speed_mps: 6.0\nfrontend:\n  tracker:\n    max_search_half_size_px: 55\n  focus:\n    nominal_speed_mps: 2.0\n"
    )
    config = run_config(smoke_log, given)
    assert (config.frontend.tracker.max_search_half_size_px, config.frontend.focus.nominal_speed_mps) == (55, 2.0)


def test_a_datasets_own_value_wins():
    from dem_graph.datasets.memory import InMemorySequence

    class CarLog(InMemorySequence):
        def run_settings(self) -> dict:
            return {"vehicle": {"speed_mps": 12.0}, "frontend": {"tracker": {"max_search_half_size_px": 80}}}

    log = CarLog(default_rig(), [], np.eye(4), 0.0)
    config = run_config(log)
    assert config.frontend.tracker.max_search_half_size_px == 80 and config.frontend.focus.nominal_speed_mps == 12.0


def test_without_a_dataset_nothing_is_derived(tmp_path):
    path = tmp_path / "car.yaml"
    path.write_text("vehicle:\n  speed_mps: 12.0\n")
    config = run_config(None, path)
    assert (config.frontend.tracker.max_search_half_size_px, config.frontend.focus.nominal_speed_mps) == (40, 1.5)
