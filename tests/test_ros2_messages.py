"""The ROS 2 node's parts that need no graph: names on DDS, the codec against rosbags, the GridMap's
and the OccupancyGrid's layouts against grid_map's and Nav2's, the reorder buffer, the live streams
against the bag reader, and the ROS 1 -> ROS 2 conversion of the player."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("rosbags")

from dem_graph.datasets.events import CameraFrame, ImuSample, LaserScan, Odometry  # noqa: E402
from dem_graph.dem.layers import Dem  # noqa: E402
from dem_graph.geometry.grid import GridGeometry  # noqa: E402
from dem_graph.geometry.se3 import make_pose, rotation_from_rpy  # noqa: E402
from dem_graph.ros2 import outputs  # noqa: E402
from dem_graph.ros2.messages import Codec, MessageError, dds_topic_name, dds_type_name, ros_topic_name, ros_type_name, typestore  # noqa: E402
from dem_graph.ros2.reorder import ReorderBuffer  # noqa: E402

CODEC = Codec()


# --- names and bytes ------------------------------------------------------------------------


def test_dds_names_are_ros2s():
    assert dds_topic_name("/scan") == "rt/scan"
    assert dds_topic_name("/dem_graph/elevation_map") == "rt/dem_graph/elevation_map"
    assert ros_topic_name("rt/camera/image_raw") == "/camera/image_raw" and ros_topic_name("DCPSPublication") is None
    assert dds_type_name("sensor_msgs/msg/LaserScan") == "sensor_msgs::msg::dds_::LaserScan_"
    assert ros_type_name("grid_map_msgs::msg::dds_::GridMap_") == "grid_map_msgs/msg/GridMap"
    for bad in ("scan topic", "/a//b", "/a/"):
        with pytest.raises(MessageError, match="not a ROS 2 topic name"):
            dds_topic_name(bad)
    with pytest.raises(MessageError, match="not a ROS 2 message type"):
        dds_type_name("sensor_msgs/LaserScan")


def _scan(codec=CODEC):
    m = codec.message_class
    header = outputs.header(codec, 1_700_000_000.25, "laser")
    return m("sensor_msgs/msg/LaserScan")(
        header=header, angle_min=-1.0, angle_max=1.0, angle_increment=0.5, time_increment=0.0, scan_time=0.02, range_min=0.1, range_max=30.0,
        ranges=np.array([1.0, 2.0, np.nan, 4.0, 5.0], dtype=np.float32), intensities=np.zeros(0, dtype=np.float32),
    )


def test_the_codec_writes_rosbags_cdr_and_reads_it_back():
    store = typestore()
    msg = _scan()
    data = CODEC.encode(msg, "sensor_msgs/msg/LaserScan")
    assert data == bytes(store.serialize_cdr(msg, "sensor_msgs/msg/LaserScan"))
    assert data[:4] == b"\x00\x01\x00\x00"  # plain CDR, little endian: XCDR1
    back = CODEC.decode(data, "sensor_msgs/msg/LaserScan")
    assert back.header.stamp.sec == 1_700_000_000 and back.header.stamp.nanosec == 250_000_000 and back.header.frame_id == "laser"
    np.testing.assert_array_equal(back.ranges, msg.ranges)
    # an XCDR2 writer's bytes (encapsulation 0x0007) are refused by name, as ROS 2's readers refuse them
    with pytest.raises(MessageError, match="XCDR2"):
        CODEC.decode(b"\x00\x07\x00\x00" + data[4:], "sensor_msgs/msg/LaserScan")
    with pytest.raises(MessageError, match="cannot be decoded from 12 bytes"):
        CODEC.decode(data[:12], "sensor_msgs/msg/LaserScan")


def test_grid_map_msgs_are_registered_as_in_ros2():
    _consts, fields = typestore().fielddefs["grid_map_msgs/msg/GridMap"]
    assert [name for name, _ in fields] == ["header", "info", "layers", "basic_layers", "data", "outer_start_index", "inner_start_index"]
    _consts, info = typestore().fielddefs["grid_map_msgs/msg/GridMapInfo"]
    assert [name for name, _ in info] == ["resolution", "length_x", "length_y", "pose"]
    assert CODEC.type_hash("grid_map_msgs/msg/GridMap").startswith("RIHS01_") and len(CODEC.type_hash("grid_map_msgs/msg/GridMap")) == 7 + 64


# --- the GridMap's layout -------------------------------------------------------------------


def _dem(n_rows=3, n_cols=4, r=0.5, x_min=1.0, y_max=1.5) -> Dem:
    """A Dem whose every layer holds each cell's centre as 100 x + y (so a cell is known by its value)."""
    g = GridGeometry(x_min, y_max, r, n_rows, n_cols)
    x, y = g.cell_centers_xy()
    value = (100.0 * x + y).astype(np.float32)
    layers = {name: value + k for k, name in enumerate(outputs.GRID_MAP_LAYERS)}
    return Dem(g, layers, frame="local", meta={})


def test_grid_map_layout_is_grid_maps():
    dem = _dem()
    g = dem.geometry
    msg = outputs.grid_map_message(CODEC, dem, 12.5, "dem_graph_heading")
    assert msg.header.frame_id == "dem_graph_heading" and msg.layers == list(outputs.GRID_MAP_LAYERS) and msg.basic_layers == ["elevation"]
    assert (msg.info.resolution, msg.info.length_x, msg.info.length_y) == (0.5, 2.0, 1.5)
    assert (msg.info.pose.position.x, msg.info.pose.position.y) == (2.0, 0.75)  # the centre: x 1..3, y 0..1.5
    assert (msg.outer_start_index, msg.inner_start_index) == (0, 0)
    elevation = msg.data[0]
    dims = elevation.layout.dim
    assert [d.label for d in dims] == ["column_index", "row_index"]  # column-major
    assert (dims[0].size, dims[0].stride, dims[1].size, dims[1].stride) == (g.n_rows, g.n_rows * g.n_cols, g.n_cols, g.n_cols)
    # grid_map's cell (i, j): i against x from the largest, j against y from the largest; data[i + j * n_i]
    n_i = g.n_cols
    for i in range(g.n_cols):
        for j in range(g.n_rows):
            x = g.x_max_m - (i + 0.5) * g.resolution_m
            y = g.y_max_m - (j + 0.5) * g.resolution_m
            assert elevation.data[i + j * n_i] == np.float32(100.0 * x + y)
    back = outputs.dem_from_grid_map(CODEC.decode(CODEC.encode(msg, "grid_map_msgs/msg/GridMap"), "grid_map_msgs/msg/GridMap"))
    assert back.geometry == g and back.meta["t_s"] == 12.5
    for name in outputs.GRID_MAP_LAYERS:
        np.testing.assert_array_equal(back.layers[name], dem.layers[name])


def test_a_grid_map_read_back_unrolls_its_circular_buffer_and_takes_row_major_data():
    dem = _dem(n_rows=4, n_cols=5)
    msg = outputs.grid_map_message(CODEC, dem, 0.0, "map", ("elevation",))
    M = np.asarray(dem.layers["elevation"])[:, ::-1].T  # grid_map's matrix (i along -x, j along -y)
    start = (2, 3)
    buffer = np.roll(M, start, axis=(0, 1))  # what a map moved by (2, 3) cells holds in its buffer
    msg.data[0].data = np.ascontiguousarray(buffer.T).ravel()  # column-major
    msg.outer_start_index, msg.inner_start_index = start
    np.testing.assert_array_equal(outputs.dem_from_grid_map(msg).layers["elevation"], dem.layers["elevation"])
    row_major = outputs.grid_map_message(CODEC, dem, 0.0, "map", ("elevation",))
    layout = row_major.data[0].layout
    layout.dim[0].label, layout.dim[1].label = "row_index", "column_index"
    row_major.data[0].data = np.ascontiguousarray(M).ravel()
    np.testing.assert_array_equal(outputs.dem_from_grid_map(row_major).layers["elevation"], dem.layers["elevation"])


def test_the_cost_map_is_an_occupancy_grid_from_its_corner_rows_along_y():
    g = GridGeometry(0.0, 1.0, 0.5, 2, 3)  # x 0..1.5, y 0..1
    nan = np.nan
    layers = {
        "elevation": np.array([[0.0, 0.0, nan], [0.0, 0.0, 0.0]], dtype=np.float32),
        "slope_deg": np.array([[10.0, 30.0, nan], [0.0, nan, 5.0]], dtype=np.float32),
        "step_height_m": np.array([[0.0, 0.0, nan], [0.075, nan, 0.0]], dtype=np.float32),
        "roughness_m": np.array([[0.0, 0.0, nan], [0.0, nan, 0.04]], dtype=np.float32),
    }
    dem = Dem(g, layers, frame="local", meta={})
    limits = outputs.CostLimits(max_slope_deg=20.0, max_step_height_m=0.15, max_roughness_m=0.05)
    # row 0 (y 0.5..1): slope 10/20 -> 50, 30/20 -> lethal, no height -> unknown; row 1: step 0.075/0.15 -> 50, no traversability -> unknown, roughness 0.04/0.05 -> 80
    np.testing.assert_array_equal(outputs.cost_of(dem, limits), [[50, 100, -1], [50, -1, 80]])
    T_map_heading = make_pose(rotation_from_rpy(0.0, 0.0, np.pi / 2), [10.0, 20.0, 0.3])
    msg = outputs.occupancy_grid_message(CODEC, dem, 3.0, "map", T_map_heading, limits)
    assert (msg.info.width, msg.info.height, msg.info.resolution) == (3, 2, 0.5)
    np.testing.assert_array_equal(msg.data, [50, -1, 80, 50, 100, -1])  # first the row of smallest y
    origin = outputs.pose_of(msg.info.origin)
    np.testing.assert_allclose(origin, T_map_heading @ make_pose(np.eye(3), [0.0, 0.0, 0.0]), atol=1e-12)  # the corner (0, 0) in the heading frame


def test_the_pose_covariance_goes_out_in_rosses_order_and_axes():
    P = np.diag([1.0, 2.0, 3.0, 4.0, 5.0, 6.0])  # [rotation x y z, translation x y z], the body's axes
    out = outputs.ros_pose_covariance(np.eye(4), P).reshape(6, 6)
    np.testing.assert_array_equal(np.diag(out), [4.0, 5.0, 6.0, 1.0, 2.0, 3.0])
    yawed = make_pose(rotation_from_rpy(0.0, 0.0, np.pi / 2), [1.0, 2.0, 0.0])  # the body's x is the map's y
    out = outputs.ros_pose_covariance(yawed, P).reshape(6, 6)
    np.testing.assert_allclose(np.diag(out), [5.0, 4.0, 6.0, 2.0, 1.0, 3.0], atol=1e-12)


# --- the reorder buffer ---------------------------------------------------------------------


def test_events_go_in_time_order_once_every_stream_has_caught_up():
    buf = ReorderBuffer(window_s=0.1)
    assert buf.push("camera", 1.00, "frame 1.00", arrived_s=0.0) == []
    assert buf.pop_ready(0.0) == ["frame 1.00"]  # no other stream heard yet: nothing to wait for
    buf.push("laser", 0.99, "scan 0.99", arrived_s=0.001)  # came after the frame it precedes: late, given at once
    assert buf.late["laser"] == 1
    buf.push("camera", 1.04, "frame 1.04", arrived_s=0.01)
    assert buf.pop_ready(0.01) == []  # the laser may still send a scan before 1.04
    assert buf.newest("camera") == 1.04 and buf.newest("laser") == 0.99 and buf.newest("odometry") is None  # (held or given)
    buf.push("laser", 1.03, "scan 1.03", arrived_s=0.02)
    assert buf.pop_ready(0.02) == ["scan 1.03"]
    buf.push("odometry", 1.04, "odom 1.04", arrived_s=0.025)
    buf.push("laser", 1.04, "scan 1.04", arrived_s=0.03)
    assert buf.pop_ready(0.03) == ["odom 1.04", "scan 1.04", "frame 1.04"]  # equal times: odometry, laser, camera
    buf.push("camera", 1.08, "frame 1.08", arrived_s=0.05)
    assert buf.pop_ready(0.10) == [] and buf.next_deadline_s() == pytest.approx(0.15)
    assert buf.pop_ready(0.151) == ["frame 1.08"] and buf.waited_out["camera"] == 1  # the window ran out
    buf.push("camera", 1.12, "frame 1.12", arrived_s=2.0)
    assert buf.pop_ready(2.0) == ["frame 1.12"]  # laser and odometry silent for over a second: not waited for
    buf.push("laser", 1.20, "scan 1.20", arrived_s=2.1)
    buf.push("camera", 1.16, "frame 1.16", arrived_s=2.1)
    assert buf.pop_ready(2.1) == ["frame 1.16"]  # the camera may still send a frame before 1.20
    buf.push("camera", 1.20, "frame 1.20", arrived_s=2.14)
    assert buf.pop_ready(2.14) == ["scan 1.20", "frame 1.20"] and len(buf) == 0


def test_a_stream_whose_next_message_is_due_after_an_event_is_not_waited_for_and_the_laser_not_against_odometry():
    buf = ReorderBuffer(window_s=0.1, periods_s={"laser": 0.02, "odometry": 0.02, "camera": 0.04})
    buf.push("camera", 1.000, "frame 1.000", arrived_s=-0.03)
    assert buf.pop_ready(-0.03) == ["frame 1.000"]
    buf.push("laser", 1.033, "scan 1.033", arrived_s=0.0)
    buf.push("odometry", 1.025, "odom 1.025", arrived_s=0.0)
    assert buf.pop_ready(0.0) == []  # each waits for the camera
    buf.push("camera", 1.040, "frame 1.040", arrived_s=0.007)
    # the laser's next scan is due at 1.053: the frame need not wait for it; the odometry's at 1.045, within half a period of the frame: it must
    assert buf.pop_ready(0.007) == ["odom 1.025", "scan 1.033"]
    buf.push("odometry", 1.045, "odom 1.045", arrived_s=0.012)
    # the frame goes, and the odometry after it without waiting for the scan due at 1.053 (laser and odometry are independent)
    assert buf.pop_ready(0.012) == ["frame 1.040", "odom 1.045"]
    assert sum(buf.waited_out.values()) == 0 and sum(buf.late.values()) == 0


# --- live streams against the bag reader ----------------------------------------------------


@pytest.fixture(scope="module")
def robot_bag(tmp_path_factory):
    from robot_bags import BagEdits, write_robot_bag  # tests/ is on sys.path

    from dem_graph.sim.pipeline import simulate
    from dem_graph.sim.scenarios import scenario

    root = tmp_path_factory.mktemp("ros2_streams")
    folder = root / "ds"
    simulate(scenario("smoke", seed=2, length_m=1.0), folder, overwrite=True, preview=False)
    return write_robot_bag(root / "bag", folder, "mcap", BagEdits(imu=True))


def test_live_streams_give_the_bag_readers_events_message_by_message(robot_bag):
    from robot_bags import IMAGE, IMU, ODOM, SCAN

    from dem_graph.datasets.bag_rig import BagTopics, fixed_transforms, rig_of_bag
    from dem_graph.datasets.open import DatasetOptions, open_dataset
    from dem_graph.datasets.ros_stream import LiveStreams, MessageLog
    from dem_graph.datasets.rosbag import open_bag

    seq = open_dataset(robot_bag, "rosbag", DatasetOptions(image_topic=IMAGE, scan_topic=SCAN, odometry_topic=ODOM, imu_topic=IMU))
    expected = list(seq.events())
    log = MessageLog()
    arrivals = []
    with open_bag(robot_bag) as reader:
        for c, _t, raw in reader.messages():
            msg = reader.deserialize(raw, c.msgtype)
            stamp = msg.header.stamp if hasattr(msg, "header") else None
            log.add(c.topic, c.msgtype, stamp.sec * 10**9 + stamp.nanosec if stamp is not None else _t, msg)
            arrivals.append((c.topic, c.msgtype, msg))
    topics = BagTopics(IMAGE, SCAN, ODOM, IMU)
    rig, derived = rig_of_bag(log, "live", topics)
    assert rig.model_dump() == seq.rig.model_dump()  # the rig of the messages is the bag's
    tree, _ = fixed_transforms(log)
    streams = LiveStreams(rig, topics, tree, derived.body_frame)
    convert = {IMAGE: lambda m, t: streams.image(m, t), SCAN: lambda m, t: streams.scan(m), ODOM: lambda m, t: streams.odometry(m), IMU: lambda m, t: streams.imu(m)}
    got = [convert[topic](msg, msgtype) for topic, msgtype, msg in arrivals if topic in convert]
    got = [e for e in got if e is not None]
    rank = {Odometry: 0, LaserScan: 1, CameraFrame: 2, ImuSample: 3}
    got.sort(key=lambda e: (e.t_s, rank[type(e)]))
    assert len(got) == len(expected)
    for a, b in zip(got, expected):
        assert type(a) is type(b) and a.t_s == b.t_s and a.index == b.index
        if isinstance(a, CameraFrame):
            np.testing.assert_array_equal(a.image, b.image)
        elif isinstance(a, LaserScan):
            np.testing.assert_array_equal(a.ranges_m, b.ranges_m)
        elif isinstance(a, Odometry):
            np.testing.assert_array_equal(a.T_prev_curr, b.T_prev_curr)
            np.testing.assert_array_equal(a.covariance, b.covariance)
        else:
            np.testing.assert_array_equal(a.gyro_rad_s, b.gyro_rad_s)
    # a scan of another layout, a stamp not after the last, an odometry pose not finite: each skipped and counted
    last_scan = next(msg for topic, _, msg in reversed(arrivals) if topic == SCAN)
    short = type(last_scan)(**{**{f: getattr(last_scan, f) for f in last_scan.__dataclass_fields__}, "ranges": last_scan.ranges[:-3]})
    assert streams.scan(short) is None and streams.scan(last_scan) is None
    last_odom = next(msg for topic, _, msg in reversed(arrivals) if topic == ODOM)
    last_odom.pose.pose.position.x = np.nan
    assert streams.odometry(last_odom) is None
    assert streams.skipped_messages() == {"laser_stamp_not_after": 1, "laser_wrong_shape": 1, "odometry_nonfinite": 1}


def test_the_player_makes_ros1_messages_ros2s():
    from rosbags.typesys import Stores, get_typestore

    from dem_graph.ros2.player import ros2_message

    ros1 = get_typestore(Stores.ROS1_NOETIC)
    T = ros1.types
    header = T["std_msgs/msg/Header"](seq=7, stamp=T["builtin_interfaces/msg/Time"](sec=5, nanosec=6), frame_id="cam")
    roi = T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
    K = np.arange(9, dtype=float)
    info = T["sensor_msgs/msg/CameraInfo"](
        header=header, height=480, width=640, distortion_model="plumb_bob", D=np.array([0.1, 0.2, 0.0, 0.0, 0.3]), K=K, R=np.eye(3).ravel(), P=np.arange(12, dtype=float),
        binning_x=0, binning_y=0, roi=roi,
    )
    out = ros2_message(info, "sensor_msgs/msg/CameraInfo", CODEC)
    back = CODEC.decode(CODEC.encode(out, "sensor_msgs/msg/CameraInfo"), "sensor_msgs/msg/CameraInfo")
    assert (back.header.stamp.sec, back.header.stamp.nanosec, back.header.frame_id) == (5, 6, "cam") and not hasattr(back.header, "seq")
    np.testing.assert_array_equal(back.k, K)
    np.testing.assert_array_equal(back.d, [0.1, 0.2, 0.0, 0.0, 0.3])
    np.testing.assert_array_equal(back.p, np.arange(12.0))


def test_ros_domain_id_is_read_as_ros2_reads_it():
    from dem_graph.errors import ConfigError
    from dem_graph.ros2.dds import localhost_only, ros_domain_id

    assert ros_domain_id({}) == 0 and ros_domain_id({"ROS_DOMAIN_ID": ""}) == 0 and ros_domain_id({"ROS_DOMAIN_ID": " 42 "}) == 42
    with pytest.raises(ConfigError, match="ROS_DOMAIN_ID='robot' is not a number"):
        ros_domain_id({"ROS_DOMAIN_ID": "robot"})
    with pytest.raises(ConfigError, match="ROS_DOMAIN_ID=233 is out of range: 0-232"):
        ros_domain_id({"ROS_DOMAIN_ID": "233"})
    assert localhost_only({"ROS_LOCALHOST_ONLY": "1"}) and localhost_only({"ROS_AUTOMATIC_DISCOVERY_RANGE": "localhost"})
    assert not localhost_only({"ROS_LOCALHOST_ONLY": "0"}) and not localhost_only({})
