"""The KITTI raw reader's IMU stream: the OXTS records' accelerations and angular rates as ImuSample
events (shared drive 0013 of 2011_09_26; skipped when ../shared is absent)."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from dem_graph.datasets.events import CameraFrame, ImuSample, LaserScan, Odometry
from dem_graph.datasets.kitti import KittiOdometrySequence, KittiRawSequence, read_calib_file, read_kitti_timestamps
from dem_graph.errors import DatasetError
from dem_graph.geometry.se3 import make_pose, rotation_from_rpy


def _oxts(drive):
    """The drive's OXTS records (N,30) read straight from the text files, and their times (seconds after the first)."""
    rows = np.stack([np.loadtxt(p) for p in sorted((drive / "oxts" / "data").glob("*.txt"))])
    sec, ns = read_kitti_timestamps(drive / "oxts" / "timestamps.txt")
    return rows, (sec - sec[0]).astype(float) + (ns - ns[0]) * 1e-9


@pytest.fixture(scope="module")
def raw_events(kitti_raw_drive):
    seq = KittiRawSequence(kitti_raw_drive)
    return seq, list(seq.events())


def test_raw_drive_yields_the_oxts_accelerations_and_angular_rates(kitti_raw_drive, raw_events):
    seq, events = raw_events
    rows, t_oxts = _oxts(kitti_raw_drive)
    imu = [e for e in events if isinstance(e, ImuSample)]
    assert seq.has_imu and len(imu) == len(rows) == 48
    assert seq.event_count() == len(events)
    assert [e.index for e in imu] == list(range(48))
    # the files' ax ay az (fields 12-14) and wx wy wz (fields 18-20) exactly: specific force already, nothing added
    np.testing.assert_array_equal(np.stack([e.accel_mps2 for e in imu]), rows[:, 11:14])
    np.testing.assert_array_equal(np.stack([e.gyro_rad_s for e in imu]), rows[:, 17:20])
    np.testing.assert_allclose([e.t_s for e in imu], t_oxts, rtol=0, atol=1e-9)
    # in time order; every camera frame and laser scan at or before an IMU sample's time comes before it
    times = [e.t_s for e in events]
    assert times == sorted(times)
    position = {id(e): k for k, e in enumerate(events)}
    for sample in imu:
        earlier = [e for e in events if isinstance(e, (CameraFrame, LaserScan, Odometry)) and e.t_s <= sample.t_s]
        assert all(position[id(e)] < position[id(sample)] for e in earlier)
    # the rig's IMU: the OXTS rate, the calibration's mounting, the RT3003's figures
    spec = seq.rig.imu
    assert spec is not None and "RT3003" in spec.part
    assert spec.rate_hz == pytest.approx(10.0, abs=0.01)  # measured 9.996
    calib = read_calib_file(kitti_raw_drive.parent / "calib_imu_to_velo.txt")  # IMU to Velodyne coordinates
    T_velo_imu = make_pose(calib["R"].reshape(3, 3), calib["T"])
    np.testing.assert_allclose(spec.T_body_imu, seq.T_body_lidar @ T_velo_imu, atol=1e-7)  # the rotation made orthonormal: 4e-8
    np.testing.assert_allclose(seq.T_body_lidar, make_pose(np.eye(3), [0.0, 0.0, 1.73]))
    assert spec.gyro_noise_density == pytest.approx(1.75e-4) and spec.accel_noise_density == pytest.approx(1e-2)
    assert spec.gravity_mps2 == pytest.approx(9.8095, abs=1e-4)  # normal gravity at 49.01 N, 114 m


def test_the_specific_force_turned_level_by_the_oxts_roll_and_pitch_is_gravitys_reaction(kitti_raw_drive, raw_events):
    """ax ay az hold gravity's reaction: turned by the recorded roll and pitch (fields 4, 5) they
    average 9.792 m/s^2 up (measured; standard deviation 0.18 over 48 records, 0.026 for the mean),
    within 0.05 (two standard errors) of gravity's 9.8095 there. Level, they average -0.24 m/s^2 forward
    (the car braking from 11.8 to 10.7 m/s) and -0.04 leftward. Without gravity |a| would be about 0.3."""
    _, events = raw_events
    rows, _ = _oxts(kitti_raw_drive)
    accel = np.stack([e.accel_mps2 for e in events if isinstance(e, ImuSample)])
    level = np.einsum("nij,nj->ni", rotation_from_rpy(rows[:, 3], rows[:, 4], np.zeros(len(rows))), accel)
    mean = level.mean(axis=0)
    assert mean[2] == pytest.approx(9.8095, abs=0.05)  # measured 9.792
    assert np.all(np.abs(mean[:2]) < 0.3)  # measured -0.240, -0.042
    assert np.linalg.norm(accel, axis=1).mean() == pytest.approx(9.81, abs=0.05)  # measured 9.800


def _drive_copy(drive, tmp_path):
    """The drive in tmp_path with its own oxts folder to break; images and scans linked, not copied."""
    date = tmp_path / drive.parent.name
    copy = date / drive.name
    copy.mkdir(parents=True)
    for name in ("calib_cam_to_cam.txt", "calib_velo_to_cam.txt", "calib_imu_to_velo.txt"):
        shutil.copy(drive.parent / name, date / name)
    for folder in drive.iterdir():
        if folder.name == "oxts":
            shutil.copytree(folder, copy / "oxts")
        else:
            (copy / folder.name).symlink_to(folder, target_is_directory=True)
    return copy


def test_a_nan_angular_rate_or_a_missing_field_is_refused_naming_the_file(kitti_raw_drive, tmp_path):
    copy = _drive_copy(kitti_raw_drive, tmp_path)
    record = copy / "oxts" / "data" / "0000000007.txt"
    fields = record.read_text().split()
    record.write_text(" ".join(fields[:19] + ["nan"] + fields[20:]) + "\n")  # wz, the 20th field
    with pytest.raises(DatasetError) as info:
        KittiRawSequence(copy)
    assert info.value.path == str(record)
    assert str(info.value) == f"{record}: wz (field 20 of 30) is nan: the IMU's accelerations and angular rates must be finite"
    record.write_text(" ".join(fields[:19] + ["inf"] + fields[20:]) + "\n")
    with pytest.raises(DatasetError, match=r"0000000007\.txt: wz \(field 20 of 30\) is inf"):
        KittiRawSequence(copy)
    record.write_text(" ".join(fields[:19] + fields[20:]) + "\n")  # wz left out: the fields after it would shift
    with pytest.raises(DatasetError) as info:
        KittiRawSequence(copy)
    assert info.value.path == str(record) and "\n" not in str(info.value)
    assert "29 numbers, an OXTS record has 30 (lat lon alt" in info.value.problem and info.value.problem.endswith(": a field is missing")
    record.write_text(" ".join(fields[:12]) + "\n")  # a short line
    with pytest.raises(DatasetError, match=r"0000000007\.txt: 12 numbers, an OXTS record has 30 .*: 18 fields are missing$"):
        KittiRawSequence(copy)
    record.write_text(" ".join(fields[:11] + ["x"] + fields[12:]) + "\n")
    with pytest.raises(DatasetError, match=r"0000000007\.txt: ax \(field 12 of 30\) is not a number: 'x'$"):
        KittiRawSequence(copy)
    record.write_text(" ".join(fields) + "\n")
    assert KittiRawSequence(copy).has_imu  # the copy itself reads


def test_kitti_odometry_sequences_have_no_imu(kitti_sample):
    seq = KittiOdometrySequence(kitti_sample)
    assert not seq.has_imu and seq.rig.imu is None
    events = list(seq.events())
    assert len(events) == seq.event_count() and not any(isinstance(e, ImuSample) for e in events)
