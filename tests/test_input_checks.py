"""Input checks: every bad input refused in one line naming the file and the field or line, every
fault survived with one warning (dem_graph.datasets.checks and the readers that use it)."""

from __future__ import annotations

import logging
import shutil

import cv2
import numpy as np
import pytest
import yaml
from pydantic import ValidationError

from dem_graph.datasets.checks import InputChecks, covariance_problems, increment_rates, plausible_increments
from dem_graph.datasets.events import CameraFrame, LaserScan, Odometry
from dem_graph.datasets.folder import FolderSequence
from dem_graph.errors import ConfigError, DatasetError
from dem_graph.estimators.odometry import OdometryIntegrator
from dem_graph.geometry.rig import OdometrySpec, PlanarBeams, default_rig
from dem_graph.geometry.se3 import make_pose, quat_xyzw_from_matrix, rotation_from_rpy

CHECKS_LOG = "dem_graph.datasets.checks"


@pytest.fixture
def folder(tiny_folder, tmp_path):
    """A copy of the 8-frame `smoke` dataset folder to break (320x240 camera, 4 scans, 16 odometry increments)."""
    return shutil.copytree(tiny_folder, tmp_path / "ds")


def _edit_yaml(path, edit):
    data = yaml.safe_load(path.read_text())
    edit(data)
    path.write_text(yaml.safe_dump(data))


def _edit_npz(path, edit):
    arrays = dict(np.load(path))
    edit(arrays)
    np.savez(path, **arrays)


def _refused(error_type, folder, *fragments, checks=None):
    with pytest.raises(error_type) as info:
        FolderSequence(folder, checks)
    msg = str(info.value)
    assert "\n" not in msg
    for fragment in fragments:
        assert fragment in msg, f"{fragment!r} not in {msg!r}"
    return msg


def _warnings(caplog):
    return [r.getMessage() for r in caplog.records if r.name == CHECKS_LOG and r.levelno == logging.WARNING]


# ---------------------------------------------------------------------------------------------- the rig


@pytest.mark.parametrize(
    "field, value, problem",
    [
        ("cx_px", float("nan"), "camera.cx_px is nan; it must be a finite pixel coordinate inside the image (-0.5 to 319.5)"),
        ("cy_px", 250.0, "camera.cy_px is 250.0; it must be a finite pixel coordinate inside the image (-0.5 to 239.5)"),
        ("fx_px", -224.0, "camera.fx_px is -224.0; it must be a finite number above 0"),
        ("rate_hz", float("inf"), "camera.rate_hz is inf; it must be a finite number above 0"),
    ],
)
def test_a_bad_camera_value_is_refused_naming_the_rig_file_and_the_field(folder, field, value, problem):
    _edit_yaml(folder / "rig.yaml", lambda rig: rig["camera"].__setitem__(field, value))
    msg = _refused(ConfigError, folder, problem)
    assert msg == f"{folder / 'rig.yaml'}: {problem}"


def test_a_nan_distortion_coefficient_is_refused(folder):
    _edit_yaml(folder / "rig.yaml", lambda rig: rig["camera"]["distortion"].__setitem__(1, float("nan")))
    _refused(ConfigError, folder, "rig.yaml: camera.distortion has k2 = nan; every coefficient must be a finite number")


def test_a_non_rigid_laser_mount_is_refused(folder):
    _edit_yaml(folder / "rig.yaml", lambda rig: rig["laser"]["T_body_laser"][0].__setitem__(0, 2.0))
    _refused(ConfigError, folder, "rig.yaml: laser.T_body_laser rotation block is not a proper rotation")


def test_kitti_intrinsics_are_checked_as_a_rig_file_would_be(tmp_path):
    from dem_graph.datasets.kitti import KittiOdometrySequence

    seq = tmp_path / "sequences" / "00"
    (seq / "image_0").mkdir(parents=True)
    (seq / "velodyne").mkdir()
    assert cv2.imwrite(str(seq / "image_0" / "000000.png"), np.zeros((20, 30), np.uint8))
    (seq / "velodyne" / "000000.bin").write_bytes(b"")
    (seq / "times.txt").write_text("0.0\n")
    Tr = "Tr: 0 -1 0 0 0 0 -1 0 1 0 0 0"
    (seq / "calib.txt").write_text(f"P0: -20 0 15 0 0 20 10 0 0 0 1 0\n{Tr}\n")
    with pytest.raises(ConfigError) as info:
        KittiOdometrySequence(tmp_path)
    assert str(info.value) == f"{seq / 'calib.txt'}: camera.fx_px is -20.0; it must be a finite number above 0"
    (seq / "calib.txt").write_text(f"P0: nan 0 15 0 0 20 10 0 0 0 1 0\n{Tr}\n")
    with pytest.raises(DatasetError, match=r"calib\.txt: 'P0' holds NaN or infinite values"):
        KittiOdometrySequence(tmp_path)


# ---------------------------------------------------------------------------------------------- odometry covariances


def _set_covariance(folder, index, edit):
    _edit_npz(folder / "odometry.npz", lambda z: edit(z["covariance"][index]))


def test_a_negative_variance_is_refused_with_the_file_and_index(folder):
    _set_covariance(folder, 3, lambda C: C.__setitem__((3, 3), -1e-4))
    msg = _refused(DatasetError, folder, "odometry.npz: covariance[3] has a negative variance: translation x [3,3] = -0.0001")
    assert msg.startswith(str(folder / "odometry.npz"))


def test_a_covariance_that_is_not_positive_definite_is_refused(folder):
    def correlate(C):
        C[0, 1] = C[1, 0] = 1.0

    _set_covariance(folder, 5, correlate)
    _refused(DatasetError, folder, "odometry.npz: covariance[5] is not positive definite (smallest eigenvalue")


def test_an_asymmetric_covariance_is_refused(folder):
    _set_covariance(folder, 2, lambda C: C.__setitem__((3, 4), 1e-5))
    _refused(DatasetError, folder, "odometry.npz: covariance[2] is not symmetric")


def test_a_covariance_symmetric_to_rounding_is_accepted(folder):
    _set_covariance(folder, 2, lambda C: C.__setitem__((3, 4), C[3, 3] * 1e-9))  # far below SYMMETRY_RTOL of the largest entry
    FolderSequence(folder)


def test_an_infinite_covariance_is_refused(folder):
    _set_covariance(folder, 7, lambda C: C.__setitem__((5, 5), np.inf))
    _refused(DatasetError, folder, "odometry.npz: covariance[7] contains NaN or infinite values")


def _odometry(sequence):
    return [e for e in sequence.events() if isinstance(e, Odometry)]


def test_all_zero_covariances_are_repaired_with_the_rigs_noise_model(folder, caplog):
    _edit_npz(folder / "odometry.npz", lambda z: z["covariance"].__setitem__(slice(None), 0.0))
    caplog.set_level(logging.WARNING)
    sequence = FolderSequence(folder)
    warnings = _warnings(caplog)
    assert len(warnings) == 1
    assert (
        "odometry.npz: 16 of 16 odometry covariances are all zero (unknown, as in ROS; first: index 0): replaced by the rig's odometry noise model"
        in warnings[0]
    )
    spec = sequence.rig.odometry
    events = _odometry(sequence)
    assert len(events) == 16
    for e in events:
        distance_m = float(np.linalg.norm(e.T_prev_curr[:3, 3]))
        np.testing.assert_allclose(e.covariance, spec.increment_covariance(distance_m), rtol=0, atol=1e-12)


def test_one_zero_covariance_is_repaired_and_the_others_kept(folder, caplog):
    original = np.load(folder / "odometry.npz")["covariance"].copy()
    _set_covariance(folder, 4, lambda C: C.__setitem__(slice(None), 0.0))
    caplog.set_level(logging.WARNING)
    events = _odometry(FolderSequence(folder))
    assert "1 of 16 odometry covariances are all zero (unknown, as in ROS; first: index 4)" in _warnings(caplog)[0]
    spec = FolderSequence(folder).rig.odometry
    np.testing.assert_allclose(events[4].covariance, spec.covariance_of(events[4].T_prev_curr), rtol=0, atol=1e-12)
    for e in events[:4] + events[5:]:
        np.testing.assert_array_equal(e.covariance, original[e.index])


def test_a_zero_covariance_without_an_odometry_block_uses_the_default_model(folder, caplog):
    _edit_yaml(folder / "rig.yaml", lambda rig: rig.pop("odometry"))
    _set_covariance(folder, 0, lambda C: C.__setitem__(slice(None), 0.0))
    caplog.set_level(logging.WARNING)
    event = _odometry(FolderSequence(folder))[0]
    assert (
        "replaced by the default odometry noise model (the rig has no odometry block) for each increment's length" in _warnings(caplog)[0]
    )
    np.testing.assert_allclose(event.covariance, OdometrySpec().covariance_of(event.T_prev_curr), rtol=0, atol=1e-12)


def test_an_empty_odometry_file_opens(folder):
    _edit_npz(folder / "odometry.npz", lambda z: z.update({k: v[:0] for k, v in z.items()}))
    _edit_yaml(folder / "dataset.yaml", lambda meta: meta["counts"].__setitem__("odometry", 0))
    assert not _odometry(FolderSequence(folder))


def test_covariance_problems_count_every_bad_matrix():
    C = np.stack([np.eye(6)] * 5)
    C[1, 2, 2] = -1.0
    C[3, 0, 0] = np.nan
    first, problem, count = covariance_problems(C)
    assert (first, count) == (1, 2) and problem == "has a negative variance: rotation z [2,2] = -1.0"
    assert covariance_problems(np.stack([np.eye(6)] * 3)) is None
    assert covariance_problems(np.zeros((0, 6, 6))) is None


# ---------------------------------------------------------------------------------------------- odometry motion


def test_an_increment_beyond_the_vehicles_speed_is_skipped_with_a_warning(folder, caplog):
    _edit_npz(folder / "odometry.npz", lambda z: z["T_prev_curr"][6].__setitem__((0, 3), z["T_prev_curr"][6][0, 3] + 5.0))
    caplog.set_level(logging.WARNING)
    sequence = FolderSequence(folder)
    warnings = _warnings(caplog)
    assert len(warnings) == 1
    assert "odometry.npz: 1 of 16 odometry increments are beyond the vehicle's motion (first: index 6, " in warnings[0]
    assert "m/s > input_checks.max_speed_mps = 10 m/s): skipped" in warnings[0]
    indices = [e.index for e in _odometry(sequence)]
    assert indices == [i for i in range(16) if i != 6]
    assert sequence.event_count() == len(list(sequence.events())) == 8 + 4 + 15 + sequence.n_imu


def test_an_increment_turning_too_fast_is_skipped(folder, caplog):
    _edit_npz(
        folder / "odometry.npz", lambda z: z["T_prev_curr"][3].__setitem__((slice(0, 3), slice(0, 3)), rotation_from_rpy(0.0, 0.0, 1.0))
    )
    caplog.set_level(logging.WARNING)
    indices = [e.index for e in _odometry(FolderSequence(folder))]
    assert 3 not in indices and len(indices) == 15
    assert "rad/s > input_checks.max_rotation_rate_rad_s = 2 rad/s" in _warnings(caplog)[0]


def test_the_limits_are_settings(folder, caplog):
    _edit_npz(folder / "odometry.npz", lambda z: z["T_prev_curr"][6].__setitem__((0, 3), 1.0))  # 1 m in 20 ms: 50 m/s
    caplog.set_level(logging.WARNING)
    assert len(_odometry(FolderSequence(folder, InputChecks(max_speed_mps=100.0)))) == 16
    assert not _warnings(caplog)


def test_increment_rates_in_metres_and_radians_per_second():
    T = np.stack([make_pose(rotation_from_rpy(0.0, 0.0, 0.2), [0.3, 0.4, 0.0]), np.eye(4), make_pose(np.eye(3), [1.0, 0.0, 0.0])])
    speed_mps, rate_rad_s = increment_rates(T, np.array([0.5, 0.0, 0.0]))
    np.testing.assert_allclose(speed_mps, [1.0, 0.0, np.inf])
    np.testing.assert_allclose(rate_rad_s, [0.4, 0.0, 0.0], atol=1e-12)
    keep = plausible_increments("here", T, np.array([0.5, 0.0, 0.0]), InputChecks())
    assert keep.tolist() == [True, True, False]


def test_a_skipped_increment_leaves_no_hole_in_the_integrated_motion():
    step = make_pose(rotation_from_rpy(0.0, 0.0, 0.01), [0.02, 0.0, 0.0])  # 1 m/s at 50 Hz
    cov = np.eye(6) * 1e-6
    events = [Odometry(0.02 * (k + 1), 0.02 * k, step, cov, k) for k in range(10)]
    whole, bridged = OdometryIntegrator(0.0), OdometryIntegrator(0.0)
    for e in events:
        whole.add(e)
        if e.index != 4:  # the reader skipped it
            bridged.add(e)
    U_whole, Q_whole = whole.increment(0.2)
    U_bridged, Q_bridged = bridged.increment(0.2)
    np.testing.assert_allclose(U_bridged, U_whole, atol=1e-12)  # constant velocity bridges it exactly
    np.testing.assert_allclose(Q_bridged, Q_whole, rtol=1e-9)  # with the last increment's whole covariance


def test_a_frame_inside_a_skipped_increment_is_bridged_on_both_sides():
    step = make_pose(np.eye(3), [0.02, 0.0, 0.0])
    bridged = OdometryIntegrator(0.0)
    for k in (0, 1, 3, 4):  # increment 2, over [0.04, 0.06], is missing
        bridged.add(Odometry(0.02 * (k + 1), 0.02 * k, step, np.eye(6) * 1e-6, k))
    U1, _ = bridged.increment(0.05)
    U2, _ = bridged.increment(0.1)
    np.testing.assert_allclose(U1[0, 3], 0.05, atol=1e-12)
    np.testing.assert_allclose(U2[0, 3], 0.05, atol=1e-12)


# ---------------------------------------------------------------------------------------------- clocks


def test_a_clock_jump_in_camera_csv_is_refused_naming_the_line(folder):
    path = folder / "camera.csv"
    lines = path.read_text().splitlines()
    for k in range(5, len(lines)):  # frames 4 on, 100 s later
        index, t, name = lines[k].split(",")
        lines[k] = f"{index},{float(t) + 100.0!r},{name}"
    path.write_text("\n".join(lines) + "\n")
    msg = _refused(DatasetError, folder, "camera.csv: line 6: frame 4 t_s = 100.16 s is 100.040 s after the one before (0.12 s)")
    assert "more than input_checks.max_gap_s = 10 s: a clock fault" in msg
    FolderSequence(folder, InputChecks(max_gap_s=200.0))  # a setting: a longer gap is allowed when asked


def test_a_clock_jump_in_the_laser_is_refused(folder):
    _edit_npz(folder / "laser.npz", lambda z: z["t_s"].__setitem__(slice(2, None), z["t_s"][2:] + 50.0))
    _refused(DatasetError, folder, "laser.npz: t_s[2] = 50.173 s is 50.080 s after the one before (0.093 s)", "a clock fault")


def test_a_clock_jump_in_the_odometry_is_refused(folder):
    def jump(z):
        z["t_s"][9:] += 30.0
        z["t_prev_s"][9:] += 30.0

    _edit_npz(folder / "odometry.npz", jump)
    _refused(DatasetError, folder, "odometry.npz: t_s[9] = ", "after the one before", "a clock fault")


def test_a_log_starting_long_after_its_start_time_is_refused(folder):
    _edit_yaml(folder / "dataset.yaml", lambda meta: meta.__setitem__("t_start_s", -20.0))
    _refused(DatasetError, folder, "camera.csv: line 2: frame 0 t_s = 0.0 s is 20.000 s after the log's start (-20.0 s)")


# ---------------------------------------------------------------------------------------------- images


def test_images_of_another_size_than_the_rigs_are_refused_on_open(folder):
    _edit_yaml(folder / "rig.yaml", lambda rig: rig["camera"].update(width_px=640, height_px=480, cx_px=319.5, cy_px=239.5))
    msg = _refused(DatasetError, folder, "image is 320x240 px but the rig's camera is 640x480 px")
    assert msg.startswith(f"{folder / 'images' / '000000.png'}: ")


def test_a_later_image_of_another_size_is_refused_when_read(folder):
    assert cv2.imwrite(str(folder / "images" / "000005.png"), np.full((120, 160), 99, np.uint8))
    sequence = FolderSequence(folder)  # only the first image is read on open
    with pytest.raises(DatasetError) as info:
        list(sequence.events())
    assert (
        str(info.value)
        == f"{folder / 'images' / '000005.png'}: image is 160x120 px but the rig's camera is 320x240 px (camera.width_px x camera.height_px): the rig is not this camera's"
    )


def _blacken(folder, frames):
    for k in frames:
        path = folder / "images" / f"{k:06d}.png"
        image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        assert cv2.imwrite(str(path), image * 0)


def test_frames_without_texture_are_marked_and_warned_once(folder, caplog):
    _blacken(folder, (2, 3, 4))
    caplog.set_level(logging.WARNING)
    frames = [e for e in FolderSequence(folder).events() if isinstance(e, CameraFrame)]
    assert [f.textureless for f in frames] == [False, False, True, True, True, False, False, False]
    warnings = _warnings(caplog)
    assert len(warnings) == 1
    assert warnings[0].startswith(
        f"{folder / 'images' / '000002.png'}: frame 2 at 0.080 s has no texture (grey-level std 0.00 DN < input_checks.min_image_std_dn = 2 DN)"
    )


def test_the_texture_limit_is_a_setting(folder, caplog):
    _blacken(folder, (2,))
    caplog.set_level(logging.WARNING)
    frames = [e for e in FolderSequence(folder, InputChecks(min_image_std_dn=0.0)).events() if isinstance(e, CameraFrame)]
    assert not any(f.textureless for f in frames) and not _warnings(caplog)


# ---------------------------------------------------------------------------------------------- laser


def test_a_log_without_laser_scans_is_said_on_open(folder, caplog):
    _edit_npz(folder / "laser.npz", lambda z: z.update(t_s=z["t_s"][:0], ranges_m=z["ranges_m"][:0]))
    _edit_yaml(folder / "dataset.yaml", lambda meta: meta["counts"].__setitem__("scans", 0))
    caplog.set_level(logging.WARNING)
    sequence = FolderSequence(folder)
    assert _warnings(caplog) == [f"{folder / 'laser.npz'}: no laser scans: the map will hold only camera points"]
    assert not any(isinstance(e, LaserScan) for e in sequence.events())


def test_a_sound_log_opens_without_a_warning(folder, caplog):
    caplog.set_level(logging.WARNING)
    sequence = FolderSequence(folder)
    events = list(sequence.events())
    assert sequence.n_imu == 63  # 0.31 s at 200 Hz
    assert len(events) == sequence.event_count() == 8 + 4 + 16 + 63
    assert not _warnings(caplog)


def test_the_limits_must_be_positive():
    with pytest.raises(ValidationError, match="max_speed_mps"):
        InputChecks(max_speed_mps=0.0)
    with pytest.raises(ValidationError, match="max_gap_s"):
        InputChecks(max_gap_s=-1.0)


# ---------------------------------------------------------------------------------------------- a ROS bag


BEAMS = PlanarBeams(angle_min_rad=-0.5, angle_increment_rad=0.01, count=101)


def _bag_rig():
    rig = default_rig()
    camera = rig.camera.model_copy(update=dict(width_px=32, height_px=24, fx_px=22.4, fy_px=22.4, cx_px=15.5, cy_px=11.5))
    return rig.model_copy(update={"camera": camera, "laser": rig.laser.model_copy(update={"beams": BEAMS})})


def _write_bag(path, scan_jump_s: float = 0.0, odometry_jump_m: float = 0.0, nan_covariance: bool = False, black_frame: int | None = None):
    """A ROS 2 bag of 4 frames (grey 32x24), 5 scans and 6 odometry messages at 1 m/s, with the faults asked for."""
    rosbags = pytest.importorskip("rosbags")  # noqa: F841 - the optional dependency
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    T = store.types
    G = "geometry_msgs/msg/"

    def header(t_s, frame):
        return T["std_msgs/msg/Header"](
            stamp=T["builtin_interfaces/msg/Time"](sec=int(t_s), nanosec=round((t_s % 1) * 1e9)), frame_id=frame
        )

    rng = np.random.default_rng(0)
    messages = []
    for k in range(4):
        t = 100.0 + 0.25 * k
        image = np.zeros((24, 32), np.uint8) if k == black_frame else rng.integers(0, 256, (24, 32), dtype=np.uint8)
        msg = T["sensor_msgs/msg/Image"](
            header=header(t, "cam"), height=24, width=32, encoding="mono8", is_bigendian=0, step=32, data=image.ravel()
        )
        messages.append(("/cam/image", "sensor_msgs/msg/Image", t, msg))
    for k in range(5):
        t = 100.0 + 0.2 * k + (scan_jump_s if k >= 3 else 0.0)
        msg = T["sensor_msgs/msg/LaserScan"](
            header=header(t, "laser"),
            angle_min=BEAMS.angle_min_rad,
            angle_max=BEAMS.angle_min_rad + 1.0,
            angle_increment=BEAMS.angle_increment_rad,
            time_increment=0.0,
            scan_time=0.1,
            range_min=0.1,
            range_max=40.0,
            ranges=np.full(BEAMS.count, 5.0, np.float32),
            intensities=np.zeros(0, np.float32),
        )
        messages.append(("/scan", "sensor_msgs/msg/LaserScan", t, msg))
    for k in range(6):
        t = 100.0 + 0.15 * k
        x_m = 0.15 * k + (odometry_jump_m if k >= 3 else 0.0)
        q = quat_xyzw_from_matrix(np.eye(3))
        pose = T[G + "Pose"](position=T[G + "Point"](x=x_m, y=0.0, z=0.0), orientation=T[G + "Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]))
        covariance = np.zeros(36)
        if nan_covariance and k == 2:
            covariance[0] = np.nan
        twist = T[G + "Twist"](linear=T[G + "Vector3"](x=0.0, y=0.0, z=0.0), angular=T[G + "Vector3"](x=0.0, y=0.0, z=0.0))
        msg = T["nav_msgs/msg/Odometry"](
            header=header(t, "odom"),
            child_frame_id="base_link",
            pose=T[G + "PoseWithCovariance"](pose=pose, covariance=covariance),
            twist=T[G + "TwistWithCovariance"](twist=twist, covariance=np.zeros(36)),
        )
        messages.append(("/odom", "nav_msgs/msg/Odometry", t, msg))
    with Writer(path, version=9) as writer:
        connections = {}
        for topic, msgtype, t, msg in sorted(messages, key=lambda m: m[2]):
            if topic not in connections:
                connections[topic] = writer.add_connection(topic, msgtype, typestore=store)
            writer.write(connections[topic], round(t * 1e9), store.serialize_cdr(msg, msgtype))
    return path


def _open_bag(path, **kwargs):
    from dem_graph.datasets.rosbag import RosbagSequence

    return RosbagSequence(path, _bag_rig(), "/cam/image", "/scan", "/odom", **kwargs)


def test_a_bag_with_an_odometry_jump_a_bad_covariance_and_a_black_frame_is_read_with_warnings(tmp_path, caplog):
    bag = _write_bag(tmp_path / "bag", odometry_jump_m=5.0, nan_covariance=True, black_frame=2)
    caplog.set_level(logging.WARNING)
    sequence = _open_bag(bag)
    odometry = [e for e in sequence.events() if isinstance(e, Odometry)]
    assert [e.index for e in odometry] == [0, 1, 3, 4]  # increment 2 (messages 2 -> 3) jumps 5 m in 0.15 s
    messages = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert any(
        "topic /odom: 1 of 5 odometry increments are beyond the vehicle's motion (first: index 2, 34.3 m/s > input_checks.max_speed_mps = 10 m/s)"
        in m
        for m in messages
    )
    assert any(
        "topic /odom: 1 of 6 messages carry a pose covariance that is not one (first: message 2, it contains NaN or infinite values); not used"
        in m
        for m in messages
    )
    assert any("topic /cam/image: frame 2 at 100.500 s has no texture" in m for m in messages)
    frames = [e for e in sequence.events() if isinstance(e, CameraFrame)]
    assert [f.textureless for f in frames] == [False, False, True, False]


def test_a_clock_jump_in_a_bag_is_refused_naming_the_topic_and_message(tmp_path):
    bag = _write_bag(tmp_path / "bag", scan_jump_s=60.0)
    with pytest.raises(DatasetError) as info:
        _open_bag(bag)
    msg = str(info.value)
    assert msg.startswith(f"{bag} topic /scan: message 3: time = ") and "s is 60.200 s after the one before" in msg
    assert "input_checks.max_gap_s = 10 s: a clock fault" in msg
