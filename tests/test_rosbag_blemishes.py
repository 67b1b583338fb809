"""Robot logs as they come: bags (ROS 1 and MCAP) with one blemish at a time and all together, read
with one bad message costing one message; a stream mostly bad, or whose clock went back, refused in
one line; a ROS 1 bag without its index and an MCAP file cut short read up to the damage; the image
encodings robots publish made grey.

The bags are test_rosbag's (its writer and its messages), longer: 2 s of a vehicle driving a curve,
20 camera frames, 25 scans, 40 odometry messages."""

from __future__ import annotations

import copy
import dataclasses
import json
import logging
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from dem_graph.datasets.events import CameraFrame, LaserScan, Odometry
from dem_graph.datasets.rosbag import RosbagSequence, image_from_message
from dem_graph.errors import DatasetError
from dem_graph.geometry.se3 import make_pose, rotation_from_rpy

pytest.importorskip("rosbags")
from test_rosbag import BEAMS, _messages, _rig, write_bag  # noqa: E402  (tests/ is on sys.path)

N_FRAMES, N_SCANS, N_ODOM = 20, 25, 40
ARGS = ("/cam/image", "/scan", "/odom")
ODOM_NAN, DUPLICATED_IMAGE, SMALL_IMAGE, LATE_SCAN, SHORT_SCAN = 10, 5, 8, 12, 15  # the message each blemish touches


def _stamp(t_ns: int) -> tuple[int, int]:
    return 100 + t_ns // 10**9, t_ns % 10**9


def _long_truth():
    """test_rosbag's truth, longer: images, stamps (sec, nanosec), ranges, odometry poses (a curve at 0.8 m/s)."""
    rng = np.random.default_rng(3)
    images = [cv2.GaussianBlur(rng.integers(0, 256, (24, 32, 3), dtype=np.uint8), (3, 3), 0) for _ in range(N_FRAMES)]
    frame_t = [_stamp(100_000_000 * i) for i in range(N_FRAMES)]
    scan_t = [_stamp(80_000_000 * i + 5) for i in range(N_SCANS)]
    ranges = rng.uniform(0.5, 20.0, (N_SCANS, BEAMS.count)).astype(np.float32)
    odom_t = [_stamp(50_000_000 * i) for i in range(N_ODOM)]
    poses = [make_pose(rotation_from_rpy(0.0, 0.0, 0.01 * i), [0.04 * i, 0.001 * i * i, 0.0]) for i in range(N_ODOM)]
    return images, frame_t, scan_t, ranges, odom_t, poses


def _nth(msgs, topic: str, k: int) -> int:
    """The list position of the ``k``-th message of ``topic``."""
    return [i for i, m in enumerate(msgs) if m[0] == topic][k]


def _odom_nan(msgs, k=ODOM_NAN):
    i = _nth(msgs, "/odom", k)
    msg = copy.deepcopy(msgs[i][3])
    msg.pose.pose.position.x = np.nan
    msgs[i] = (*msgs[i][:3], msg)


def _duplicate_image(msgs):
    """A camera driver publishing frame 5 twice, with the same stamp."""
    i = _nth(msgs, "/cam/image", DUPLICATED_IMAGE)
    topic, msgtype, t_ns, msg = msgs[i]
    msgs.insert(i + 1, (topic, msgtype, t_ns + 1_000_000, msg))


def _small_image(msgs):
    i = _nth(msgs, "/cam/image", SMALL_IMAGE)
    msg = copy.deepcopy(msgs[i][3])
    msg.height, msg.width, msg.step = 12, 16, 48
    msg.data = msg.data[: 12 * 48]
    msgs[i] = (*msgs[i][:3], msg)


def _late_scan(msgs):
    """Scan 12 delivered late: its stamp 10 ms before scan 11's, recorded after it."""
    i11, i12 = _nth(msgs, "/scan", LATE_SCAN - 1), _nth(msgs, "/scan", LATE_SCAN)
    msg = copy.deepcopy(msgs[i12][3])
    before = msgs[i11][3].header.stamp
    msg.header.stamp = dataclasses.replace(before, nanosec=before.nanosec - 10_000_000)
    msgs[i12] = (*msgs[i12][:3], msg)


def _short_scan(msgs):
    i = _nth(msgs, "/scan", SHORT_SCAN)
    msg = copy.deepcopy(msgs[i][3])
    msg.ranges = msg.ranges[:50]
    msgs[i] = (*msgs[i][:3], msg)


BLEMISHES = {
    "odometry_nan": ([_odom_nan], {"odometry_nonfinite": 1}),
    "small_image": ([_small_image], {"camera_wrong_shape": 1}),
    "late_scan": ([_late_scan], {"laser_stamp_not_after": 1}),
    "short_scan": ([_short_scan], {"laser_wrong_shape": 1}),
    "duplicate_image": ([_duplicate_image], {"camera_stamp_not_after": 1}),  # last: "all" counts the others' messages before it is inserted
}
BLEMISHES["all"] = (
    [f for edits, _ in BLEMISHES.values() for f in edits],
    {k: v for _, counts in BLEMISHES.values() for k, v in counts.items()},
)


def _bag(path, fmt: str, edits=(), chunk_bytes: int | None = None):
    """A long bag (``fmt`` "ros1" or "mcap") with ``edits`` applied to its messages."""

    def messages(store, ros1):
        msgs = _messages(store, ros1, _long_truth())
        for edit in edits:
            edit(msgs)
        return msgs

    return write_bag(path, fmt == "ros1", messages=messages, mcap=fmt == "mcap", chunk_bytes=chunk_bytes)


def _open(bag, **kwargs):
    return RosbagSequence(bag, _rig(), *ARGS, body_frame="base_link", laser_frame="laser_link", **kwargs)


def _streams(seq):
    events = list(seq.events())
    return (
        [e for e in events if isinstance(e, CameraFrame)],
        [e for e in events if isinstance(e, LaserScan)],
        [e for e in events if isinstance(e, Odometry)],
    )


def _odometry_poses(odometry) -> dict[float, np.ndarray]:
    """The odometry's poses by time, integrated from the first message's (the identity)."""
    T = np.eye(4)
    poses = {odometry[0].t_prev_s: T}
    for o in odometry:
        T = T @ o.T_prev_curr
        poses[o.t_s] = T
    return poses


def _warnings(caplog) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]


@pytest.fixture(scope="module")
def clean(tmp_path_factory):
    """The clean bags, ROS 1 and MCAP, and what they read back."""
    out = {}
    for fmt in ("ros1", "mcap"):
        bag = _bag(tmp_path_factory.mktemp(fmt) / ("clean.bag" if fmt == "ros1" else "clean"), fmt)
        out[fmt] = (bag, _streams(_open(bag)))
    return out


@pytest.mark.parametrize("fmt", ["ros1", "mcap"])
@pytest.mark.parametrize("blemish", list(BLEMISHES))
def test_one_bad_message_costs_one_message(tmp_path, caplog, clean, fmt, blemish):
    edits, counts = BLEMISHES[blemish]
    bag = _bag(tmp_path / ("log.bag" if fmt == "ros1" else "log"), fmt, edits)
    caplog.set_level(logging.WARNING)
    seq = _open(bag)
    assert seq.skipped_messages() == counts
    frames, scans, odometry = _streams(seq)
    clean_frames, clean_scans, clean_odometry = clean[fmt][1]
    # what is left is the clean bag's, less the messages skipped: frames and scans exactly
    lost_frames = {SMALL_IMAGE} if "camera_wrong_shape" in counts else set()
    lost_scans = ({LATE_SCAN} if "laser_stamp_not_after" in counts else set()) | ({SHORT_SCAN} if "laser_wrong_shape" in counts else set())
    expected_frames = [f for k, f in enumerate(clean_frames) if k not in lost_frames]
    assert [f.t_s for f in frames] == [f.t_s for f in expected_frames]
    assert all(np.array_equal(f.image, g.image) for f, g in zip(frames, expected_frames))
    expected_scans = [s for k, s in enumerate(clean_scans) if k not in lost_scans]
    assert [s.t_s for s in scans] == [s.t_s for s in expected_scans]
    assert all(np.array_equal(s.ranges_m, g.ranges_m, equal_nan=True) for s, g in zip(scans, expected_scans))
    # the odometry's poses at every message kept are the clean bag's, to 1e-9 m
    poses, clean_poses = _odometry_poses(odometry), _odometry_poses(clean_odometry)
    assert len(poses) == N_ODOM - counts.get("odometry_nonfinite", 0)
    for t, T in poses.items():
        np.testing.assert_allclose(T, clean_poses[t], atol=1e-9)
    # one warning per kind skipped, naming the topic and the message, numbers as numbers
    skipped = [m for m in _warnings(caplog) if m.endswith(": skipped")]
    assert len(skipped) == len(counts)
    for m in skipped:
        assert "\n" not in m and "np.float64" not in m and " topic /" in m
    if "odometry_nonfinite" in counts:
        assert any(
            f"topic /odom: 1 of {N_ODOM} messages hold a value that is not finite (first: message {ODOM_NAN}, position (nan, " in m
            for m in skipped
        )
    if "laser_stamp_not_after" in counts:
        assert any(
            f"topic /scan: 1 of {N_SCANS} messages have a stamp not after the previous one" in m
            and f"message {LATE_SCAN}, stamp 100.87" in m
            for m in skipped
        )
    if "camera_stamp_not_after" in counts:
        assert any(
            f"topic /cam/image: 1 of {N_FRAMES + 1} messages have a stamp not after" in m
            and f"message {DUPLICATED_IMAGE + 1}, stamp 100.5 s" in m
            for m in skipped
        )


@pytest.mark.parametrize("fmt", ["ros1", "mcap"])
def test_a_run_over_a_blemished_bag_follows_the_clean_one(tmp_path, clean, fmt):
    """Every blemish at once: the run finishes, its trajectory within 5 mm of the clean bag's (both
    anchored at their first frame), and metrics.json counts what was skipped."""
    from dem_graph.pipeline.config import RunOverrides, run_config
    from dem_graph.pipeline.run import run_dataset, run_estimator

    edits, counts = BLEMISHES["all"]
    bag = _bag(tmp_path / ("log.bag" if fmt == "ros1" else "log"), fmt, edits)
    clean_seq = _open(clean[fmt][0])
    reference = run_estimator(clean_seq, run_config(clean_seq, None, RunOverrides(estimator="gm")), with_dem=False)
    run = run_dataset(_open(bag), RunOverrides(estimator="gm"), out_dir=tmp_path / "run")
    assert run.error is None and reference.error is None
    est, ref = run.estimator.trajectory(), reference.estimator.trajectory()
    assert len(est.t_s) == N_FRAMES - 1 and len(ref.t_s) == N_FRAMES  # frame 8 lost, the duplicate of 5 not counted
    ref_at = ref.at(est.t_s)
    rel_est = np.linalg.inv(est.poses_se3[0]) @ est.poses_se3
    rel_ref = np.linalg.inv(ref_at[0]) @ ref_at
    error_m = np.linalg.norm(rel_est[:, :3, 3] - rel_ref[:, :3, 3], axis=1)
    assert error_m.max() < 0.005, error_m
    assert np.linalg.norm(rel_ref[-1, :3, 3]) > 1.0  # the vehicle did move: the comparison means something
    metrics = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert metrics["skipped_messages"] == counts


@pytest.mark.parametrize("fmt", ["ros1", "mcap"])
def test_a_third_of_the_odometry_not_finite_is_refused_in_one_line(tmp_path, fmt):
    edits = [lambda msgs, k=k: _odom_nan(msgs, k) for k in range(1, N_ODOM, 3)]  # 13 of 40
    bag = _bag(tmp_path / ("log.bag" if fmt == "ros1" else "log"), fmt, edits)
    with pytest.raises(DatasetError) as info:
        _open(bag)
    message = str(info.value)
    assert message.startswith(
        f"{bag} topic /odom: 13 of 40 messages cannot be used (13 not finite; first: message 1, position (nan, 0.001, 0.000) m"
    )
    assert message.endswith(
        "more than input_checks.max_skipped_fraction = 20% of the stream, a faulty driver or recording rather than a blemish"
    )
    assert "\n" not in message and "np." not in message


def test_a_clock_that_goes_back_as_a_whole_is_refused(tmp_path):
    """Scans 15 to 24 stamped 1 s early: not ten late scans but a clock that went back."""

    def back(msgs):
        for k in range(15, N_SCANS):
            i = _nth(msgs, "/scan", k)
            msg = copy.deepcopy(msgs[i][3])
            msg.header.stamp = dataclasses.replace(msg.header.stamp, sec=msg.header.stamp.sec - 1)
            msgs[i] = (*msgs[i][:3], msg)

    bag = _bag(tmp_path / "log.bag", "ros1", [back])
    with pytest.raises(
        DatasetError,
        match=r"topic /scan: messages 15 to 24 \(10 in a row\) have stamps not after the messages before them .*the stream's clock went back",
    ):
        _open(bag)


def _unindex_and_cut(bag, keep_fraction: float) -> int:
    """``bag`` as a killed ``rosbag record`` leaves it: no index (index_pos 0), cut at ``keep_fraction`` of its bytes."""
    data = bytearray(bag.read_bytes())
    at = data.index(b"index_pos=") + len(b"index_pos=")
    data[at : at + 8] = bytes(8)
    cut = int(len(data) * keep_fraction)
    bag.write_bytes(bytes(data[:cut]))
    return cut


def _assert_prefix(truncated, whole):
    """Each stream of ``truncated`` is a non-empty beginning of ``whole``'s, pose for pose to 1e-9."""
    (frames, scans, odometry), (clean_frames, clean_scans, clean_odometry) = truncated, whole
    assert 0 < len(frames) < len(clean_frames) and 0 < len(scans) < len(clean_scans) and 0 < len(odometry) < len(clean_odometry)
    assert all(f.t_s == g.t_s and np.array_equal(f.image, g.image) for f, g in zip(frames, clean_frames))
    assert all(s.t_s == g.t_s and np.array_equal(s.ranges_m, g.ranges_m, equal_nan=True) for s, g in zip(scans, clean_scans))
    poses, clean_poses = _odometry_poses(odometry), _odometry_poses(clean_odometry)
    assert list(poses) == list(clean_poses)[: len(poses)]
    for t, T in poses.items():
        np.testing.assert_allclose(T, clean_poses[t], atol=1e-9)


def test_a_ros1_bag_without_its_index_is_read_up_to_the_damage(tmp_path, caplog, clean):
    bag = _bag(tmp_path / "killed.bag", "ros1", chunk_bytes=8000)
    size = bag.stat().st_size
    cut = _unindex_and_cut(bag, 0.6)
    caplog.set_level(logging.WARNING)
    _assert_prefix(_streams(_open(bag)), clean["ros1"][1])
    told = [m for m in _warnings(caplog) if "rosbag reindex" in m]
    assert len(told) == 1 and "read message by message, whole up to byte " in told[0] and f" of {cut:,}" in told[0] and cut < size


def test_an_mcap_file_cut_short_is_read_up_to_the_damage(tmp_path, caplog, clean):
    folder = _bag(tmp_path / "cut", "mcap", chunk_bytes=8000)
    (mcap,) = folder.glob("*.mcap")
    data = mcap.read_bytes()
    mcap.write_bytes(data[: int(len(data) * 0.6)])
    caplog.set_level(logging.WARNING)
    for path in (folder, mcap):  # the ROS 2 bag folder, or the .mcap file alone
        caplog.clear()
        _assert_prefix(_streams(_open(path)), clean["mcap"][1])
        told = [m for m in _warnings(caplog) if "mcap recover" in m]
        assert len(told) == 1 and "an MCAP file without its summary" in told[0] and "whole up to byte " in told[0]


def test_a_bag_cut_before_its_first_message_is_refused(tmp_path):
    bag = _bag(tmp_path / "empty.bag", "ros1")
    _unindex_and_cut(bag, 0.001)
    with pytest.raises(
        DatasetError, match=r"empty\.bag: cannot open the bag \(AnyReaderError: Bag is not indexed, reindex before reading\.\)"
    ):
        _open(bag)


# ------------------------------------------------------------------------------------------------
# encodings


def _image_msg(encoding: str, pixels: np.ndarray, bigendian: bool = False):
    h, w = pixels.shape[:2]
    data = pixels.astype(pixels.dtype.newbyteorder(">" if bigendian else "<")).tobytes()
    return SimpleNamespace(
        encoding=encoding, height=h, width=w, step=len(data) // h, is_bigendian=int(bigendian), data=np.frombuffer(data, np.uint8)
    )


@pytest.mark.parametrize("bigendian", [False, True])
def test_mono16_keeps_the_top_8_bits_of_the_streams_depth(bigendian):
    rng = np.random.default_rng(5)
    twelve_bit = rng.integers(0, 4096, (24, 32)).astype(np.uint16)
    twelve_bit[0, 0] = 4095
    image = image_from_message(_image_msg("mono16", twelve_bit, bigendian), "sensor_msgs/msg/Image", "test")
    assert image.dtype == np.uint8 and np.array_equal(image, (twelve_bit >> 4).astype(np.uint8))  # 12 bits: the top 8
    # a frame of the same stream, darker, keeps the stream's scale (depth_bits from its first frame)
    dark = (twelve_bit // 4).astype(np.uint16)
    image = image_from_message(_image_msg("16UC1", dark, bigendian), "sensor_msgs/msg/Image", "test", depth_bits=12)
    assert np.array_equal(image, (dark >> 4).astype(np.uint8))


@pytest.mark.parametrize("pattern", ["rggb", "bggr", "gbrg", "grbg"])
def test_bayer_becomes_the_scenes_grey(pattern):
    """A flat colour scene (B, G, R) = (50, 100, 200) seen through each Bayer mosaic: grey 124 (BT.601), to 1 DN."""
    bgr = {"b": 50, "g": 100, "r": 200}
    mosaic = np.zeros((24, 32), dtype=np.uint8)
    for k, colour in enumerate(pattern):
        mosaic[k // 2 :: 2, k % 2 :: 2] = bgr[colour]
    grey = image_from_message(_image_msg(f"bayer_{pattern}8", mosaic), "sensor_msgs/msg/Image", "test")
    expected = 0.114 * 50 + 0.587 * 100 + 0.299 * 200
    assert grey.shape == (24, 32) and np.all(np.abs(grey[2:-2, 2:-2].astype(float) - expected) <= 1.0)


@pytest.mark.parametrize(("encoding", "order"), [("yuv422", "uyvy"), ("yuv422_yuy2", "yuyv")])
def test_yuv422_becomes_its_luma(encoding, order):
    rng = np.random.default_rng(6)
    luma = rng.integers(16, 236, (24, 32), dtype=np.uint8)
    chroma = rng.integers(16, 240, (24, 32), dtype=np.uint8)
    packed = np.empty((24, 64), dtype=np.uint8)
    y_at = 1 if order == "uyvy" else 0
    packed[:, y_at::2], packed[:, 1 - y_at :: 2] = luma, chroma
    grey = image_from_message(_image_msg(encoding, packed.reshape(24, 32, 2)), "sensor_msgs/msg/Image", "test")
    assert np.array_equal(grey, luma)


def test_depth_images_are_refused_naming_the_encoding():
    depth = _image_msg("32FC1", np.zeros((24, 32), dtype=np.float32))
    with pytest.raises(DatasetError, match=r"^bag topic /depth message 3: image encoding '32FC1' cannot be used \(a depth or float image"):
        image_from_message(depth, "sensor_msgs/msg/Image", "bag topic /depth message 3")
    compressed = SimpleNamespace(format="16UC1; compressedDepth png", data=np.zeros(8, np.uint8))
    with pytest.raises(DatasetError, match=r"compressed depth image \(16UC1; compressedDepth png\) cannot be used"):
        image_from_message(compressed, "sensor_msgs/msg/CompressedImage", "bag topic /depth")


# ------------------------------------------------------------------------------------------------
# the same standard for KITTI raw drives' time stamps


def test_a_kitti_raw_stamp_not_after_the_one_before_costs_its_one_scan(tmp_path, caplog):
    from test_kitti import make_raw_drive

    from dem_graph.datasets.kitti import KittiRawSequence

    drive, _, _ = make_raw_drive(tmp_path, n=11)
    clean = KittiRawSequence(drive)
    stamps = drive / "velodyne_points" / "timestamps.txt"
    lines = stamps.read_text().splitlines()
    lines[6] = lines[5]  # the recorder wrote scan 5's stamp twice
    stamps.write_text("\n".join(lines) + "\n")
    caplog.set_level(logging.WARNING)
    seq = KittiRawSequence(drive)
    assert seq.skipped_messages() == {"laser_stamp_not_after": 1}
    t_clean, _ = clean.laser_scans()
    t, _ = seq.laser_scans()
    np.testing.assert_array_equal(t, np.delete(t_clean, 6))  # scan 6 lost, the others to the nanosecond
    told = [m for m in _warnings(caplog) if m.endswith(": skipped")]
    assert len(told) == 1 and "velodyne_points/timestamps.txt: 1 of 11 lines have a stamp not after the previous one's" in told[0]
    assert f"(first: line 7, {lines[5].strip()}, line 6 kept before it: {lines[5].strip()})" in told[0]
    # a third of the lines out of order: refused in one line
    for k in (2, 4, 6, 8):
        lines[k] = lines[k - 1]
    stamps.write_text("\n".join(lines) + "\n")
    with pytest.raises(
        DatasetError,
        match=r"velodyne_points/timestamps.txt: 4 of 11 lines cannot be used \(4 stamp not after the previous; first: line 3, ",
    ):
        KittiRawSequence(drive)


def test_a_compressed_frame_that_does_not_decode_costs_that_frame(tmp_path, caplog, clean):
    """Frame 4's PNG cut short: skipped while the log is replayed (its size is known only decoded), the others exact."""

    def messages(store, ros1):
        T = store.types
        out = []
        for topic, msgtype, t_ns, msg in _messages(store, ros1, _long_truth()):
            if topic == "/cam/image":
                bgr = np.frombuffer(bytes(msg.data), np.uint8).reshape(24, 32, 3)[:, :, ::-1]
                png = cv2.imencode(".png", bgr)[1].ravel()
                k = sum(m[0] == "/cam/image" for m in out)
                msg = T["sensor_msgs/msg/CompressedImage"](
                    header=msg.header, format="bgr8; png compressed bgr8", data=png[:40] if k == 4 else png
                )
                topic, msgtype = "/cam/image", "sensor_msgs/msg/CompressedImage"
            out.append((topic, msgtype, t_ns, msg))
        return out

    bag = write_bag(tmp_path / "compressed.bag", True, messages=messages)
    caplog.set_level(logging.WARNING)
    seq = _open(bag)
    frames, _, _ = _streams(seq)
    clean_frames = [f for k, f in enumerate(clean["ros1"][1][0]) if k != 4]
    assert [f.t_s for f in frames] == [f.t_s for f in clean_frames]
    assert all(np.array_equal(f.image, g.image) for f, g in zip(frames, clean_frames))
    assert seq.skipped_messages() == {"camera_wrong_shape": 1}
    list(seq.events())  # a second replay counts it once
    assert seq.skipped_messages() == {"camera_wrong_shape": 1}
    told = [m for m in _warnings(caplog) if "cannot be decoded" in m]
    assert (
        len(told) == 1 and "topic /cam/image message 4: compressed image (bgr8; png compressed bgr8) cannot be decoded: skipped" in told[0]
    )


def test_a_mono16_bag_reads_as_grey_on_one_scale(tmp_path):
    """A 12-bit camera in mono16: every frame its top 8 bits (the depth told from frame 0), exactly."""
    rng = np.random.default_rng(8)
    frames12 = [rng.integers(0, 4096, (24, 32)).astype(np.uint16) for _ in range(N_FRAMES)]
    frames12[0][0, 0] = 4095

    def messages(store, ros1):
        out = []
        for topic, msgtype, t_ns, msg in _messages(store, ros1, _long_truth()):
            if topic == "/cam/image":
                k = sum(m[0] == "/cam/image" for m in out)
                msg.encoding, msg.step, msg.data = "mono16", 64, np.frombuffer(frames12[k].astype("<u2").tobytes(), np.uint8)
            out.append((topic, msgtype, t_ns, msg))
        return out

    frames, _, _ = _streams(_open(write_bag(tmp_path / "mono16.bag", True, messages=messages)))
    assert len(frames) == N_FRAMES
    assert all(f.image.dtype == np.uint8 and np.array_equal(f.image, (g >> 4).astype(np.uint8)) for f, g in zip(frames, frames12))
