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
