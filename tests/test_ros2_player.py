"""``dem-graph ros2 play`` on a ROS 1 bag: its messages arrive as ROS 2's, with the bag's values
(header stamps and frames, CameraInfo's D K R P as d k r p, the scans' ranges, ROS 1's tf/tfMessage
as tf2_msgs/TFMessage), with the QoS ROS 2 drivers use; and ``dem-graph simulate --bag`` writes the
bag the player takes."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("rosbags")
pytest.importorskip("cyclonedds")

from ros2_graph import Collector, dem_graph, domain_id, loopback_env, play  # noqa: E402

from dem_graph.ros2.qos import LISTENER, TF_STATIC  # noqa: E402

pytestmark = pytest.mark.slow


def test_a_ros1_bag_is_published_as_ros2_messages_with_its_values(tmp_path):
    import subprocess

    from dem_graph.datasets.rosbag import open_bag

    bag = tmp_path / "sim.bag"
    made = subprocess.run(dem_graph("simulate", "--scenario", "smoke", "--length-m", "1", "--seed", "6", "--out", str(tmp_path / "sim"), "--bag", str(bag)), capture_output=True, text=True, timeout=300)
    assert made.returncode == 0 and f"bag: {bag}" in made.stdout, made.stderr
    env = loopback_env(tmp_path, domain_id(4))
    topics = [("/camera/camera_info", "sensor_msgs/msg/CameraInfo", LISTENER.with_depth(500)), ("/scan", "sensor_msgs/msg/LaserScan", LISTENER.with_depth(500)),
              ("/tf", "tf2_msgs/msg/TFMessage", LISTENER.with_depth(1000)), ("/tf_static", "tf2_msgs/msg/TFMessage", TF_STATIC.with_depth(10)),
              ("/camera/image_raw", "sensor_msgs/msg/Image", LISTENER.with_depth(500))]  # (the player waits for the image's subscription, and the scan's)
    collector = Collector(domain_id(4), env, topics)
    try:
        played = play(env, bag, "--wait-for-subscribers-s", "60")
        assert played.returncode == 0, played.stderr
        with open_bag(bag) as reader:
            sent: dict[str, list] = {}
            for c, _, raw in reader.messages():
                sent.setdefault(c.topic, []).append(reader.deserialize(raw, c.msgtype))
        for topic, _, _ in topics:
            collector.wait_for(topic, len(sent[topic]), timeout_s=10)
    finally:
        collector.close()
    got = {topic: [m for _, m, _ in collector.received[topic]] for topic, _, _ in topics}
    assert len(got["/camera/camera_info"]) == len(sent["/camera/camera_info"]) and len(got["/scan"]) == len(sent["/scan"])
    for ros2, ros1 in zip(got["/camera/camera_info"], sent["/camera/camera_info"]):
        assert (ros2.header.stamp.sec, ros2.header.stamp.nanosec, ros2.header.frame_id) == (ros1.header.stamp.sec, ros1.header.stamp.nanosec, ros1.header.frame_id)
        np.testing.assert_array_equal(ros2.k, ros1.K)
        np.testing.assert_array_equal(ros2.d, ros1.D)
        np.testing.assert_array_equal(ros2.p, ros1.P)
    for ros2, ros1 in zip(got["/scan"], sent["/scan"]):
        np.testing.assert_array_equal(ros2.ranges, ros1.ranges)
        assert ros2.angle_increment == ros1.angle_increment
    # ROS 1's /tf carries two types (TFMessage and the older tf/tfMessage): both arrive as TFMessage
    frames = {(t.header.frame_id, t.child_frame_id) for m in got["/tf"] for t in m.transforms}
    assert ("odom", "base_footprint") in frames and ("base_link", "wheel_left") in frames
    assert len(got["/tf"]) == len(sent["/tf"])
    np.testing.assert_array_equal(got["/camera/image_raw"][-1].data, sent["/camera/image_raw"][-1].data)
    assert {(t.header.frame_id, t.child_frame_id) for t in got["/tf_static"][0].transforms} == {(t.header.frame_id, t.child_frame_id) for t in sent["/tf_static"][0].transforms}
