"""The rig from the bag: a simulated drive written as a ROS 1 bag (CameraInfo's D, K, R, P; /tf in two
message types) and as a ROS 2 MCAP bag, the way robots record them (zero odometry covariances,
base_footprint -> base_link -> sensors in /tf_static), runs with only its topics named: the rig read
from the bag equals the simulation's true rig (intrinsics and extrinsics to 1e-9, beams exactly) and
the trajectory follows the folder run's with the true rig to 5 mm. What the bag lacks is one line
naming the topic, the frame or the message."""

from __future__ import annotations

import numpy as np
import pytest

from dem_graph.datasets.open import DatasetOptions, open_dataset
from dem_graph.errors import DatasetError
from dem_graph.geometry.rig import load_rig, rig_to_dict

pytest.importorskip("rosbags")
from robot_bags import CAMERA_FRAME, IMAGE, INFO, LASER_FRAME, ODOM, SCAN, BagEdits, f32_beams, write_robot_bag  # noqa: E402

TOPICS = DatasetOptions(image_topic=IMAGE, scan_topic=SCAN, odometry_topic=ODOM)


@pytest.fixture(scope="module")
def drive(tmp_path_factory):
    """A 2 m `smoke` drive (no IMU) whose laser has float32 beam angles and range limits, as a LaserScan carries them."""
    from dem_graph.sim.pipeline import simulate
    from dem_graph.sim.scenarios import scenario

    config = scenario("smoke", seed=5, length_m=2.0, with_imu=False)
    laser = config.rig.laser.model_copy(update={"beams": f32_beams(config.rig.laser.beams), "range_min_m": float(np.float32(0.1))})
    config = config.model_copy(update={"rig": config.rig.model_copy(update={"laser": laser, "imu": None})})
    out = tmp_path_factory.mktemp("drive") / "smoke"
    simulate(config, out, preview=False)
    return out


@pytest.fixture(scope="module")
def folder_run(drive, tmp_path_factory):
    from dem_graph.pipeline.config import RunOverrides
    from dem_graph.pipeline.run import run_dataset

    return run_dataset(drive, RunOverrides(estimator="ptpm"), out_dir=tmp_path_factory.mktemp("folder_run") / "run")


def _bag(tmp_path, drive, fmt, edits=None):
    return write_robot_bag(tmp_path / ("robot.bag" if fmt == "ros1" else "robot"), drive, fmt, edits)


def _relative(trajectory, t_s=None):
    P = trajectory.poses_se3 if t_s is None else trajectory.at(t_s)
    return np.linalg.inv(P[0]) @ P


@pytest.mark.parametrize("fmt", ["ros1", "mcap"])
def test_the_rig_read_from_the_bag_is_the_true_rig(tmp_path, drive, fmt):
    truth = load_rig(drive / "rig.yaml")
    seq = open_dataset(_bag(tmp_path, drive, fmt), None, TOPICS)
    rig = seq.rig
    for name in ("width_px", "height_px"):
        assert getattr(rig.camera, name) == getattr(truth.camera, name)
    for name in ("fx_px", "fy_px", "cx_px", "cy_px"):
        assert abs(getattr(rig.camera, name) - getattr(truth.camera, name)) < 1e-9
    np.testing.assert_allclose(rig.camera.distortion, truth.camera.distortion, rtol=0, atol=1e-9)
    np.testing.assert_allclose(rig.T_body_cam, truth.T_body_cam, rtol=0, atol=1e-9)
    np.testing.assert_allclose(rig.T_body_laser, truth.T_body_laser, rtol=0, atol=1e-9)
    assert rig.laser.beams == truth.laser.beams  # exactly
    assert (rig.laser.range_min_m, rig.laser.range_max_m) == (truth.laser.range_min_m, truth.laser.range_max_m)
    assert abs(rig.camera.rate_hz - truth.camera.rate_hz) < 1e-3 and abs(rig.laser.rate_hz - truth.laser.rate_hz) < 1e-3
    assert rig.odometry is not None and rig.odometry.sigma_scale == truth.odometry.sigma_scale


@pytest.mark.parametrize("fmt", ["ros1", "mcap"])
def test_a_bag_with_only_its_topics_named_runs_as_the_folder_with_the_true_rig(tmp_path, drive, folder_run, fmt, caplog):
    from dem_graph.pipeline.config import RunOverrides
    from dem_graph.pipeline.run import run_dataset

    bag = _bag(tmp_path, drive, fmt)
    with caplog.at_level("WARNING"):
        run = run_dataset(bag, RunOverrides(estimator="ptpm"), out_dir=tmp_path / "run", dataset_options=TOPICS)
    assert run.error is None and folder_run.error is None
    told = [r.getMessage() for r in caplog.records if "the rig from the bag" in r.getMessage()]
    assert len(told) == 1 and "'base_footprint' (REP 105" in told[0] and "odometry noise" in told[0]
    est, ref = run.estimator.trajectory(), folder_run.estimator.trajectory()
    assert len(est.t_s) == len(ref.t_s) > 20
    error_m = np.linalg.norm(_relative(est)[:, :3, 3] - _relative(ref)[:, :3, 3], axis=1)
    assert error_m.max() < 0.005, error_m.max()
    assert np.linalg.norm(_relative(ref)[-1, :3, 3]) > 1.5  # it drove: the comparison means something
    # the run folder holds the rig it used, whole, and --rig reads it back to the same rig
    saved = rig_to_dict(load_rig(tmp_path / "run" / "rig.yaml"))
    assert saved == rig_to_dict(open_dataset(bag, None, TOPICS).rig) == rig_to_dict(run_rig(bag, tmp_path / "run" / "rig.yaml"))


def run_rig(bag, rig_path):
    return open_dataset(bag, None, DatasetOptions(image_topic=IMAGE, scan_topic=SCAN, odometry_topic=ODOM, rig=rig_path)).rig


def test_a_rig_file_overrides_field_by_field(tmp_path, drive):
    bag = _bag(tmp_path, drive, "ros1")
    part = tmp_path / "part.yaml"
    part.write_text("laser:\n  range_sigma_m: 0.005\nodometry:\n  sigma_scale: 0.03\n")
    rig = run_rig(bag, part)
    truth = load_rig(drive / "rig.yaml")
    assert rig.laser.range_sigma_m == 0.005 and rig.odometry.sigma_scale == 0.03
    np.testing.assert_allclose(rig.T_body_laser, truth.T_body_laser, rtol=0, atol=1e-9)  # the rest from the bag


def test_a_rectified_image_takes_p_and_rational_polynomial_reads(tmp_path, drive):
    truth = load_rig(drive / "rig.yaml")
    rect = open_dataset(
        _bag(tmp_path, drive, "mcap", BagEdits(rectified=True)), None, DatasetOptions(image_topic=IMAGE.replace("image_raw", "image_rect"), scan_topic=SCAN)
    ).rig
    assert rect.camera.distortion == (0.0,) * 5 and rect.camera.fx_px == truth.camera.fx_px and rect.camera.cy_px == truth.camera.cy_px
    (tmp_path / "b").mkdir()
    rational = open_dataset(_bag(tmp_path / "b", drive, "ros1", BagEdits(distortion_model="rational_polynomial")), None, TOPICS).rig
    np.testing.assert_allclose(rational.camera.distortion, truth.camera.distortion, rtol=0, atol=1e-12)


@pytest.mark.parametrize(
    "edits, message",
    [
        (BagEdits(no_camera_info=True), rf"topic {IMAGE}: no sensor_msgs/CameraInfo beside it \(looked for {INFO}"),
        (BagEdits(no_laser_tf=True), rf"frame '{LASER_FRAME}' \(the frame_id of {SCAN}\) is not in tf's fixed transforms \(its frames: base_footprint, base_link, {CAMERA_FRAME}"),
        (BagEdits(beams_change_at=8), rf"topic {SCAN} message 8: the beams change from 361 .* to 351 .* in \d+ of \d+ scans"),
    ],
    ids=["no_camera_info", "frame_not_in_tf", "beams_change"],
)
def test_what_the_bag_lacks_is_one_line_naming_it(tmp_path, drive, edits, message):
    bag = _bag(tmp_path, drive, "ros1", edits)
    with pytest.raises(DatasetError, match=message) as info:
        open_dataset(bag, None, TOPICS)
    assert "\n" not in str(info.value) and str(bag) in str(info.value)


def test_a_rig_file_fills_what_the_bag_lacks(tmp_path, drive):
    bag = _bag(tmp_path, drive, "mcap", BagEdits(no_camera_info=True))
    truth = load_rig(drive / "rig.yaml")
    camera = tmp_path / "camera.yaml"
    import yaml

    camera.write_text(yaml.safe_dump({"camera": {k: v for k, v in truth.camera.model_dump(mode="json").items() if k != "T_body_cam"}}))
    rig = run_rig(bag, camera)
    assert rig.camera.fx_px == truth.camera.fx_px
    np.testing.assert_allclose(rig.T_body_cam, truth.T_body_cam, rtol=0, atol=1e-9)
