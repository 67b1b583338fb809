"""The KITTI reader and the pipeline on the shared sample (skipped when ../shared is absent)."""

from __future__ import annotations

import numpy as np
import pytest

from dem_graph.datasets.events import CameraFrame, LaserScan
from dem_graph.geometry.se3 import transform_points

pytestmark = pytest.mark.shared_data


def test_sample_opens_with_a_road_ring(kitti_sequence):
    seq = kitti_sequence
    assert seq.n_frames == 51 and not seq.has_odometry
    assert seq.ring_split == "azimuth"
    assert -11.0 < seq.ring_laser.elevation_deg < -8.0  # the ring ~10 m ahead on the road
    cam = seq.rig.camera
    assert (cam.width_px, cam.height_px) == (1226, 370)
    for i in (0, 25, 50):
        points, ring = seq.read_scan(i)
        # every scan splits into the HDL-64E's 64 rings by the stored order: ring 0 highest, 63 lowest, over
        # the sensor's vertical field of view (+2 to -24.8 deg, Velodyne's data sheet), each ring a thin cone
        elevation_deg = np.degrees(np.arctan2(points[:, 2], np.hypot(points[:, 0], points[:, 1])))
        assert np.bincount(ring, minlength=64).min() > 1000 and ring.max() == 63
        median = np.array([np.median(elevation_deg[ring == r]) for r in range(64)])
        assert np.all(np.diff(median) < 0)  # measured on frames 0, 25, 50: no inversion
        assert 1.0 < median[0] < 3.5 and -25.0 < median[-1] < -22.5  # measured 2.3-2.8 and -23.7
        spread = [np.subtract(*np.percentile(elevation_deg[ring == r], [75, 25])) for r in range(64)]
        assert max(spread) < 1.5  # interquartile range in degrees, measured at most 1.31
    truth = seq.ground_truth.trajectory
    assert 60.0 < truth.path_length_m < 80.0
    np.testing.assert_allclose(truth.positions_xyz[-1, 1:], 0.0, atol=1.0)  # straight ahead along body x, z up


def test_ring_returns_lie_on_the_reference_ground(kitti_sequence):
    """The ring's fixed beams, placed with the true poses, against the 64-ring reference: within a few cm."""
    seq = kitti_sequence
    truth = seq.ground_truth
    t_s, ranges = seq.laser_scans()
    dirs = seq.rig.laser.beam_directions()
    errors = []
    for i in range(0, len(t_s), 5):
        ok = np.isfinite(ranges[i])
        T_world_laser = truth.trajectory.at(np.array([t_s[i]]))[0] @ seq.rig.T_body_laser
        p = transform_points(T_world_laser, dirs[ok] * ranges[i][ok, None])
        errors.append(p[:, 2] - truth.elevation.height_at(p[:, 0], p[:, 1]))
    e = np.concatenate(errors)
    e = e[np.isfinite(e)]
    assert len(e) > 1000
    assert abs(np.median(e)) < 0.04 and np.percentile(np.abs(e), 90) < 0.10


def test_events_in_order(kitti_sequence):
    kinds = [type(e) for _, e in zip(range(6), kitti_sequence.events())]
    assert kinds == [LaserScan, CameraFrame] * 3


def test_an_estimator_runs_on_the_first_frames(kitti_sequence):
    from dem_graph.pipeline import RunOverrides, run_config, run_estimator

    config = run_config(kitti_sequence, overrides=RunOverrides(estimator="ptpm", max_frames=12))
    run = run_estimator(kitti_sequence, config)
    assert run.error is None
    m = run.metrics
    assert m.frames == 12 and m.points_per_frame.tracked_median > 10
    assert m.trajectory.distance_m > 10.0
    assert m.trajectory.ate_rmse_m < 1.0  # 15 m driven without odometry


def test_starting_speed_from_the_first_two_scans(kitti_sequence):
    truth = kitti_sequence.ground_truth.trajectory
    true_speed = np.linalg.norm(truth.positions_xyz[1] - truth.positions_xyz[0]) / (truth.t_s[1] - truth.t_s[0])
    assert kitti_sequence.initial_speed_mps == pytest.approx(true_speed, abs=0.3)


def test_raw_drive_0013_runs_on_its_colour_camera(kitti_raw_drive):
    """Drive 0013 holds only the colour camera 2: it is read as grey with camera 2's rectified
    projection (KITTI's ``P_rect_02 @ R_rect_00 @ T_cam0_velo`` reproduced to 1e-4 px on Velodyne
    points: measured 3e-5, the calibration's rotation made exactly orthonormal), and PTPM with the KITTI settings and OXTS odometry drifts less than 3.5 %
    over its 53 m (measured: 3.17 % at 1045830 and on this tree, the IMU samples ignored by PTPM; 2.5 % in an earlier tree)."""
    from dem_graph.datasets.kitti import open_kitti, read_calib_file
    from dem_graph.geometry.se3 import invert, make_pose
    from dem_graph.pipeline import RunOverrides, run_config
    from dem_graph.pipeline.run import run_estimator

    seq = open_kitti(kitti_raw_drive)
    assert seq.camera == 2 and (seq.rig.camera.width_px, seq.rig.camera.height_px) == (1242, 375)
    frame = next(e for e in seq.events() if isinstance(e, CameraFrame))
    assert frame.image.ndim == 2
    cam = read_calib_file(kitti_raw_drive.parent / "calib_cam_to_cam.txt")
    velo = read_calib_file(kitti_raw_drive.parent / "calib_velo_to_cam.txt")
    R_rect = make_pose(cam["R_rect_00"].reshape(3, 3), np.zeros(3))
    T_cam0_velo = make_pose(velo["R"].reshape(3, 3), velo["T"])
    points, _ = seq.read_scan(10)
    X = points[(points[:, 0] > 8.0) & (points[:, 0] < 40.0)][::50, :3].astype(float)
    kitti = (cam["P_rect_02"].reshape(3, 4) @ R_rect @ T_cam0_velo @ np.c_[X, np.ones(len(X))].T).T
    kitti = kitti[:, :2] / kitti[:, 2:]
    uv, _ = seq.rig.camera_model.project(transform_points(invert(seq.rig.T_body_cam) @ seq.T_body_lidar, X))
    np.testing.assert_allclose(uv, kitti, atol=1e-4)
    config = run_config(seq, overrides=RunOverrides(estimator="ptpm"))
    run = run_estimator(seq, config, with_dem=False)
    assert run.error is None and run.metrics.trajectory.drift_percent < 3.5


def _heading_in_body_deg(T_rel: np.ndarray) -> np.ndarray:
    """The direction of travel of relative poses (N,4,4) in the body frame, degrees left of its x axis."""
    return np.degrees(np.arctan2(T_rel[:, 1, 3], T_rel[:, 0, 3]))


def test_drive_0013_gps_track_runs_a_degree_off_the_direction_the_velodyne_and_the_oxts_velocities_agree_on(kitti_raw_drive):
    """Drive 0013's OXTS GPS positions (the development kit's truth) run about a degree right of the
    direction of travel that the Velodyne's consecutive scans, registered, and the OXTS's own
    velocities both give (measured over scans 0-45, every sixth pair, degrees left of the body's x
    axis: Velodyne +0.36 with a spread of 0.16 between pairs, velocities +0.14, positions -1.17;
    every third pair gives +0.36, +0.16 and -1.23 for twice the registrations). That
    degree is 1.2 m across the 53 m: most of the 2.4 % drift of isam2 measured against the
    positions, which the OXTS velocities, integrated without any camera, also show (2.5 %).
    ``--truth velocities`` is the reference that resolves drift on this drive: against it isam2
    without odometry drifts 0.22 % (asserted below 2 %, issue 23's bound)."""
    from dem_graph.datasets.kitti import open_kitti
    from dem_graph.datasets.velodyne import register_scans
    from dem_graph.geometry.se3 import invert

    by_gps = open_kitti(kitti_raw_drive)
    by_velocity = open_kitti(kitti_raw_drive, truth="velocities")
    pairs = list(range(0, 46, 6))
    lidar = []
    for i in pairs:
        T_to_from, used = register_scans(by_gps.read_scan(i + 1)[0][:, :3], by_gps.read_scan(i)[0][:, :3])
        assert used > 1000
        lidar.append(T_to_from)
    velodyne = float(np.mean(_heading_in_body_deg(np.array(lidar))))  # the body frame is the lidar's, lowered
    t_scan, _ = by_gps.laser_scans()
    headings = {}
    for name, seq in (("positions", by_gps), ("velocities", by_velocity)):
        T = seq.ground_truth.trajectory.at(t_scan)
        T_rel = np.array([invert(T[i]) @ T[i + 1] for i in pairs])
        headings[name] = float(np.mean(_heading_in_body_deg(T_rel)))
    assert abs(headings["velocities"] - velodyne) < 0.3
    assert velodyne - headings["positions"] > 1.0

    from dem_graph.pipeline import RunOverrides, run_config
    from dem_graph.pipeline.run import run_estimator

    run = run_estimator(by_velocity, run_config(by_velocity, overrides=RunOverrides(estimator="isam2", no_odometry=True)), with_dem=False)
    assert run.error is None and run.metrics.trajectory.drift_percent < 2.0
