"""The simulator's car: a pushbroom rig (a 16 Hz camera 1.4 m up and 2 degrees down, a 50 Hz 541-beam
laser on the bumper meeting the road below the camera's view), 7 m/s, no odometry, no IMU, and a bag
with the camera's raw Bayer images."""

from __future__ import annotations

import numpy as np
import pytest
from click.testing import CliRunner

from dem_graph.cli import main
from dem_graph.datasets import CameraFrame, FolderSequence, LaserScan, Odometry
from dem_graph.datasets.open import DatasetOptions, open_dataset
from dem_graph.geometry.ground_view import laser_view
from dem_graph.sim.scenarios import scenario


def test_the_car_scenario_has_the_pushbroom_geometry():
    config = scenario("car")
    rig = config.rig
    assert config.path.speed_mps == 7.0 and rig.camera.rate_hz == 16.0 and rig.laser.rate_hz == 50.0
    beams = rig.laser.beams
    assert beams.count == 541 and np.degrees((beams.count - 1) * beams.angle_increment_rad) == pytest.approx(270.0)
    assert not config.with_odometry and not config.with_imu and rig.odometry is None and rig.imu is None
    assert rig.T_body_cam[2, 3] == pytest.approx(1.4)
    optical_axis_body = rig.T_body_cam[:3, 2]
    assert np.degrees(np.arcsin(-optical_axis_body[2])) == pytest.approx(2.0)
    assert rig.T_body_laser[2, 3] == pytest.approx(0.33)
    view = laser_view(rig)
    assert not view.in_view and view.laser_ahead_m < view.camera_nearest_m
    assert config.camera_encoding == "bayer_gbrg8"


@pytest.fixture(scope="module")
def car(tmp_path_factory):
    """The car's first 2.5 m (0.36 s: 6 frames, 18 scans), as a dataset folder and a ROS 2 bag."""
    out = tmp_path_factory.mktemp("car")
    result = CliRunner().invoke(
        main, ["--no-progress", "simulate", "--scenario", "car", "--length-m", "2.5", "--out", str(out / "ds"), "--bag", str(out / "bag")]
    )
    assert result.exit_code == 0, result.output
    return out / "ds", out / "bag", result.output


def test_the_car_bag_carries_bayer_images_that_read_as_the_grey_ones(car):
    """The bag's images are bayer_gbrg8 (the grey scene as a colour camera of equal channel gains
    records it); read back, OpenCV's demosaic to grey gives the folder's images to within the
    demosaic's own interpolation: 1 grey level median, the same image (correlation above 0.99).
    The bag has no odometry and no IMU, and its scans have 541 beams."""
    folder, bag, output = car
    assert "images bayer_gbrg8" in output and "/odom" not in output and "/imu/data" not in output
    from rosbags.highlevel import AnyReader

    with AnyReader([bag]) as reader:
        encodings = {reader.deserialize(raw, c.msgtype).encoding for c, _, raw in reader.messages([c for c in reader.connections if c.topic == "/camera/image_raw"])}
    assert encodings == {"bayer_gbrg8"}
    grey = [e.image for e in FolderSequence(folder).events() if isinstance(e, CameraFrame)]
    events = list(open_dataset(bag, "rosbag", DatasetOptions(image_topic="/camera/image_raw", scan_topic="/scan")).events())
    from_bag = [e.image for e in events if isinstance(e, CameraFrame)]
    assert len(from_bag) == len(grey) == 6
    assert not any(isinstance(e, Odometry) for e in events)
    assert {len(e.ranges_m) for e in events if isinstance(e, LaserScan)} == {541}
    for a, b in zip(grey, from_bag):
        d = np.abs(a.astype(float) - b.astype(float))
        assert np.median(d) <= 1.0
        assert np.corrcoef(a.ravel(), b.ravel())[0, 1] > 0.99


def test_the_ground_motion_between_frames_is_the_cars_own(car):
    """GroundMotion on the car's first frames (7.2 m/s at 16 Hz: 0.452 m a frame by the simulator's
    truth): each pair's forward shift within two of its own standard deviations of the truth
    (measured: within 0.05 m, its sigma 0.055 m), the lateral one within 2 cm (it drives straight)."""
    from dem_graph.frontend.ground_motion import GroundMotion, GroundMotionConfig
    from dem_graph.geometry.se3 import invert

    folder, _, _ = car
    seq = FolderSequence(folder)
    frames = [e for e in seq.events() if isinstance(e, CameraFrame)]
    ground = GroundMotion(GroundMotionConfig(), seq.rig)
    assert ground.problem is None
    truth = seq.ground_truth.trajectory
    for a, b in zip(frames, frames[1:]):
        shift = ground.shift(ground.top_view(a.image), ground.top_view(b.image), b.t_s - a.t_s)
        assert not isinstance(shift, str), shift
        T = truth.at(np.array([a.t_s, b.t_s]))
        step = invert(T[0]) @ T[1]
        assert abs(shift.forward_m - step[0, 3]) <= 2.0 * shift.sigma_m, (shift, step[0, 3])
        assert abs(shift.lateral_m - step[1, 3]) <= 0.02


@pytest.fixture(scope="module")
def car_street(tmp_path_factory):
    """The car's first 20 m (2.8 s, 46 frames), as a dataset folder."""
    out = tmp_path_factory.mktemp("car_street") / "ds"
    result = CliRunner().invoke(main, ["--no-progress", "simulate", "--scenario", "car", "--length-m", "20", "--out", str(out)])
    assert result.exit_code == 0, result.output
    return out


def _run(folder, out, estimator: str, config_text: str | None = None):
    import json

    args = ["--no-progress", "run", str(folder), "--estimator", estimator, "--out", str(out)]
    if config_text is not None:
        (out.parent / f"{out.name}.yaml").write_text(config_text)
        args += ["--config", str(out.parent / f"{out.name}.yaml")]
    result = CliRunner().invoke(main, args)
    return result, json.loads((out / "metrics.json").read_text())


def test_the_car_starts_at_its_speed_untold(car_street, tmp_path):
    """No speed given, no odometry, no IMU: the graph estimator measures the speed from the ground on
    its second frame and tracks from there: over half of the searches match, and the path's length is
    the truth's within 3 % (measured: 0.1 %). Without the ground's motion (today's start, at 0 m/s),
    every search is too large, the run fails in its last line and exits with 3."""
    truth = FolderSequence(car_street).ground_truth.trajectory
    result, metrics = _run(car_street, tmp_path / "untold", "isam2")
    assert result.exit_code == 0, result.output
    assert metrics["tracking"]["matched_fraction"] > 0.5 and metrics["events"]["ground_motion_measured"] >= 1
    from dem_graph.io.tum import read_tum

    estimate = read_tum(tmp_path / "untold" / "trajectory.tum")
    driven = truth.slice(float(estimate.t_s[0]), float(estimate.t_s[-1]))
    assert estimate.path_length_m == pytest.approx(driven.path_length_m, rel=0.03)
    result, metrics = _run(car_street, tmp_path / "off", "isam2", "frontend:\n  ground_motion:\n    enabled: false\n")
    assert result.exit_code == 3 and metrics["status"] == "failed"
    assert metrics["tracking"]["failed_fraction"]["search_too_large"] > 0.9


@pytest.fixture(scope="module")
def car_street_mis_mounted(car_street, tmp_path_factory):
    """The car's first 20 m with its rig.yaml's camera 7 cm higher and 2 degrees further down than it
    was (the laser moved with it: the laser-camera transform is a calibration's); the rest linked."""
    from dem_graph.datasets.folder import with_rig
    from dem_graph.geometry.rig import camera_remounted, load_rig

    out = tmp_path_factory.mktemp("car_street_mis_mounted") / "ds"
    return with_rig(car_street, out, camera_remounted(load_rig(car_street / "rig.yaml"), 0.07, np.radians(2.0)))


def test_the_laser_below_the_view_gives_the_scale_and_the_level_on_a_rig_mounted_wrong(car_street, car_street_mis_mounted, tmp_path, caplog):
    """The laser's line never in the image, the camera's mount 2 degrees and 7 cm off: isam2 ties the
    landmarks to the scans of their ground (on by itself for this rig), finds the mount off from the
    ground of the first second (a warning) and levels the world from it. The path's length is the
    truth's within 2 % (the issue's bound; measured 0.2 %). Without the ties the camera's mount sets
    the scale: over 5 % short (measured 12.9 %); the DEM's height error over the laser's cells with
    the ties under a quarter of that without (measured 6.9 against 36.7 cm: the pitch still drifts
    some tenths of a degree without gravity, docs/pushbroom.md)."""
    from dem_graph.io.tum import read_tum

    truth = FolderSequence(car_street).ground_truth.trajectory

    def scale_error(out):
        estimate = read_tum(out / "trajectory.tum")
        return estimate.path_length_m / truth.slice(float(estimate.t_s[0]), float(estimate.t_s[-1])).path_length_m - 1.0

    result, tied = _run(car_street_mis_mounted, tmp_path / "tied", "isam2")
    assert result.exit_code == 0, result.output
    assert tied["events"]["laser_ties"] > 500 and tied["events"]["laser_ties_level"] > 50
    # the mount found off: the ground of the first second tilted beyond the 1 degree that decides (measured 1.7 degrees, 6 cm up;
    # the start pose, free, has already taken some of the 2 degrees by then)
    assert "the camera's and laser's mount in the rig is probably off" in caplog.text
    assert tied["events"]["laser_start_ground_tilt_mdeg"] > 1000
    assert abs(scale_error(tmp_path / "tied")) < 0.02
    result, untied = _run(car_street_mis_mounted, tmp_path / "untied", "isam2", "isam2:\n  laser_ties: 'off'\n")
    assert result.exit_code == 0, result.output
    assert "laser_ties" not in untied["events"]
    assert scale_error(tmp_path / "untied") < -0.05
    dem_tied, dem_untied = (m["dem"]["height_error_laser_cells"]["rmse_m"] for m in (tied, untied))
    assert dem_tied < 0.25 * dem_untied
