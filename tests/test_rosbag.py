"""The ROS bag reader: small ROS 1 and ROS 2 bags written with rosbags itself, read back exactly."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from dem_graph.datasets.events import CameraFrame, LaserScan, Odometry
from dem_graph.datasets.rosbag import RosbagSequence, TransformTree
from dem_graph.errors import DatasetError
from dem_graph.geometry.rig import PlanarBeams, default_rig
from dem_graph.geometry.se3 import make_pose, quat_xyzw_from_matrix, rotation_from_rpy

rosbags = pytest.importorskip("rosbags")
from rosbags.typesys import Stores, get_typestore  # noqa: E402

BEAMS = PlanarBeams(angle_min_rad=-0.5, angle_increment_rad=0.01, count=101)
N_FRAMES, N_SCANS, N_ODOM = 4, 5, 6


def _rig():
    """The default rig with the bags' laser beams and a camera of the bags' 32x24 images."""
    rig = default_rig()
    camera = rig.camera.model_copy(update={"width_px": 32, "height_px": 24, "fx_px": 22.4, "fy_px": 22.4, "cx_px": 15.5, "cy_px": 11.5})
    return rig.model_copy(update={"camera": camera, "laser": rig.laser.model_copy(update={"beams": BEAMS})})


def _truth():
    """Images, scans (times, ranges with invalid values), odometry poses; times chosen exact in float64."""
    rng = np.random.default_rng(0)
    images = [rng.integers(0, 256, (24, 32, 3), dtype=np.uint8) for _ in range(N_FRAMES)]
    frame_t = [(100, 250_000_000 * i) for i in range(N_FRAMES)]
    scan_t = [(100, 200_000_000 * i + 5) for i in range(N_SCANS)]
    ranges = rng.uniform(0.5, 20.0, (N_SCANS, BEAMS.count)).astype(np.float32)
    ranges[:, 0] = np.inf
    ranges[:, 1] = np.nan
    ranges[:, 2] = 0.05  # below range_min 0.1
    ranges[:, 3] = 45.0  # above range_max 40
    odom_t = [(100, 150_000_000 * i) for i in range(N_ODOM)]
    poses = [make_pose(rotation_from_rpy(0.0, 0.0, 0.05 * i), [0.3 * i, 0.01 * i * i, 0.0]) for i in range(N_ODOM)]
    return images, frame_t, scan_t, ranges, odom_t, poses


def _with_tf(store):
    from rosbags.typesys import get_types_from_msg

    if "tf2_msgs/msg/TFMessage" not in store.types:
        store.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms", "tf2_msgs/msg/TFMessage"))
    return store


def _messages(store, ros1: bool, truth=None):
    """The bag's messages ``(topic, msgtype, bag time ns, message)`` in bag order; ``truth``: as :func:`_truth` gives (its default)."""
    T = _with_tf(store).types
    Time = T["builtin_interfaces/msg/Time"]
    extra = {"seq": 0} if ros1 else {}

    def header(sec, ns, frame):
        return T["std_msgs/msg/Header"](**extra, stamp=Time(sec=sec, nanosec=ns), frame_id=frame)

    images, frame_t, scan_t, ranges, odom_t, poses = _truth() if truth is None else truth
    height, width = images[0].shape[:2]
    out = []
    for (sec, ns), img in zip(frame_t, images):
        rgb = np.ascontiguousarray(img[:, :, ::-1])
        msg = T["sensor_msgs/msg/Image"](
            header=header(sec, ns, "cam"), height=height, width=width, encoding="rgb8", is_bigendian=0, step=3 * width, data=rgb.ravel()
        )
        out.append(("/cam/image", "sensor_msgs/msg/Image", sec * 10**9 + ns, msg))
    for (sec, ns), r in zip(scan_t, ranges):
        msg = T["sensor_msgs/msg/LaserScan"](
            header=header(sec, ns, "laser"), angle_min=BEAMS.angle_min_rad, angle_max=BEAMS.angle_min_rad + (len(r) - 1) * BEAMS.angle_increment_rad,
            angle_increment=BEAMS.angle_increment_rad, time_increment=0.0, scan_time=0.1, range_min=0.1, range_max=40.0,
            ranges=r, intensities=np.zeros(0, dtype=np.float32),
        )
        out.append(("/scan", "sensor_msgs/msg/LaserScan", sec * 10**9 + ns, msg))
    G = "geometry_msgs/msg/"
    for (sec, ns), P in zip(odom_t, poses):
        q = quat_xyzw_from_matrix(P[:3, :3])
        pose = T[G + "Pose"](position=T[G + "Point"](x=P[0, 3], y=P[1, 3], z=P[2, 3]), orientation=T[G + "Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]))
        twist = T[G + "Twist"](linear=T[G + "Vector3"](x=0.0, y=0.0, z=0.0), angular=T[G + "Vector3"](x=0.0, y=0.0, z=0.0))
        msg = T["nav_msgs/msg/Odometry"](
            header=header(sec, ns, "odom"), child_frame_id="base_link",
            pose=T[G + "PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
            twist=T[G + "TwistWithCovariance"](twist=twist, covariance=np.zeros(36)),
        )
        out.append(("/odom", "nav_msgs/msg/Odometry", sec * 10**9 + ns, msg))
    # a static transform base_link -> laser_link: 1 m up, pitched down 0.3 rad
    q = quat_xyzw_from_matrix(rotation_from_rpy(0.0, 0.3, 0.0))
    tf = T[G + "TransformStamped"](
        header=header(100, 0, "base_link"), child_frame_id="laser_link",
        transform=T[G + "Transform"](translation=T[G + "Vector3"](x=0.5, y=0.0, z=1.0), rotation=T[G + "Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3])),
    )
    out.append(("/tf_static", "tf2_msgs/msg/TFMessage", 100 * 10**9, T["tf2_msgs/msg/TFMessage"](transforms=[tf])))
    return sorted(out, key=lambda m: m[2])


def write_bag(path, ros1: bool, skip_topic: str | None = None, messages=None, mcap: bool = False, chunk_bytes: int | None = None):
    """Write a ROS 1 bag (``ros1``) or a ROS 2 bag (SQLite, or MCAP when ``mcap``) at ``path``.
    ``messages``: ``(store, ros1) -> [(topic, msgtype, bag time ns, message)]`` (default :func:`_messages`);
    ``chunk_bytes``: close a chunk once it holds this many bytes (ROS 1 and MCAP; default the writers' 1 MiB)."""
    if ros1:
        from rosbags.rosbag1 import Writer

        store = get_typestore(Stores.ROS1_NOETIC)
        writer = Writer(path)
        if chunk_bytes is not None:
            writer.chunk_threshold = chunk_bytes
        serialize = store.serialize_ros1
    else:
        from rosbags.rosbag2 import StoragePlugin, Writer

        store = get_typestore(Stores.ROS2_HUMBLE)
        writer = Writer(path, version=9, storage_plugin=StoragePlugin.MCAP if mcap else StoragePlugin.SQLITE3)
        serialize = store.serialize_cdr
    with writer:
        connections = {}
        for topic, msgtype, t_ns, msg in (messages or _messages)(store, ros1):
            if topic == skip_topic:
                continue
            if (topic, msgtype) not in connections:  # a topic may carry two types (ROS 1's /tf: TFMessage and tf/tfMessage)
                connections[topic, msgtype] = writer.add_connection(topic, msgtype, typestore=store)
            writer.write(connections[topic, msgtype], t_ns, serialize(msg, msgtype))
            if mcap and chunk_bytes is not None and writer.storage.chunk.bio.tell() > chunk_bytes:
                writer.storage.close_chunk()
    return path


@pytest.mark.parametrize("ros1", [True, False], ids=["ros1", "ros2"])
def test_bag_reads_back_exactly(tmp_path, ros1):
    bag = write_bag(tmp_path / ("log.bag" if ros1 else "log"), ros1)
    seq = RosbagSequence(bag, _rig(), "/cam/image", "/scan", "/odom", body_frame="base_link", laser_frame="laser_link")
    images, frame_t, scan_t, ranges, odom_t, poses = _truth()
    events = list(seq.events())
    frames = [e for e in events if isinstance(e, CameraFrame)]
    scans = [e for e in events if isinstance(e, LaserScan)]
    odo = [e for e in events if isinstance(e, Odometry)]
    assert len(frames) == N_FRAMES and len(scans) == N_SCANS and len(odo) == N_ODOM - 1
    for f, img, (sec, ns) in zip(frames, images, frame_t):
        assert np.array_equal(f.image, img)  # rgb8 in the bag, BGR out, pixel-exact
        assert f.t_s == sec + ns * 1e-9
    expected = ranges.copy()
    expected[:, :4] = np.nan
    for s, r, (sec, ns) in zip(scans, expected, scan_t):
        assert np.array_equal(s.ranges_m, r, equal_nan=True)
        assert s.t_s == sec + ns * 1e-9
    for k, o in enumerate(odo):
        assert o.t_prev_s == odom_t[k][0] + odom_t[k][1] * 1e-9 and o.t_s == odom_t[k + 1][0] + odom_t[k + 1][1] * 1e-9
        np.testing.assert_allclose(o.T_prev_curr, np.linalg.inv(poses[k]) @ poses[k + 1], atol=1e-9)
        assert o.covariance.shape == (6, 6)
    times = [e.t_s for e in events]
    assert times == sorted(times) and seq.t_start_s == min(times[0], odo[0].t_prev_s)
    # T_body_laser from tf_static, not from the rig
    np.testing.assert_allclose(seq.rig.T_body_laser, make_pose(rotation_from_rpy(0.0, 0.3, 0.0), [0.5, 0.0, 1.0]), atol=1e-12)
    np.testing.assert_array_equal(seq.rig.T_body_cam, _rig().T_body_cam)
    t, r = seq.laser_scans()
    assert np.array_equal(r, expected.astype(float), equal_nan=True)


def test_compressed_image_and_mono(tmp_path):
    from rosbags.rosbag2 import Writer

    store = get_typestore(Stores.ROS2_HUMBLE)
    T = store.types
    img = np.random.default_rng(1).integers(0, 256, (24, 32), dtype=np.uint8)
    ok, png = cv2.imencode(".png", img)
    assert ok
    header = T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=5, nanosec=0), frame_id="cam")
    msg = T["sensor_msgs/msg/CompressedImage"](header=header, format="png", data=png.ravel())
    scans = [m for m in _messages(store, False) if m[0] == "/scan"]
    with Writer(tmp_path / "c", version=9) as writer:
        c = writer.add_connection("/cam/compressed", "sensor_msgs/msg/CompressedImage", typestore=store)
        writer.write(c, 5 * 10**9, store.serialize_cdr(msg, "sensor_msgs/msg/CompressedImage"))
        s = writer.add_connection("/scan", "sensor_msgs/msg/LaserScan", typestore=store)
        for _, msgtype, t_ns, m in scans:
            writer.write(s, t_ns, store.serialize_cdr(m, msgtype))
    seq = RosbagSequence(tmp_path / "c", _rig(), "/cam/compressed", "/scan")
    frames = [e for e in seq.events() if isinstance(e, CameraFrame)]
    assert len(frames) == 1 and np.array_equal(frames[0].image, img) and frames[0].t_s == 5.0
    assert not seq.has_odometry


def test_missing_topic_is_named(tmp_path):
    bag = write_bag(tmp_path / "log.bag", True, skip_topic="/scan")
    with pytest.raises(DatasetError, match=r"no topic '/scan' in the bag") as info:
        RosbagSequence(bag, _rig(), "/cam/image", "/scan")
    assert "log.bag" in str(info.value) and "\n" not in str(info.value)


def test_scan_angles_must_match_the_rig(tmp_path):
    bag = write_bag(tmp_path / "log", False)
    rig = default_rig()  # 361 beams from -pi/2
    with pytest.raises(DatasetError, match=r"topic /scan: none of the 5 messages can be used \(5 of another shape; first: message 0, 101 beams from -0.500000 rad"):
        RosbagSequence(bag, rig, "/cam/image", "/scan")


def test_wrong_topic_type(tmp_path):
    bag = write_bag(tmp_path / "log", False)
    with pytest.raises(DatasetError, match=r"topic /scan: has type sensor_msgs/msg/LaserScan, expected sensor_msgs/msg/Image"):
        RosbagSequence(bag, _rig(), "/scan", "/scan")


def test_transform_tree_chains_both_ways():
    tree = TransformTree()
    A = make_pose(rotation_from_rpy(0.1, 0.2, 0.3), [1.0, 2.0, 3.0])
    B = make_pose(rotation_from_rpy(-0.2, 0.0, 0.5), [0.0, -1.0, 0.5])
    tree.add("base", "mid", A)
    tree.add("/mid", "laser", B)
    np.testing.assert_allclose(tree.lookup("base", "laser"), A @ B, atol=1e-12)
    np.testing.assert_allclose(tree.lookup("laser", "base"), np.linalg.inv(A @ B), atol=1e-12)
    assert tree.lookup("base", "nowhere") is None


def test_an_image_of_another_size_than_the_rig_is_refused_naming_the_message(tmp_path):
    bag = write_bag(tmp_path / "log.bag", True)
    with pytest.raises(DatasetError, match=r"topic /cam/image: none of the 4 messages can be used \(4 of another shape; first: message 0, image is 32x24 px but the rig's camera is 800x600 px\)$"):
        RosbagSequence(bag, default_rig().model_copy(update={"laser": _rig().laser}), "/cam/image", "/scan")
