"""Calibration recordings in ROS bags: a simulated calibration written both as a ROS 2 bag and as a RADLOCC
folder calibrates to the same T_cam_laser, near the truth; a ROS 1 bag reads back exactly; bad bags and bad
command lines are one-line errors."""

from __future__ import annotations

import json
from dataclasses import replace
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from dem_graph.calibration.board import BoardSpec
from dem_graph.calibration.pipeline import CalibrationOptions, calibrate_recording
from dem_graph.calibration.readers import ScanSet, read_radlocc_recording, write_opencv_intrinsics
from dem_graph.calibration.rosbag_reader import read_rosbag_recording
from dem_graph.calibration.simulate import simulate_calibration, write_recording
from dem_graph.cli import main
from dem_graph.datasets.rosbag import stamp_s
from dem_graph.errors import DatasetError
from dem_graph.geometry.lie import local

pytest.importorskip("rosbags")
from rosbags.typesys import Stores, get_typestore  # noqa: E402

IMAGE, SCAN, INFO = "/camera/image_raw", "/scan", "/camera/camera_info"
RANGE_SIGMA_M = 0.01


def _stamp(t_s: float) -> tuple[int, int]:
    sec = int(np.floor(t_s))
    return sec, int(round((t_s - sec) * 1e9))


def _stamped(t_s: np.ndarray) -> np.ndarray:
    """The times a bag's header stamps give back for ``t_s`` (whole nanoseconds, read as stamp_s reads them)."""
    return np.array([stamp_s(SimpleNamespace(stamp=SimpleNamespace(sec=s, nanosec=ns))) for s, ns in map(_stamp, t_s)])


def _bag_ready(sim):
    """``sim`` with what a bag carries exactly: float32 beam angles and ranges, stamps in whole nanoseconds."""
    scans = sim.scans
    f32 = ScanSet(
        _stamped(scans.times_s),
        float(np.float32(scans.angle_min_rad)),
        float(np.float32(scans.angle_increment_rad)),
        scans.ranges_m.astype(np.float32).astype(float),
    )
    return replace(sim, scans=f32, image_times_s=_stamped(sim.image_times_s))


def _messages(store, ros1: bool, sim, images, with_info: bool = True):
    """(topic, msgtype, bag time ns, message) for the images (mono8), the scans and one CameraInfo."""
    T = store.types
    extra = {"seq": 0} if ros1 else {}

    def header(t_s, frame):
        sec, ns = _stamp(t_s)
        return T["std_msgs/msg/Header"](**extra, stamp=T["builtin_interfaces/msg/Time"](sec=sec, nanosec=ns), frame_id=frame)

    def ns(t_s):
        sec, nsec = _stamp(t_s)
        return sec * 10**9 + nsec

    out = []
    for t_s, img in zip(sim.image_times_s, images):
        h, w = img.shape
        msg = T["sensor_msgs/msg/Image"](header=header(t_s, "cam"), height=h, width=w, encoding="mono8", is_bigendian=0, step=w, data=img.ravel())
        out.append((IMAGE, "sensor_msgs/msg/Image", ns(t_s), msg))
    s = sim.scans
    for t_s, r in zip(s.times_s, s.ranges_m):
        msg = T["sensor_msgs/msg/LaserScan"](
            header=header(t_s, "laser"), angle_min=s.angle_min_rad, angle_max=s.angle_min_rad + s.angle_increment_rad * (s.n_beams - 1),
            angle_increment=s.angle_increment_rad, time_increment=0.0, scan_time=0.025, range_min=0.0, range_max=100.0,
            ranges=r.astype(np.float32), intensities=np.zeros(0, dtype=np.float32),
        )
        out.append((SCAN, "sensor_msgs/msg/LaserScan", ns(t_s), msg))
    if with_info:
        intr = sim.intrinsics
        P = np.hstack([intr.K, np.zeros((3, 1))])
        mats = {"d": intr.distortion.copy(), "k": intr.K.ravel().copy(), "r": np.eye(3).ravel(), "p": P.ravel()}
        if ros1:
            mats = {key.upper(): value for key, value in mats.items()}
        roi = T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
        msg = T["sensor_msgs/msg/CameraInfo"](
            header=header(sim.image_times_s[0], "cam"), height=intr.height_px, width=intr.width_px, distortion_model="plumb_bob",
            **mats, binning_x=0, binning_y=0, roi=roi,
        )
        out.append((INFO, "sensor_msgs/msg/CameraInfo", ns(sim.image_times_s[0]), msg))
    return sorted(out, key=lambda m: m[2])


def _store(ros1: bool):
    return get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)


def _write_bag(path, ros1: bool, messages, store):
    if ros1:
        from rosbags.rosbag1 import Writer

        writer, serialize = Writer(path), store.serialize_ros1
    else:
        from rosbags.rosbag2 import Writer

        writer, serialize = Writer(path, version=9), store.serialize_cdr
    with writer:
        connections = {}
        for topic, msgtype, t_ns, msg in messages:
            if topic not in connections:
                connections[topic] = writer.add_connection(topic, msgtype, typestore=store)
            writer.write(connections[topic], t_ns, serialize(msg, msgtype))
    return path


def _small_sim(n_views: int = 4):
    """A simulation without rendered images (their pixels do not matter to the reading tests)."""
    sim = _bag_ready(simulate_calibration(seed=2, n_views=n_views, range_sigma_m=RANGE_SIGMA_M))
    rng = np.random.default_rng(1)
    images = [rng.integers(0, 256, (sim.intrinsics.height_px, sim.intrinsics.width_px), dtype=np.uint8) for _ in range(n_views)]
    return sim, images


def _errors(T_true, T):
    return np.degrees(np.linalg.norm(local(T_true, T)[:3])), np.linalg.norm(T[:3, 3] - T_true[:3, 3])


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """The simulation of tests/test_calibration_io.py's command test (seed 5, 6 views, 1 cm ranges), rendered into a
    RADLOCC folder and the same images, scans and intrinsics into a ROS 2 bag."""
    tmp = tmp_path_factory.mktemp("calbag")
    sim = _bag_ready(simulate_calibration(seed=5, n_views=6, range_sigma_m=RANGE_SIGMA_M))
    folder = write_recording(sim, tmp / "rec", seed=5, samples=1)
    images = [cv2.imread(str(folder / "data" / f"RGB{k + 1}.png"), cv2.IMREAD_UNCHANGED) for k in range(6)]
    store = _store(False)
    bag = _write_bag(tmp / "bag", False, _messages(store, False, sim, images), store)
    return SimpleNamespace(sim=sim, folder=folder, bag=bag, images=images, tmp=tmp)


def test_bag_and_folder_of_one_simulation_calibrate_alike_and_near_the_truth(recorded):
    sim = recorded.sim
    from_bag = read_rosbag_recording(recorded.bag, IMAGE, SCAN, camera_info_topic=INFO)
    from_folder = read_radlocc_recording(recorded.folder)
    # the bag holds the same data as the folder, bit for bit
    np.testing.assert_array_equal(from_bag.image_times_s, from_folder.image_times_s)
    np.testing.assert_array_equal(from_bag.scans.times_s, from_folder.scans.times_s)
    np.testing.assert_array_equal(from_bag.scans.ranges_m, from_folder.scans.ranges_m)
    assert (from_bag.scans.angle_min_rad, from_bag.scans.angle_increment_rad) == (from_folder.scans.angle_min_rad, from_folder.scans.angle_increment_rad)
    np.testing.assert_array_equal(from_bag.intrinsics.K, from_folder.intrinsics.K)
    np.testing.assert_array_equal(from_bag.intrinsics.distortion, from_folder.intrinsics.distortion)
    for k in range(6):
        np.testing.assert_array_equal(from_bag.load_image(k), from_folder.load_image(k))
    assert from_bag.board is None and from_folder.board == sim.board
    options = CalibrationOptions(range_sigma_m=RANGE_SIGMA_M)
    bag_result = calibrate_recording(from_bag, options, board=sim.board)
    folder_result = calibrate_recording(from_folder, options)
    # same data, same result (to rounding)
    np.testing.assert_allclose(bag_result.T_cam_laser, folder_result.T_cam_laser, rtol=0, atol=1e-9)
    assert [v.used for v in bag_result.views] == [v.used for v in folder_result.views]
    # tests/test_calibration_io.py's tolerance for 6 views from rendered images: 2 cm; and 0.5 deg
    rot_deg, trans_m = _errors(sim.T_cam_laser, bag_result.T_cam_laser)
    assert rot_deg < 0.5 and trans_m < 0.02, (rot_deg, trans_m)


def test_command_calibrates_a_bag_with_the_board_given(recorded):
    out = recorded.tmp / "out"
    args = ["calibrate", str(recorded.bag), "--format", "rosbag", "--image-topic", IMAGE, "--scan-topic", SCAN, "--camera-info-topic", INFO, "--camera-height-m", "1.2", "--camera-pitch-deg", "20"]
    run = CliRunner().invoke(main, [*args, "--board", "9x6", "--square-m", "0.09", "--range-sigma-m", str(RANGE_SIGMA_M), "--out", str(out)])
    assert run.exit_code == 0, run.output
    T = np.asarray(json.loads((out / "calibration.json").read_text())["T_cam_laser"])
    expected = calibrate_recording(read_radlocc_recording(recorded.folder), CalibrationOptions(range_sigma_m=RANGE_SIGMA_M)).T_cam_laser
    np.testing.assert_allclose(T, expected, rtol=0, atol=1e-9)
    picture = cv2.imread(str(out / "views" / "view_01.png"), cv2.IMREAD_UNCHANGED)  # a bag numbers its images from 1
    assert picture.shape == (480, 640, 3)  # the bag's grey image drawn on in colour
    # without --board the bag does not say which board it shows
    run = CliRunner().invoke(main, [*args, "--out", str(recorded.tmp / "o2")])
    assert run.exit_code == 2 and "give --board COLSxROWS and --square-m" in run.output


def test_ros1_bag_reads_back_exactly(tmp_path):
    sim, images = _small_sim()
    store = _store(True)
    bag = _write_bag(tmp_path / "cal.bag", True, _messages(store, True, sim, images), store)
    rec = read_rosbag_recording(bag, IMAGE, SCAN, camera_info_topic=INFO)
    np.testing.assert_array_equal(rec.image_times_s, sim.image_times_s)
    np.testing.assert_array_equal(rec.scans.times_s, sim.scans.times_s)
    np.testing.assert_array_equal(rec.scans.ranges_m, sim.scans.ranges_m)
    assert (rec.scans.angle_min_rad, rec.scans.angle_increment_rad, rec.scans.n_beams) == (
        sim.scans.angle_min_rad, sim.scans.angle_increment_rad, sim.scans.n_beams,
    )
    np.testing.assert_array_equal(rec.intrinsics.K, sim.intrinsics.K)
    np.testing.assert_array_equal(rec.intrinsics.distortion, sim.intrinsics.distortion)
    assert (rec.intrinsics.width_px, rec.intrinsics.height_px) == (640, 480)
    assert len(rec.image_names) == 4 and rec.board is None
    for k in (3, 0):  # any order: each read from the bag again
        np.testing.assert_array_equal(rec.load_image(k), images[k])
        colour = rec.load_image(k, color=True)
        assert colour.shape == (480, 640, 3) and all(np.array_equal(colour[:, :, c], images[k]) for c in range(3))
    picked = rec.select([2, 1])
    np.testing.assert_array_equal(picked.image_times_s, sim.image_times_s[[2, 1]])
    np.testing.assert_array_equal(picked.load_image(0), images[2])
    # the intrinsics from an OpenCV file instead of the topic, with its board
    write_opencv_intrinsics(sim.intrinsics, BoardSpec(7, 5, 0.1), tmp_path / "cam.xml")
    rec = read_rosbag_recording(bag, IMAGE, SCAN, intrinsics_path=tmp_path / "cam.xml")
    assert rec.board == BoardSpec(7, 5, 0.1)
    np.testing.assert_array_equal(rec.intrinsics.K, sim.intrinsics.K)


def _swap_stamps(messages, topic, i, j):
    """Swap the header stamps of the ``i``-th and ``j``-th messages of ``topic`` (bag order kept)."""
    idx = [n for n, m in enumerate(messages) if m[0] == topic]
    a, b = messages[idx[i]], messages[idx[j]]
    messages[idx[i]] = (*a[:3], replace(a[3], header=b[3].header))
    messages[idx[j]] = (*b[:3], replace(b[3], header=a[3].header))


def _change_scan(messages, i, **fields):
    idx = [n for n, m in enumerate(messages) if m[0] == SCAN][i]
    messages[idx] = (*messages[idx][:3], replace(messages[idx][3], **fields))


@pytest.mark.parametrize(
    "change, topics, message",
    [
        (None, (IMAGE, SCAN, "/camera/info"), r"no topic '/camera/info' in the bag \(topics: /camera/camera_info, /camera/image_raw, /scan\)"),
        (None, ("/cam", SCAN, INFO), r"no topic '/cam' in the bag"),
        (None, (SCAN, SCAN, INFO), r"topic /scan: has type sensor_msgs/msg/LaserScan, expected sensor_msgs/msg/Image or"),
        (lambda m: _change_scan(m, 2, ranges=np.ones(100, dtype=np.float32)), (IMAGE, SCAN, INFO), r"topic /scan: scan 2 has 100 beams from .* scan 0 has 721"),
        (lambda m: _change_scan(m, 1, angle_increment=0.005), (IMAGE, SCAN, INFO), r"topic /scan: scan 1 has 721 beams from -1.570796 rad every 0.005000 rad"),
        (lambda m: _swap_stamps(m, IMAGE, 1, 2), (IMAGE, SCAN, INFO), r"topic /camera/image_raw: message 2: time .* is not after the previous"),
        (lambda m: _swap_stamps(m, SCAN, 0, 3), (IMAGE, SCAN, INFO), r"topic /scan: message 1: time .* is not after the previous"),
    ],
    ids=["missing-info", "missing-image", "wrong-type", "beam-count", "beam-spacing", "image-stamps", "scan-stamps"],
)
def test_bad_bags_are_one_line_errors_naming_the_topic(tmp_path, change, topics, message):
    sim, images = _small_sim()
    store = _store(False)
    messages = _messages(store, False, sim, images)
    if change is not None:
        change(messages)
    bag = _write_bag(tmp_path / "bad", False, messages, store)
    with pytest.raises(DatasetError, match=message) as info:
        read_rosbag_recording(bag, *topics[:2], camera_info_topic=topics[2])
    assert str(bag) in str(info.value) and "\n" not in str(info.value)


@pytest.mark.parametrize(
    "info_fields, message",
    [
        ({"distortion_model": "equidistant"}, r"topic /camera/camera_info: distortion model 'equidistant' is not supported"),
        ({"distortion_model": "rational_polynomial", "d": np.array([-0.08, 0.05, 0.0, 0.0, 0.0, 0.01, 0.0, 0.0])}, r"8 coefficients, some beyond k3 non-zero"),
        ({"width": 320}, r"topic /camera/image_raw: images are 640x480, the intrinsics are for 320x480"),
        ({"k": np.zeros(9)}, r"topic /camera/camera_info: K is not a valid camera matrix"),
    ],
    ids=["model", "rational", "size", "K"],
)
def test_bad_camera_info_is_an_error(tmp_path, info_fields, message):
    sim, images = _small_sim(n_views=1)
    store = _store(False)
    messages = [(t, ty, ns, replace(m, **info_fields) if t == INFO else m) for t, ty, ns, m in _messages(store, False, sim, images)]
    bag = _write_bag(tmp_path / "bad", False, messages, store)
    with pytest.raises(DatasetError, match=message):
        read_rosbag_recording(bag, IMAGE, SCAN, camera_info_topic=INFO)


def test_rational_polynomial_with_zero_extra_coefficients_is_plumb_bob(tmp_path):
    sim, images = _small_sim(n_views=1)
    store = _store(False)
    d8 = np.concatenate([sim.intrinsics.distortion, np.zeros(3)])
    messages = [(t, ty, ns, replace(m, distortion_model="rational_polynomial", d=d8) if t == INFO else m) for t, ty, ns, m in _messages(store, False, sim, images)]
    rec = read_rosbag_recording(_write_bag(tmp_path / "rp", False, messages, store), IMAGE, SCAN, camera_info_topic=INFO)
    np.testing.assert_array_equal(rec.intrinsics.distortion, sim.intrinsics.distortion)


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--scan-topic", SCAN, "--camera-info-topic", INFO], "--format rosbag needs --image-topic"),
        (["--image-topic", IMAGE, "--camera-info-topic", INFO], "--format rosbag needs --scan-topic"),
        (["--image-topic", IMAGE, "--scan-topic", SCAN], "give --camera-info-topic or --intrinsics"),
        (["--image-topic", IMAGE, "--scan-topic", SCAN, "--camera-info-topic", INFO, "--board", "9"], "Invalid value for '--board': give the board's inner corners as COLSxROWS, e.g. 9x6, not '9'"),
        (["--image-topic", IMAGE, "--scan-topic", SCAN, "--camera-info-topic", INFO, "--board", "9x6x2"], "Invalid value for '--board'"),
        (["--image-topic", IMAGE, "--scan-topic", SCAN, "--camera-info-topic", INFO, "--board", "1x6"], "a board has at least 2x2 inner corners, not '1x6'"),
        (["--image-topic", IMAGE, "--scan-topic", SCAN, "--camera-info-topic", INFO, "--square-m", "-0.1"], "Invalid value for '--square-m'"),
    ],
    ids=["no-image-topic", "no-scan-topic", "no-intrinsics", "board-one-number", "board-three-numbers", "board-too-small", "negative-square"],
)
def test_command_line_errors_are_one_line_before_reading(tmp_path, extra, message):
    run = CliRunner().invoke(main, ["calibrate", str(tmp_path / "no-bag"), "--format", "rosbag", "--out", str(tmp_path / "o"), *extra])
    assert run.exit_code == 2, run.output
    errors = [line for line in run.output.splitlines() if line.startswith("Error:")]
    assert len(errors) == 1 and message in errors[0], run.output


def test_rosbag_options_with_the_radlocc_layout_are_an_error(tmp_path):
    run = CliRunner().invoke(main, ["calibrate", str(tmp_path), "--out", str(tmp_path / "o"), "--image-topic", IMAGE])
    assert run.exit_code == 2 and "Error: --image-topic: only for --format rosbag" in run.output
