"""KITTI readers on files the tests make: ring separation, the ring as a laser, both layouts, bad input."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from dem_graph.datasets.events import CameraFrame, LaserScan, Odometry
from dem_graph.datasets.folder import FolderSequence
from dem_graph.datasets.kitti import KittiOdometrySequence, KittiRawSequence, open_kitti, oxts_poses
from dem_graph.datasets.open import detect_format
from dem_graph.datasets.velodyne import RingLaser, elevation_deg, read_velodyne_bin, reference_surface, split_rings
from dem_graph.errors import DatasetError
from dem_graph.frontend.search_cap import (
    REFERENCE_RATE_HZ,
    REFERENCE_SPEED_MPS,
    cap_for_speed,
    derived_search_half_size_px,
    nearest_ground_motion_px,
)
from dem_graph.geometry.rig import default_rig
from dem_graph.geometry.se3 import invert, make_pose, rotation_from_rpy, transform_points
from dem_graph.pipeline import RunConfig, RunOverrides, run_config

LIDAR_H = 1.73
ELEVATIONS_DEG = np.concatenate([np.linspace(2.0, -8.33, 32), np.linspace(-8.83, -24.33, 32)])
# lidar -> camera: camera x = -lidar y, camera y = -lidar z, camera z = lidar x (as KITTI's Tr, roughly)
T_CAM_LIDAR = make_pose(np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]]), [0.0, -0.08, -0.27])


def synthetic_scan(rng=None, drop_first_deg: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """64 rings swept from facing forward with increasing azimuth; rings below the horizon hit flat
    ground ``LIDAR_H`` below the lidar, the others a 30 m cylinder. Returns points (N,4) float32 and ring ids."""
    az = np.radians(np.arange(0.0, 360.0, 0.2) + 0.05)
    pts, ids = [], []
    for k, el_deg in enumerate(ELEVATIONS_DEG):
        el = math.radians(el_deg)
        a = az[np.degrees(az) >= drop_first_deg] if k == 0 else az
        r = LIDAR_H / math.sin(-el) if el < -0.5 * math.pi / 180 else 30.0 / math.cos(el)
        r = np.full(len(a), r) if rng is None else r + rng.normal(0.0, 0.002, len(a))
        d = np.stack([np.cos(el) * np.cos(a), np.cos(el) * np.sin(a), np.full(len(a), np.sin(el))], axis=1)
        pts.append(np.concatenate([d * r[:, None], np.zeros((len(a), 1))], axis=1))
        ids.append(np.full(len(a), k))
    return np.concatenate(pts).astype(np.float32), np.concatenate(ids)


def test_rings_split_exactly_by_azimuth_order():
    points, ids = synthetic_scan(np.random.default_rng(0), drop_first_deg=20.0)
    ring, how = split_rings(points)
    assert how == "azimuth"
    assert np.array_equal(ring, ids)


def test_rings_fall_back_to_elevation():
    points, ids = synthetic_scan()
    shuffled = np.random.default_rng(1).permutation(len(points))  # stored order lost: the azimuth split fails
    ring, how = split_rings(points[shuffled], ring_elevations_deg=ELEVATIONS_DEG)
    assert how == "elevation"
    assert np.array_equal(ring, ids[shuffled])


def test_ring_laser_puts_returns_on_the_ground():
    points, ids = synthetic_scan()
    k = int(np.argmin(np.abs(ELEVATIONS_DEG + 9.5)))
    laser = RingLaser(k, float(np.median(elevation_deg(points[ids == k]))), 40.0, 0.25)
    ranges = laser.ranges_m(points, ids)
    assert len(ranges) == len(laser.azimuths_deg) == laser.beams().count
    assert np.isfinite(ranges).all()
    xyz = laser.beams().directions() * ranges[:, None]
    np.testing.assert_allclose(xyz[:, 2], -LIDAR_H, atol=1e-4)
    # a bin with no point near its centre stays NaN
    keep = ~((ids == k) & (np.abs(np.degrees(np.arctan2(points[:, 1], points[:, 0]))) < 1.0))
    ranges = laser.ranges_m(points[keep], ids[keep])
    assert np.isnan(ranges[np.abs(laser.azimuths_deg) < 0.9]).all() and np.isfinite(ranges[np.abs(laser.azimuths_deg) > 1.1]).all()


def test_reference_surface_of_a_plane_with_a_car():
    rng = np.random.default_rng(2)
    ground = np.column_stack([rng.uniform(0, 20, 200_000), rng.uniform(-5, 5, 200_000), rng.normal(0.7, 0.02, 200_000)])
    car = np.column_stack([rng.uniform(8, 12, 20_000), rng.uniform(-1, 1, 20_000), rng.uniform(1.0, 2.2, 20_000)])  # roof and sides, no ground under it
    grid = reference_surface([ground, car], 0.5, bounds_xy_m=(0.0, -5.0, 20.0, 5.0))
    z = grid.z_m
    assert np.isfinite(z).mean() > 0.85
    np.testing.assert_allclose(np.nanmedian(z), 0.7, atol=0.01)
    assert np.nanmax(np.abs(z - 0.7)) < 0.03  # the car's cells are dropped, not kept as ground


def _write_png(path, image):
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), image)


def _scan_file(path, dx_m: float = 0.0):
    points, _ = synthetic_scan()
    path.parent.mkdir(parents=True, exist_ok=True)
    points.tofile(path)


def _calib_line(key, M):
    return f"{key}: " + " ".join(f"{v:.12e}" for v in np.asarray(M).ravel())


P0 = np.array([[700.0, 0.0, 300.0, 0.0], [0.0, 700.0, 90.0, 0.0], [0.0, 0.0, 1.0, 0.0]])


def make_odometry_layout(root, n=3, images=None, times=None, calib=True, size_px=(600, 180), P=P0):
    seq = root / "sequences" / "07"
    rng = np.random.default_rng(3)
    for i in range(n if images is None else images):
        _write_png(seq / "image_0" / f"{i:06d}.png", rng.integers(0, 256, size_px[::-1], dtype=np.uint8))
    for i in range(n):
        _scan_file(seq / "velodyne" / f"{i:06d}.bin")
    if calib:
        (seq / "calib.txt").write_text("\n".join([_calib_line("P0", P), _calib_line("Tr", T_CAM_LIDAR[:3])]) + "\n")
    (seq / "times.txt").write_text("\n".join(f"{0.1 * i:.6e}" for i in range(n if times is None else times)) + "\n")
    # camera 0 drives 1 m per frame along its optical axis (forward)
    (root / "poses").mkdir(parents=True, exist_ok=True)
    lines = [" ".join(f"{v:.9e}" for v in make_pose(np.eye(3), [0.0, 0.0, 1.0 * i])[:3].ravel()) for i in range(n)]
    (root / "poses" / "07.txt").write_text("\n".join(lines) + "\n")
    return root


def test_odometry_layout(tmp_path):
    root = make_odometry_layout(tmp_path / "kitti")
    assert detect_format(root) == "kitti-odometry"
    seq = open_kitti(root)
    assert isinstance(seq, KittiOdometrySequence) and not seq.has_odometry
    cam = seq.rig.camera
    assert (cam.width_px, cam.height_px, cam.fx_px, cam.cx_px, cam.cy_px) == (600, 180, 700.0, 300.0, 90.0)
    np.testing.assert_allclose(seq.rig.T_body_cam, make_pose(np.eye(3), [0, 0, LIDAR_H]) @ invert(T_CAM_LIDAR), atol=1e-9)
    # the default ring is the one hitting the ground nearest 10 m ahead
    el = ELEVATIONS_DEG[seq.ring]
    assert abs(LIDAR_H / math.tan(math.radians(-el)) - 10.0) < 1.0
    events = list(seq.events())
    assert [type(e) for e in events] == [LaserScan, CameraFrame] * 3
    assert [e.t_s for e in events] == pytest.approx([0.0, 0.0, 0.1, 0.1, 0.2, 0.2])
    dirs = seq.rig.laser.beam_directions()
    for scan in (e for e in events if isinstance(e, LaserScan)):
        xyz = dirs * scan.ranges_m[:, None]
        np.testing.assert_allclose(xyz[:, 2], -LIDAR_H, atol=1e-3)  # the road, in the lidar frame
    truth = seq.ground_truth
    # body 1 m forward per frame, world z up, initial pose the identity
    np.testing.assert_allclose(truth.trajectory.positions_xyz, [[0, 0, 0], [1, 0, 0], [2, 0, 0]], atol=1e-9)
    np.testing.assert_allclose(seq.T_world_body_initial, np.eye(4))
    ground = truth.elevation
    assert np.isfinite(ground.z_m).mean() > 0.3
    np.testing.assert_allclose(np.nanmedian(ground.z_m), 0.0, atol=0.01)  # the road is the body's z = 0 plane
    assert np.nanmax(np.abs(ground.z_m)) < 0.01


def test_missing_calibration_is_named(tmp_path):
    root = make_odometry_layout(tmp_path / "kitti", calib=False)
    with pytest.raises(DatasetError, match=r"sequences/07/calib.txt: calibration file not found"):
        open_kitti(root)


def test_truncated_scan_is_named(tmp_path):
    root = make_odometry_layout(tmp_path / "kitti")
    path = root / "sequences/07/velodyne/000001.bin"
    path.write_bytes(path.read_bytes()[:-6])
    with pytest.raises(DatasetError, match=r"000001.bin: \d+ bytes is not a whole number of 16-byte points"):
        read_velodyne_bin(path)
    seq = open_kitti(root)  # the first scan is fine: the error comes when the bad one is read
    with pytest.raises(DatasetError, match=r"000001.bin"):
        list(seq.events())


def test_images_and_times_must_match(tmp_path):
    root = make_odometry_layout(tmp_path / "kitti", n=3, images=2)
    with pytest.raises(DatasetError, match=r"times.txt: 3 times but 2 images in image_0"):
        open_kitti(root)


# ----------------------------------------------------------------------------------------------
# raw layout

R_EARTH = 6378137.0
LAT0 = 49.0


def _stamp(t_s: float) -> str:
    whole = math.floor(t_s)
    ns = round((t_s - whole) * 1e9)
    base = 13 * 3600 + 2 * 60 + whole
    return f"2011-09-26 {base // 3600:02d}:{base // 60 % 60:02d}:{base % 60:02d}.{ns:09d}"


def circle_path(t_s, speed=10.0, yaw_rate=0.2):
    """IMU poses driving a circle (world ENU), and the OXTS records that describe them."""
    yaw = yaw_rate * t_s
    radius = speed / yaw_rate
    x, y = radius * np.sin(yaw), radius * (1 - np.cos(yaw))
    scale = math.cos(math.radians(LAT0))
    mx0 = 0.0
    my0 = scale * R_EARTH * math.log(math.tan(math.radians(90 + LAT0) / 2))
    lon = np.degrees((mx0 + x) / (scale * R_EARTH))
    lat = np.degrees(2 * np.arctan(np.exp((my0 + y) / (scale * R_EARTH)))) - 90.0
    rows = np.zeros((len(t_s), 30))
    rows[:, 0], rows[:, 1], rows[:, 2] = lat, lon, 100.0
    rows[:, 5] = yaw
    rows[:, 8] = speed  # vf
    rows[:, 6], rows[:, 7] = speed * np.sin(yaw), speed * np.cos(yaw)  # vn, ve
    rows[:, 22] = yaw_rate  # wu
    rows[:, 23:30] = [0.1, 0.1, 4, 10, 5, 5, 6]
    poses = make_pose(rotation_from_rpy(0.0, 0.0, yaw), np.stack([x, y, np.zeros_like(x)], axis=1))
    return rows, poses


def make_raw_drive(root, n=11, oxts_stamps=None, gps_heading_error_deg: float = 0.0):
    """A raw drive on :func:`circle_path`; ``gps_heading_error_deg`` turns the GPS positions (only
    them) about the first one, as a GPS track that runs off the vehicle's direction of travel does."""
    drive = root / "2011_09_26" / "2011_09_26_drive_0001_sync"
    t = 0.1 * np.arange(n)
    rows, poses = circle_path(t)
    if gps_heading_error_deg:
        a = math.radians(gps_heading_error_deg)
        xy = poses[:, :2, 3] @ np.array([[math.cos(a), math.sin(a)], [-math.sin(a), math.cos(a)]])  # each row turned by a
        scale = math.cos(math.radians(LAT0))
        my0 = scale * R_EARTH * math.log(math.tan(math.radians(90 + LAT0) / 2))
        rows[:, 1] = np.degrees(xy[:, 0] / (scale * R_EARTH))
        rows[:, 0] = np.degrees(2 * np.arctan(np.exp((my0 + xy[:, 1]) / (scale * R_EARTH)))) - 90.0
    rng = np.random.default_rng(4)
    for i in range(n):
        _write_png(drive / "image_00/data" / f"{i:010d}.png", rng.integers(0, 256, (180, 600), dtype=np.uint8))
        _scan_file(drive / "velodyne_points/data" / f"{i:010d}.bin")
        (drive / "oxts/data").mkdir(parents=True, exist_ok=True)
        (drive / "oxts/data" / f"{i:010d}.txt").write_text(" ".join(repr(float(v)) for v in rows[i]) + "\n")
    (drive / "image_00/timestamps.txt").write_text("\n".join(_stamp(x + 0.004) for x in t) + "\n")
    for name in ("timestamps.txt", "timestamps_start.txt", "timestamps_end.txt"):
        (drive / "velodyne_points" / name).write_text("\n".join(_stamp(x + 0.002) for x in t) + "\n")
    (drive / "oxts/timestamps.txt").write_text("\n".join(_stamp(x) for x in (t if oxts_stamps is None else t[:oxts_stamps])) + "\n")
    date = drive.parent
    (date / "calib_cam_to_cam.txt").write_text(
        "calib_time: 09-Jan-2012 13:57:47\n" + "\n".join([_calib_line("S_rect_00", [600, 180]), _calib_line("R_rect_00", np.eye(3)), _calib_line("P_rect_00", P0)]) + "\n"
    )
    (date / "calib_velo_to_cam.txt").write_text("calib_time: 15-Mar-2012 11:37:16\n" + _calib_line("R", T_CAM_LIDAR[:3, :3]) + "\n" + _calib_line("T", T_CAM_LIDAR[:3, 3]) + "\n")
    T_velo_imu = make_pose(np.eye(3), [-0.8, 0.3, -0.8])
    (date / "calib_imu_to_velo.txt").write_text("calib_time: 25-May-2012 16:47:16\n" + _calib_line("R", T_velo_imu[:3, :3]) + "\n" + _calib_line("T", T_velo_imu[:3, 3]) + "\n")
    return drive, poses, T_velo_imu


def test_raw_layout_oxts_truth_and_odometry(tmp_path):
    drive, T_world_imu, T_velo_imu = make_raw_drive(tmp_path)
    assert detect_format(drive) == "kitti-raw"
    seq = open_kitti(drive)
    assert isinstance(seq, KittiRawSequence) and seq.has_odometry
    T_body_imu = make_pose(np.eye(3), [0, 0, LIDAR_H]) @ T_velo_imu
    truth = seq.ground_truth.trajectory
    np.testing.assert_allclose(truth.t_s, 0.1 * np.arange(11), atol=1e-9)
    expected = T_world_imu @ invert(T_body_imu)
    expected[:, :3, 3] -= T_world_imu[0, :3, 3]  # the world's origin is the first OXTS position
    np.testing.assert_allclose(truth.poses_se3, expected, atol=2e-3)  # the Mercator round trip, to millimetres
    # the OXTS velocities integrate to the same path
    odo = [e for e in seq.events() if isinstance(e, Odometry)]
    assert len(odo) == 10
    T = seq.T_world_body_initial
    for o in odo:
        T = T @ o.T_prev_curr
    np.testing.assert_allclose(T[:3, 3], truth.poses_se3[-1][:3, 3], atol=0.01)
    np.testing.assert_allclose(T[:3, :3], truth.poses_se3[-1][:3, :3], atol=1e-6)
    events = list(seq.events())
    times = [e.t_s for e in events]
    assert times == sorted(times) and times[0] >= seq.t_start_s
    frames = [e for e in events if isinstance(e, CameraFrame)]
    assert frames[0].t_s == pytest.approx(0.004, abs=1e-9)


def test_raw_truth_from_the_velocities_keeps_the_direction_of_travel_when_the_gps_track_runs_off(tmp_path):
    drive, T_world_imu, T_velo_imu = make_raw_drive(tmp_path, n=31, gps_heading_error_deg=1.0)  # 3 s, 30 m of a circle
    T_body_imu = make_pose(np.eye(3), [0, 0, LIDAR_H]) @ T_velo_imu
    expected = T_world_imu @ invert(T_body_imu)
    by_gps = open_kitti(drive).ground_truth.trajectory.poses_se3
    by_velocity = open_kitti(drive, truth="velocities").ground_truth.trajectory.poses_se3
    # the GPS track is turned by 1 degree: 30 m on, its end is about 0.5 m away from the vehicle's
    assert np.linalg.norm(by_gps[-1, :3, 3] - expected[-1, :3, 3]) == pytest.approx(math.radians(1.0) * np.linalg.norm(T_world_imu[-1, :2, 3]), rel=0.02)
    # the velocities integrate (trapezoid, 0.1 s steps) to the circle within 2 cm over 30 m; the attitude is the OXTS's in both
    np.testing.assert_allclose(by_velocity[:, :3, 3], expected[:, :3, 3], atol=0.02)
    np.testing.assert_allclose(by_velocity[:, :3, :3], by_gps[:, :3, :3], atol=1e-12)
    with pytest.raises(DatasetError, match=r"unknown truth 'imu': a raw drive's trajectory is built from positions or velocities"):
        open_kitti(drive, truth="imu")


def test_oxts_mercator_origin_is_zero():
    rows, _ = circle_path(np.array([0.0, 1.0]))
    T = oxts_poses(rows)
    np.testing.assert_allclose(T[0], np.eye(4), atol=1e-12)


def test_raw_stamps_and_files_must_match(tmp_path):
    drive, _, _ = make_raw_drive(tmp_path, oxts_stamps=9)
    with pytest.raises(DatasetError, match=r"oxts/timestamps.txt: 9 time stamps but 11 files in oxts/data"):
        open_kitti(drive)


def _as_colour_camera_2(drive, t_rect=(0.06, -0.002, 0.003)):
    """The drive's camera 0 moved to ``image_02`` as colour images, with a ``P_rect_02`` whose
    camera sits at ``t_rect`` from camera 0's in its rectified frame (the stereo baseline)."""
    import shutil

    for png in sorted((drive / "image_00/data").glob("*.png")):
        grey = cv2.imread(str(png), cv2.IMREAD_GRAYSCALE)
        _write_png(drive / "image_02/data" / png.name, np.dstack([grey, grey // 2, 255 - grey]))
    (drive / "image_02/timestamps.txt").write_text((drive / "image_00/timestamps.txt").read_text())
    shutil.rmtree(drive / "image_00")
    P2 = P0.copy()
    P2[:, 3] = P0[:, :3] @ np.asarray(t_rect)
    calib = drive.parent / "calib_cam_to_cam.txt"
    calib.write_text(calib.read_text() + _calib_line("P_rect_02", P2) + "\n")
    return P2


def test_raw_layout_reads_the_colour_camera_as_grey_with_its_own_projection(tmp_path):
    """A drive with only camera 2 (colour, as the shared drive 0013): it is told as KITTI raw and
    camera 2 chosen; frames are its images converted to grey; and the rig projects a lidar point
    where KITTI's own formula ``P_rect_02 @ R_rect_00 @ T_cam0_velo`` does."""
    drive, _, _ = make_raw_drive(tmp_path)
    P2 = _as_colour_camera_2(drive)
    assert detect_format(drive) == "kitti-raw"
    seq = open_kitti(drive)
    assert seq.camera == 2 and seq.open_options()["camera"] == 2
    frame = next(e for e in seq.events() if isinstance(e, CameraFrame))
    colour = cv2.imread(str(drive / "image_02/data/0000000000.png"))
    np.testing.assert_array_equal(frame.image, cv2.cvtColor(colour, cv2.COLOR_BGR2GRAY))
    X_lidar = np.array([[12.0, 1.5, -1.2], [25.0, -4.0, 0.5], [8.0, 0.2, -1.6]])
    kitti = (P2 @ (T_CAM_LIDAR @ np.c_[X_lidar, np.ones(3)].T)).T  # R_rect_00 is the identity here
    kitti = kitti[:, :2] / kitti[:, 2:]
    rig = seq.rig
    X_cam = transform_points(invert(rig.T_body_cam) @ seq.T_body_lidar, X_lidar)
    uv, _ = rig.camera_model.project(X_cam)
    np.testing.assert_allclose(uv, kitti, atol=1e-6)


def test_a_drive_that_is_almost_kitti_raw_is_told_what_it_lacks(tmp_path):
    drive, _, _ = make_raw_drive(tmp_path)
    _as_colour_camera_2(drive)
    with pytest.raises(DatasetError, match=r"image_00/data: not found: camera 0 is not in this drive \(it holds camera 2\)"):
        open_kitti(drive, camera=0)
    import shutil

    shutil.rmtree(drive / "oxts")
    (drive.parent / "calib_imu_to_velo.txt").unlink()
    assert detect_format(drive) == "kitti-raw"  # a camera and the Velodyne: a drive, with parts missing
    with pytest.raises(DatasetError, match=r"not a complete KITTI raw drive: oxts/data, oxts/timestamps.txt, calib_imu_to_velo.txt not found"):
        open_kitti(drive)
    shutil.rmtree(drive / "image_02")
    (drive / "oxts").mkdir()
    with pytest.raises(DatasetError, match=r"no camera: a KITTI raw drive holds one of image_00/data, image_01/data, image_02/data, image_03/data"):
        open_kitti(drive)


def test_cli_runs_on_a_kitti_folder_and_names_a_missing_topic(tmp_path):
    import json

    from click.testing import CliRunner

    from dem_graph.cli import main

    root = make_odometry_layout(tmp_path / "kitti")
    out = tmp_path / "run"
    result = CliRunner().invoke(main, ["--no-progress", "run", str(root), "--format", "kitti-odometry", "--ring", "40", "--estimator", "ptpm", "--max-frames", "3", "--out", str(out)])
    # the layout's made-up images hold no ground to track: the run goes to its end, writes its
    # folder, and says last that it failed (exit code 3)
    assert result.exit_code == 3 and result.stderr.strip().splitlines()[-1].startswith("dem-graph: run failed: "), result.output
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["frames"] == 3 and "trajectory" in metrics
    assert metrics["dataset_options"] == {"format": "kitti-odometry", "ring": 40, "sequence": "07"}
    # the DEM made again from the run folder reads ring 40 again, not the default ring
    made = np.load(out / "dem.npz")["layer_elevation"]
    (out / "dem.npz").unlink()
    result = CliRunner().invoke(main, ["--no-progress", "dem", str(out)])
    assert result.exit_code == 0, result.output
    np.testing.assert_array_equal(np.load(out / "dem.npz")["layer_elevation"], made)
    assert open_kitti(root).ring != 40  # (the default ring would have given another DEM)
    bag = tmp_path / "x.bag"
    bag.write_bytes(b"")
    result = CliRunner().invoke(main, ["--no-progress", "run", str(bag), "--estimator", "ptpm", "--out", str(tmp_path / "r2")])
    assert result.exit_code == 2 and "a ROS bag needs --image-topic and --scan-topic" in result.output and "bag-info" in result.output


def _box_scene(rng, n):
    """Points on a ground plane, three walls and a box, sampled at random (no two samplings share points)."""
    parts = [
        np.column_stack([rng.uniform(-30, 30, n), rng.uniform(-30, 30, n), np.full(n, -LIDAR_H)]),
        np.column_stack([np.full(n // 3, 25.0), rng.uniform(-10, 10, n // 3), rng.uniform(-1.7, 2, n // 3)]),
        np.column_stack([rng.uniform(-20, 20, n // 3), np.full(n // 3, 12.0), rng.uniform(-1.7, 2, n // 3)]),
        np.column_stack([rng.uniform(-25, 5, n // 3), np.full(n // 3, -9.0), rng.uniform(-1.7, 1, n // 3)]),
        np.column_stack([np.full(n // 6, 8.0), rng.uniform(3, 6, n // 6), rng.uniform(-1.7, 0, n // 6)]),
        np.column_stack([rng.uniform(8, 11, n // 6), np.full(n // 6, 3.0), rng.uniform(-1.7, 0, n // 6)]),
    ]
    return np.concatenate(parts)


def test_scan_registration_recovers_a_metre_of_motion():
    from dem_graph.datasets.velodyne import register_scans

    rng = np.random.default_rng(5)
    T_to_from = make_pose(rotation_from_rpy(0.0, 0.0, math.radians(1.0)), [1.3, 0.05, 0.02])
    scene_to = _box_scene(rng, 60_000)
    scene_from = _box_scene(rng, 60_000) @ T_to_from[:3, :3] - T_to_from[:3, :3].T @ T_to_from[:3, 3]  # the same world seen from the moved lidar
    T, pairs = register_scans(scene_from, scene_to)
    assert pairs > 1000
    np.testing.assert_allclose(T[:3, 3], T_to_from[:3, 3], atol=0.02)
    np.testing.assert_allclose(T[:3, :3], T_to_from[:3, :3], atol=1e-3)


def test_the_dataset_speed_replaces_the_prior_only_when_asked():
    from types import SimpleNamespace

    from dem_graph.pipeline.run import RunConfig, with_dataset_speed

    sequence = SimpleNamespace(has_odometry=False, initial_speed_mps=12.5)
    config = RunConfig()
    assert with_dataset_speed(sequence, config) is config
    config.motion.initial_speed_from_dataset = True
    assert with_dataset_speed(sequence, config).motion.initial_speed_mps == 12.5
    assert config.motion.initial_speed_mps == 0.0  # the caller's configuration is not changed
    assert with_dataset_speed(SimpleNamespace(has_odometry=True, initial_speed_mps=12.5), config).motion.initial_speed_mps == 0.0


# sequence 04's camera: 1226x370 px, P0's focal length and centre
SIZE_04_PX = (1226, 370)
P0_04 = np.array([[707.0912, 0.0, 601.8873, 0.0], [0.0, 707.0912, 183.1104, 0.0], [0.0, 0.0, 1.0, 0.0]])


def _level_camera_ground_motion_px(f_px: float, cy_px: float, height_px: int, camera_height_m: float, step_m: float) -> float:
    """By hand, for a level pinhole camera: the bottom row sees the ground D = h f / (rows - 1 - cy)
    ahead; after the step the point is D - step ahead, at row cy + f h / (D - step)."""
    below_px = height_px - 1 - cy_px
    D = camera_height_m * f_px / below_px
    return f_px * camera_height_m / (D - step_m) - below_px


def test_kitti_brings_its_run_settings_under_the_users_configuration(tmp_path):
    # the package's defaults are for a small robot at 25 Hz: KITTI's reader brings a car's settings,
    # and a configuration file the user gives wins key by key
    seq = open_kitti(make_odometry_layout(tmp_path / "kitti", size_px=SIZE_04_PX, P=P0_04))
    defaults = RunConfig()
    config = run_config(seq)
    assert config.motion.initial_speed_from_dataset and not defaults.motion.initial_speed_from_dataset
    # KITTI gives no speed and no search cap: the speed comes from the scans (or the ground's motion),
    # and the cap follows the speed the estimator holds (frontend.search_cap): at 12 m/s, the camera's
    # 10 Hz (times.txt) and its intrinsics, the formula of dem_graph/pipeline/derived.py at 1.25 times the speed
    assert "vehicle" not in seq.run_settings() and "max_search_half_size_px" not in seq.run_settings()["frontend"]["tracker"]
    assert config.vehicle.speed_mps == defaults.vehicle.speed_mps and seq.rig.camera.rate_hz == pytest.approx(10.0)
    assert config.frontend.tracker.max_search_half_size_px == 40 and config.frontend.tracker.search_cap_follows_speed
    camera_height_m = seq.rig.T_body_cam[2, 3]  # 1.65 m, level (T_CAM_LIDAR)
    rate_hz = seq.rig.camera.rate_hz
    motion_px = _level_camera_ground_motion_px(707.0912, 183.1104, SIZE_04_PX[1], camera_height_m, 1.25 * 12.0 / rate_hz)
    reference_px = nearest_ground_motion_px(default_rig(), REFERENCE_SPEED_MPS / REFERENCE_RATE_HZ)  # distorted: the function's
    expected = max(40, round(40 * motion_px / reference_px))
    assert cap_for_speed(seq.rig, 40, 12.0) == expected == derived_search_half_size_px(seq.rig, 15.0, rate_hz)
    assert 130 < expected < 170  # 155 px here at 10 Hz and 15 m/s
    assert config.frontend.focus.corridor_width_m == 6.0 and config.frontend.focus.max_distance_m == 25.0
    user = tmp_path / "mine.yaml"
    user.write_text("frontend:\n  focus:\n    corridor_width_m: 4.0\n")
    config = run_config(seq, user, RunOverrides(estimator="ptpm"))
    assert config.frontend.focus.corridor_width_m == 4.0  # the user's value
    assert config.frontend.focus.max_distance_m == 25.0 and config.frontend.focus.cell_size_m == 1.0  # KITTI's, beside it
    assert config.motion.sigma_angular_acc_radps2 == 0.2 and config.estimator == "ptpm"
    # a dataset folder brings nothing
    assert FolderSequence.run_settings(object.__new__(FolderSequence)) == {}
