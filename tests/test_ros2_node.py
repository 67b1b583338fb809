"""The ROS 2 node end to end on loopback: the player publishes a ROS 2 bag written as a robot records
one (Image, CameraInfo, LaserScan, Odometry with all-zero covariances, Imu, tf_static, tf, and one
bad message in three streams), the node runs in its own process with only the topic names, and this
test's subscriber decodes what it publishes with rosbags. The truth is ``dem-graph run`` on the same
bag with the same deterministic estimator (PTPM): the GridMaps are its live maps, to the bit
(float32), the Odometry its trajectory, the rig the node wrote its rig."""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml

pytest.importorskip("rosbags")
pytest.importorskip("cyclonedds")

from robot_bags import IMAGE, IMU, ODOM, SCAN, BagEdits, write_robot_bag  # noqa: E402  (tests/ is on sys.path)
from ros2_graph import Collector, domain_id, loopback_env, play, start_node, wait_node  # noqa: E402

from dem_graph.io.live_maps import read_live_maps  # noqa: E402
from dem_graph.io.tum import read_tum  # noqa: E402
from dem_graph.ros2 import outputs  # noqa: E402
from dem_graph.ros2.qos import DEFAULT, LATCHED  # noqa: E402

pytestmark = pytest.mark.slow

GRID_MAP, ODOMETRY, COST, DIAGNOSTICS = "grid_map_msgs/msg/GridMap", "nav_msgs/msg/Odometry", "nav_msgs/msg/OccupancyGrid", "diagnostic_msgs/msg/DiagnosticArray"
TOPICS = ["--image-topic", IMAGE, "--scan-topic", SCAN, "--odometry-topic", ODOM, "--imu-topic", IMU]


@pytest.fixture(scope="module")
def bag(tmp_path_factory):
    from dem_graph.sim.pipeline import simulate
    from dem_graph.sim.scenarios import scenario

    root = tmp_path_factory.mktemp("ros2_node")
    simulate(scenario("smoke", seed=3, length_m=4.0), root / "ds", overwrite=True, preview=False)
    return write_robot_bag(root / "bag", root / "ds", "mcap", BagEdits(imu=True, blemishes=True))


@pytest.fixture(scope="module")
def bag_run(bag, tmp_path_factory):
    """``dem-graph run`` on the bag (PTPM): the truth."""
    from dem_graph.datasets.open import DatasetOptions
    from dem_graph.pipeline.config import RunOverrides
    from dem_graph.pipeline.run import run_dataset

    out = tmp_path_factory.mktemp("ros2_bag_run") / "run"
    run_dataset(bag, RunOverrides(estimator="ptpm"), out_dir=out, dataset_options=DatasetOptions(image_topic=IMAGE, scan_topic=SCAN, odometry_topic=ODOM, imu_topic=IMU))
    return out


@pytest.fixture(scope="module")
def node_run(bag, bag_run, tmp_path_factory):
    """The node (PTPM, each frame's whole work done in it: ``--as-fast-as-possible``) on the player's messages, stopped with SIGTERM."""
    root = tmp_path_factory.mktemp("ros2_node_run")
    domain = domain_id(0)
    env = loopback_env(root, domain)
    frames = json.loads((bag_run / "metrics.json").read_text())["frames"]
    collector = Collector(domain, env, [
        ("/dem_graph/elevation_map", GRID_MAP, DEFAULT.with_depth(400)), ("/dem_graph/odometry", ODOMETRY, DEFAULT.with_depth(400)),
        ("/dem_graph/cost_map", COST, LATCHED.with_depth(400)), ("/diagnostics", DIAGNOSTICS, DEFAULT.with_depth(100)),
    ])
    node = start_node(env, root / "run", *TOPICS, "--estimator", "ptpm", "--as-fast-as-possible", "--max-frame-lag-s", "0", log_path=root / "node.log")
    try:
        played = play(env, bag, "--wait-for-subscribers-s", "60")
        assert played.returncode == 0, played.stderr
        collector.wait_for("/dem_graph/elevation_map", frames, timeout_s=60)
        endpoints = _endpoints(collector.participant)  # as discovery announces them to any participant
        code = wait_node(node)
    finally:
        if node.poll() is None:
            node.kill()
        collector.close()
    return {"out": root / "run", "code": code, "log": (root / "node.log").read_text(), "received": collector.received, "frames": frames, "played": played, "endpoints": endpoints}


def _endpoints(participant):
    """The ROS topics' writers and readers on the graph as DDS discovery tells any participant of
    them (DCPSPublication, DCPSSubscription): (kind, DDS topic) -> (type name, QoS)."""
    from cyclonedds.builtin import BuiltinDataReader, BuiltinTopicDcpsPublication, BuiltinTopicDcpsSubscription

    out = {}
    for kind, topic in (("writer", BuiltinTopicDcpsPublication), ("reader", BuiltinTopicDcpsSubscription)):
        reader = BuiltinDataReader(participant.dp, topic)
        for sample in reader.read(N=1000):
            if sample.topic_name.startswith("rt/") and sample.participant_key != participant.dp.guid:
                out.setdefault((kind, sample.topic_name), []).append((sample.type_name, sample.qos))
    return out


def test_the_node_stops_on_sigterm_with_its_run_folder_written(node_run):
    assert node_run["code"] == 0, node_run["log"]
    out = node_run["out"]
    for name in ("dem.tif", "trajectory.tum", "metrics.json", "rig.yaml", "config.yaml", "live_maps.nc"):
        assert (out / name).is_file(), name
    assert not (out / "live_maps.part").exists()
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["frames"] == node_run["frames"]


def test_the_grid_maps_on_the_wire_are_the_bag_runs_live_maps(node_run, bag_run, bag):
    from dem_graph.datasets.rosbag import open_bag

    maps = {}
    for _data, msg, _ in node_run["received"]["/dem_graph/elevation_map"]:
        dem = outputs.dem_from_grid_map(msg)
        maps[(msg.header.stamp.sec, msg.header.stamp.nanosec)] = dem
    assert len(maps) == node_run["frames"]  # one per frame, none lost
    # each GridMap carries its image's own stamp, to the nanosecond
    with open_bag(bag) as reader:
        image_stamps = {(m.header.stamp.sec, m.header.stamp.nanosec) for m in (reader.deserialize(raw, c.msgtype) for c, _, raw in reader.messages(connections=[c for c in reader.connections if c.topic == IMAGE]))}
    assert set(maps) <= image_stamps
    saved = read_live_maps(bag_run / "live_maps.nc")
    by_time = {round(d.meta["t_s"], 6): d for d in maps.values()}
    assert len(saved["time"]) >= 5
    for i, t in enumerate(saved["time"].values):
        dem = by_time[round(float(t), 6)]
        assert dem.meta["frame_id"] == "dem_graph_heading"
        for layer in outputs.GRID_MAP_LAYERS:
            np.testing.assert_array_equal(dem.layers[layer], saved[layer].values[i].astype(np.float32), err_msg=f"{layer} at {t}")


def test_the_bytes_on_the_wire_are_rosbags_cdr(node_run):
    from dem_graph.ros2.messages import Codec

    codec = Codec()
    for topic, msgtype in (("/dem_graph/elevation_map", GRID_MAP), ("/dem_graph/odometry", ODOMETRY), ("/dem_graph/cost_map", COST)):
        data, msg, _ = node_run["received"][topic][-1]
        assert data[:4] == b"\x00\x01\x00\x00"
        assert data == codec.encode(msg, msgtype)


def test_the_odometry_on_the_wire_is_the_bag_runs_trajectory_and_the_rig_its_rig(node_run, bag_run):
    odometry = node_run["received"]["/dem_graph/odometry"]
    trajectory = read_tum(bag_run / "trajectory.tum")
    assert len(odometry) == len(trajectory.t_s)
    t = np.array([m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec for _, m, _ in odometry])
    np.testing.assert_allclose(t, trajectory.t_s, rtol=0, atol=1e-6)  # (the stamps are exact; the TUM file's times are decimals)
    poses = np.array([outputs.pose_of(m.pose.pose) for _, m, _ in odometry])
    np.testing.assert_allclose(poses, trajectory.poses_se3, rtol=0, atol=1e-9)
    assert {m.header.frame_id for _, m, _ in odometry} == {"map"} and {m.child_frame_id for _, m, _ in odometry} == {"base_footprint"}
    assert yaml.safe_load((node_run["out"] / "rig.yaml").read_text()) == yaml.safe_load((bag_run / "rig.yaml").read_text())


def test_nothing_the_node_received_was_lost_and_bad_messages_cost_one_message(node_run, bag_run, bag):
    from dem_graph.datasets.rosbag import open_bag

    with open_bag(bag) as reader:
        sent = {c.topic: 0 for c in reader.connections}
        for c, _, _ in reader.messages():
            sent[c.topic] += 1
    metrics = json.loads((node_run["out"] / "metrics.json").read_text())
    truth = json.loads((bag_run / "metrics.json").read_text())
    streams = metrics["live_source"]["streams"]
    for stream, topic in (("camera", IMAGE), ("laser", SCAN), ("odometry", ODOM), ("imu", IMU), ("camera_info", "/camera/camera_info"), ("tf", "/tf"), ("tf_static", "/tf_static")):
        h = streams[stream]
        assert (h["received"], h["late"], h["undecodable"]) == (sent[topic], 0, 0), (stream, h)
    assert streams["camera"]["missing"] == streams["laser"]["missing"] == 0
    # the bad messages: skipped, counted as the bag run counts them, and nothing else lost
    assert metrics["skipped_messages"] == truth["skipped_messages"] == {"imu_nonfinite": 1, "laser_wrong_shape": 1, "odometry_nonfinite": 1}
    assert metrics["live_source"]["frames_published"] == truth["frames"] == metrics["frames"]


def test_the_wire_is_ros2s_as_discovery_announces_it(node_run):
    """Topic names under rt/, ROS 2's type names, XCDR1 only, the RIHS01 type hash in USER_DATA, ROS 2's QoS profiles."""
    from cyclonedds.qos import Policy

    from dem_graph.ros2.messages import Codec

    codec = Codec()
    endpoints = node_run["endpoints"]
    expected = {
        ("writer", "rt/dem_graph/elevation_map"): (GRID_MAP, True, False),
        ("writer", "rt/dem_graph/global_map"): (GRID_MAP, True, True),
        ("writer", "rt/dem_graph/cost_map"): (COST, True, True),
        ("writer", "rt/dem_graph/odometry"): (ODOMETRY, True, False),
        ("writer", "rt/diagnostics"): (DIAGNOSTICS, True, False),
        ("writer", "rt/tf"): ("tf2_msgs/msg/TFMessage", True, False),
        ("reader", "rt/camera/image_raw"): ("sensor_msgs/msg/Image", False, False),
        ("reader", "rt/scan"): ("sensor_msgs/msg/LaserScan", False, False),
        ("reader", "rt/tf_static"): ("tf2_msgs/msg/TFMessage", True, True),
    }
    for key, (msgtype, reliable, transient_local) in expected.items():
        found = [(t, q) for t, q in endpoints.get(key, []) if q[Policy.Userdata] is not None and q[Policy.Userdata].data.startswith(b"typehash=") and t == msgtype.replace("/msg/", "::msg::dds_::") + "_"]
        assert found, (key, endpoints.get(key))
        type_name, qos = found[-1]
        assert qos[Policy.Userdata].data == f"typehash={codec.type_hash(msgtype)};".encode()
        assert qos[Policy.DataRepresentation] == Policy.DataRepresentation(use_cdrv0_representation=True, use_xcdrv2_representation=False)
        assert (qos[Policy.Reliability] != Policy.Reliability.BestEffort) == reliable, key
        assert (qos[Policy.Durability] == Policy.Durability.TransientLocal) == transient_local, key


def test_the_diagnostics_say_the_frame_time_the_graph_the_tracking_and_each_stream(node_run):
    arrays = [m for _, m, _ in node_run["received"]["/diagnostics"]]
    assert arrays
    last = {s.name: s for s in arrays[-1].status}
    assert {"dem_graph: frame time", "dem_graph: graph", "dem_graph: tracking", f"dem_graph: {IMAGE}", f"dem_graph: {SCAN}"} <= set(last)
    values = {s.name: {kv.key: kv.value for kv in s.values} for s in arrays[-1].status}
    assert float(values["dem_graph: frame time"]["median_ms"]) > 0 and float(values["dem_graph: frame time"]["camera_period_ms"]) == 40.0
    assert values["dem_graph: graph"]["estimator"] == "ekf-ptpm" and last["dem_graph: graph"].message == "no graph"
    assert int(values[f"dem_graph: {IMAGE}"]["received"]) > 0 and float(values[f"dem_graph: {SCAN}"]["rate_hz"]) == 12.5
    assert int(values["dem_graph: tracking"]["tracked"]) > 0
