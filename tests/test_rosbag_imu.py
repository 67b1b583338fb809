"""The ROS bag reader's IMU stream: sensor_msgs/Imu messages in small ROS 1 and ROS 2 bags (written with
rosbags itself, beside test_rosbag's images, scans, odometry and tf_static) read back exactly as
ImuSample events; T_body_imu from tf_static; bad messages and bad rigs."""

from __future__ import annotations

import logging

import numpy as np
import pytest
from click.testing import CliRunner

from dem_graph.cli import main
from dem_graph.datasets.base import CAMERA_STREAM, IMU_STREAM, LASER_STREAM, ODOMETRY_STREAM
from dem_graph.datasets.events import CameraFrame, ImuSample, LaserScan, Odometry
from dem_graph.datasets.open import DatasetOptions, open_dataset
from dem_graph.datasets.rosbag import RosbagSequence
from dem_graph.errors import DatasetError
from dem_graph.geometry.rig import save_rig
from dem_graph.geometry.se3 import make_pose, quat_xyzw_from_matrix, rotation_from_rpy

pytest.importorskip("rosbags")
from rosbags.typesys import Stores, get_typestore  # noqa: E402
from test_rosbag import N_FRAMES, N_ODOM, N_SCANS, _messages, _rig, _with_tf  # noqa: E402  (tests/ is on sys.path)

IMU = "/imu/data"
RATE_HZ = 200
N_IMU = 161  # 100.000 s to 100.800 s, every 5 ms: as long as the other streams, some stamps equal to theirs
T_BODY_IMU = make_pose(rotation_from_rpy(0.02, -0.1, np.pi / 2), [0.2, -0.05, 0.3])
ARGS = ["/cam/image", "/scan", "/odom"]


def _imu_truth():
    """Stamps (sec, nanosec), gyro (N,3) and accel (N,3) of the IMU messages."""
    rng = np.random.default_rng(7)
    stamps = [(100, (10**9 // RATE_HZ) * k) for k in range(N_IMU)]
    gyro = rng.normal(0.0, 0.2, (N_IMU, 3))
    accel = rng.normal(0.0, 0.5, (N_IMU, 3)) + [0.0, 0.0, 9.81]
    return stamps, gyro, accel


def _t(sec: int, ns: int) -> float:
    return sec + ns * 1e-9  # as stamp_s reads a stamp


def _imu_messages(store, ros1: bool, frame: str = "imu_link", nan_at: int | None = None):
    T = store.types
    extra = {"seq": 0} if ros1 else {}
    V, Q = T["geometry_msgs/msg/Vector3"], T["geometry_msgs/msg/Quaternion"]
    stamps, gyro, accel = _imu_truth()
    unknown = np.zeros(9)
    no_orientation = np.zeros(9)
    no_orientation[0] = -1.0  # ROS: "no orientation estimate"
    out = []
    for k, ((sec, ns), w, a) in enumerate(zip(stamps, gyro, accel)):
        if k == nan_at:
            w = [w[0], np.nan, w[2]]
        header = T["std_msgs/msg/Header"](**extra, stamp=T["builtin_interfaces/msg/Time"](sec=sec, nanosec=ns), frame_id=frame)
        msg = T["sensor_msgs/msg/Imu"](
            header=header, orientation=Q(x=0.0, y=0.0, z=0.0, w=1.0), orientation_covariance=no_orientation,
            angular_velocity=V(x=w[0], y=w[1], z=w[2]), angular_velocity_covariance=unknown,
            linear_acceleration=V(x=a[0], y=a[1], z=a[2]), linear_acceleration_covariance=unknown,
        )
        out.append((IMU, "sensor_msgs/msg/Imu", sec * 10**9 + ns, msg))
    return out


def _imu_tf(store, ros1: bool):
    """A second /tf_static message: base_link -> imu_link, T_BODY_IMU."""
    T = _with_tf(store).types
    G = "geometry_msgs/msg/"
    extra = {"seq": 0} if ros1 else {}
    q = quat_xyzw_from_matrix(T_BODY_IMU[:3, :3])
    p = T_BODY_IMU[:3, 3]
    header = T["std_msgs/msg/Header"](**extra, stamp=T["builtin_interfaces/msg/Time"](sec=100, nanosec=1), frame_id="base_link")
    tf = T[G + "TransformStamped"](
        header=header, child_frame_id="imu_link",
        transform=T[G + "Transform"](translation=T[G + "Vector3"](x=p[0], y=p[1], z=p[2]), rotation=T[G + "Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3])),
    )
    return [("/tf_static", "tf2_msgs/msg/TFMessage", 100 * 10**9 + 1, T["tf2_msgs/msg/TFMessage"](transforms=[tf]))]


def write_imu_bag(path, ros1: bool, imu_type: str = "sensor_msgs/msg/Imu", **imu_kwargs):
    """test_rosbag's bag (images, scans, odometry with all-zero covariances, tf_static) with an IMU topic
    and the transform base_link -> imu_link; ``imu_type`` another type: that topic holds scans instead."""
    if ros1:
        from rosbags.rosbag1 import Writer

        store = get_typestore(Stores.ROS1_NOETIC)
        writer, serialize = Writer(path), store.serialize_ros1
    else:
        from rosbags.rosbag2 import Writer

        store = get_typestore(Stores.ROS2_HUMBLE)
        writer, serialize = Writer(path, version=9), store.serialize_cdr
    messages = _messages(store, ros1) + _imu_tf(store, ros1)
    if imu_type == "sensor_msgs/msg/Imu":
        messages += _imu_messages(store, ros1, **imu_kwargs)
    else:
        messages += [(IMU, msgtype, t_ns, msg) for topic, msgtype, t_ns, msg in _messages(store, ros1) if topic == "/scan"]
    with writer:
        connections = {}
        for topic, msgtype, t_ns, msg in sorted(messages, key=lambda m: m[2]):
            if topic not in connections:
                connections[topic] = writer.add_connection(topic, msgtype, typestore=store)
            writer.write(connections[topic], t_ns, serialize(msg, msgtype))
    return path


@pytest.mark.parametrize("ros1", [True, False], ids=["ros1", "ros2"])
def test_imu_reads_back_exactly_merged_after_the_other_streams(tmp_path, ros1):
    bag = write_imu_bag(tmp_path / ("log.bag" if ros1 else "log"), ros1)
    seq = RosbagSequence(bag, _rig(), *ARGS, imu_topic=IMU)
    assert seq.has_imu and seq.has_odometry
    events = list(seq.events())
    assert seq.event_count() == len(events) == N_FRAMES + N_SCANS + (N_ODOM - 1) + N_IMU
    samples = [e for e in events if isinstance(e, ImuSample)]
    stamps, gyro, accel = _imu_truth()
    assert [s.index for s in samples] == list(range(N_IMU))
    assert [s.t_s for s in samples] == [_t(*st) for st in stamps]
    assert np.array_equal(np.array([s.gyro_rad_s for s in samples]), gyro)
    assert np.array_equal(np.array([s.accel_mps2 for s in samples]), accel)
    # time order; at equal times odometry, laser, camera, then IMU
    kind = {Odometry: ODOMETRY_STREAM, LaserScan: LASER_STREAM, CameraFrame: CAMERA_STREAM, ImuSample: IMU_STREAM}
    keys = [(e.t_s, kind[type(e)], e.index) for e in events]
    assert keys == sorted(keys)
    shared = {e.t_s for e in events if not isinstance(e, ImuSample)} & {s.t_s for s in samples}
    assert len(shared) >= 6  # frames every 250 ms and odometry every 150 ms fall on IMU stamps
    assert seq.t_start_s == _t(100, 0) and f"imu={N_IMU}" in repr(seq)
    # no body frame given: T_body_imu is the rig's
    np.testing.assert_array_equal(seq.rig.T_body_imu, _rig().T_body_imu)


@pytest.mark.parametrize("ros1", [True, False], ids=["ros1", "ros2"])
def test_T_body_imu_from_tf_static(tmp_path, ros1, caplog):
    bag = write_imu_bag(tmp_path / ("log.bag" if ros1 else "log"), ros1)
    seq = RosbagSequence(bag, _rig(), *ARGS, body_frame="base_link", laser_frame="laser_link", imu_topic=IMU)
    np.testing.assert_allclose(seq.rig.T_body_imu, T_BODY_IMU, atol=1e-12)
    np.testing.assert_allclose(seq.rig.T_body_laser, make_pose(rotation_from_rpy(0.0, 0.3, 0.0), [0.5, 0.0, 1.0]), atol=1e-12)
    assert seq.rig.imu.gyro_noise_density == _rig().imu.gyro_noise_density  # the noise figures stay the rig's
    # messages in a frame tf does not know: the rig's, with a warning
    other = write_imu_bag(tmp_path / "other", False, frame="/mystery_imu")
    with caplog.at_level(logging.WARNING, logger="dem_graph.datasets.rosbag"):
        seq = RosbagSequence(other, _rig(), *ARGS, body_frame="base_link", imu_topic=IMU)
    np.testing.assert_array_equal(seq.rig.T_body_imu, _rig().T_body_imu)
    assert any("does not link base_link to mystery_imu: T_body_imu from the rig" in r.getMessage() for r in caplog.records)


def test_a_non_finite_sample_is_skipped_with_one_warning(tmp_path, caplog):
    bag = write_imu_bag(tmp_path / "log", False, nan_at=37)
    with caplog.at_level(logging.WARNING):
        seq = RosbagSequence(bag, _rig(), *ARGS, imu_topic=IMU)
    warnings = [r.getMessage() for r in caplog.records if IMU in r.getMessage()]
    assert len(warnings) == 1
    assert "1 of 161 messages" in warnings[0] and "first: message 37" in warnings[0] and "skipped" in warnings[0]
    samples = [e for e in seq.events() if isinstance(e, ImuSample)]
    stamps, gyro, accel = _imu_truth()
    keep = np.arange(N_IMU) != 37
    assert len(samples) == N_IMU - 1 and [s.index for s in samples] == list(range(N_IMU - 1))
    assert [s.t_s for s in samples] == [_t(*st) for st, k in zip(stamps, keep) if k]
    assert np.array_equal(np.array([s.gyro_rad_s for s in samples]), gyro[keep])
    assert np.array_equal(np.array([s.accel_mps2 for s in samples]), accel[keep])


def test_a_rig_without_an_imu_section_takes_the_imu_noise_from_the_defaults(tmp_path):
    """Since the rig comes from the bag (tests/test_bag_rig.py), a rig file without an imu section no
    longer refuses an IMU topic: the noise figures are ImuSpec's defaults, T_body_imu from tf."""
    from dem_graph.geometry.rig import ImuSpec

    bag = write_imu_bag(tmp_path / "log.bag", True)
    rig = tmp_path / "rig.yaml"
    save_rig(_rig().model_copy(update={"imu": None}), rig)
    options = DatasetOptions(rig=rig, image_topic="/cam/image", scan_topic="/scan", imu_topic=IMU)
    seq = open_dataset(bag, None, options)
    assert seq.has_imu and seq.rig.imu.gyro_noise_density == ImuSpec().gyro_noise_density
    assert abs(seq.rig.imu.rate_hz - RATE_HZ) < 1e-3
    np.testing.assert_allclose(seq.rig.T_body_imu, T_BODY_IMU, rtol=0, atol=1e-12)
    # without the IMU topic the same rig opens the bag
    assert not open_dataset(bag, None, DatasetOptions(rig=rig, image_topic="/cam/image", scan_topic="/scan")).has_imu


def test_a_wrong_message_type_is_refused_from_the_command_line(tmp_path):
    bag = write_imu_bag(tmp_path / "log", False, imu_type="sensor_msgs/msg/LaserScan")
    with pytest.raises(DatasetError, match=r"topic /imu/data: has type sensor_msgs/msg/LaserScan, expected sensor_msgs/msg/Imu"):
        RosbagSequence(bag, _rig(), *ARGS, imu_topic=IMU)
    rig = tmp_path / "rig.yaml"
    save_rig(_rig(), rig)
    args = ["run", str(bag), "--rig", str(rig), "--image-topic", "/cam/image", "--scan-topic", "/scan", "--imu-topic", IMU]
    result = CliRunner().invoke(main, [*args, "--out", str(tmp_path / "run")])
    assert result.exit_code == 2
    assert "has type sensor_msgs/msg/LaserScan, expected sensor_msgs/msg/Imu" in result.output


def test_the_imu_topic_goes_from_the_command_line_into_a_dataset_folder(tmp_path):
    from dem_graph.datasets.folder import FolderSequence

    bag = write_imu_bag(tmp_path / "log", False)
    rig = tmp_path / "rig.yaml"
    save_rig(_rig(), rig)
    args = ["degrade", str(bag), "--rig", str(rig), "--image-topic", "/cam/image", "--scan-topic", "/scan", "--imu-topic", IMU]
    result = CliRunner().invoke(main, [*args, "--out", str(tmp_path / "copy")])
    assert result.exit_code == 0, result.output
    copy = FolderSequence(tmp_path / "copy")
    samples = [e for e in copy.events() if isinstance(e, ImuSample)]
    stamps, gyro, _ = _imu_truth()
    assert copy.has_imu and [s.t_s for s in samples] == [_t(*st) for st in stamps]
    assert np.array_equal(np.array([s.gyro_rad_s for s in samples]), gyro)
