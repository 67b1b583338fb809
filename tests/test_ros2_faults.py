"""The ROS 2 node's faults, each against what it must do, on loopback (tests/ros2_graph.py):

- a topic that never comes: one warning naming it, and the map goes on; refused in one line only
  when the topic carries the rig and ``--rig`` does not give what it would;
- the player restarted (its clock goes back): a new map in RUN-2 (``--on-clock-back new-map``), or
  the run written and the node stopped with one line (``stop``);
- a publisher whose QoS does not match the node's subscription: reported, by topic and policy;
- SIGKILL: the run folder holds what was written as the node went (the trajectory and the saved
  live maps, read back from their part file).

(SIGTERM and bad messages are in tests/test_ros2_node.py.)"""

from __future__ import annotations

import json
import signal
import time

import numpy as np
import pytest
import yaml

pytest.importorskip("rosbags")
pytest.importorskip("cyclonedds")

from robot_bags import IMAGE, INFO, ODOM, SCAN, BagEdits, write_robot_bag  # noqa: E402  (tests/ is on sys.path)
from ros2_graph import Collector, domain_id, loopback_env, play, start_node, start_player, wait_node  # noqa: E402

from dem_graph.ros2 import outputs  # noqa: E402
from dem_graph.ros2.qos import DEFAULT, SENSOR_DATA  # noqa: E402

pytestmark = pytest.mark.slow

GRID_MAP = "grid_map_msgs/msg/GridMap"
FAST_START = ["--estimator", "ptpm", "--startup-s", "0.5", "--topic-timeout-s", "2"]
# the tests that count frames map every one: on a loaded CI machine the default 0.2 s lag skips most of them
EVERY_FRAME = ["--max-frame-lag-s", "0"]


@pytest.fixture(scope="module")
def bag(tmp_path_factory):
    from dem_graph.sim.pipeline import simulate
    from dem_graph.sim.scenarios import scenario

    root = tmp_path_factory.mktemp("ros2_faults")
    simulate(scenario("smoke", seed=4, length_m=3.0), root / "ds", overwrite=True, preview=False)
    return write_robot_bag(root / "bag", root / "ds", "mcap", BagEdits())


def _bag_topics(bag, *left_out: str) -> str:
    from dem_graph.datasets.rosbag import open_bag

    with open_bag(bag) as reader:
        return ",".join(sorted({c.topic for c in reader.connections} - set(left_out)))


def test_a_topic_that_carries_the_rig_and_never_comes_is_refused_in_one_line(bag, tmp_path):
    env = loopback_env(tmp_path, domain_id(1))
    node = start_node(env, tmp_path / "run", "--image-topic", IMAGE, "--scan-topic", SCAN, *FAST_START, log_path=tmp_path / "node.log")
    try:
        play(env, bag, "--topics", _bag_topics(bag, INFO), "--wait-for-subscribers-s", "60")
        code = wait_node(node, sig=None, timeout_s=60)
    finally:
        if node.poll() is None:
            node.kill()
    log = (tmp_path / "node.log").read_text()
    errors = [line for line in log.splitlines() if line.startswith("dem-graph: error:")]
    assert code == 2 and len(errors) == 1, log
    assert f"{IMAGE}: no sensor_msgs/CameraInfo beside it" in errors[0] and "--rig with the camera's intrinsics" in errors[0]
    warned = [line for line in log.splitlines() if f"no message on {INFO}" in line]
    assert len(warned) == 1 and "unless --rig gives them" in warned[0]
    assert "Traceback" not in log


def test_a_topic_that_never_comes_is_named_once_the_map_goes_on_and_a_restart_stops_with_one_line(bag, tmp_path):
    """No odometry and no CameraInfo on the graph, the camera's intrinsics in --rig: one warning for
    each, a map without odometry; then the player again: with --on-clock-back stop, the run written and one line."""
    from dem_graph.datasets.folder import FolderSequence

    rig = FolderSequence(bag.parent / "ds").rig
    camera = {k: v for k, v in rig.camera.model_dump(mode="json").items() if k in ("width_px", "height_px", "fx_px", "fy_px", "cx_px", "cy_px", "distortion")}
    (tmp_path / "camera.yaml").write_text(yaml.safe_dump({"camera": camera}))
    env = loopback_env(tmp_path, domain_id(2))
    out = tmp_path / "run"
    args = ["--image-topic", IMAGE, "--scan-topic", SCAN, "--odometry-topic", ODOM, "--rig", str(tmp_path / "camera.yaml"), "--on-clock-back", "stop", *FAST_START, *EVERY_FRAME]
    node = start_node(env, out, *args, log_path=tmp_path / "node.log")
    try:
        topics = _bag_topics(bag, INFO, ODOM)
        assert play(env, bag, "--topics", topics, "--wait-for-subscribers-s", "60").returncode == 0
        time.sleep(1.0)
        play(env, bag, "--topics", topics)
        code = wait_node(node, sig=None, timeout_s=60)
    finally:
        if node.poll() is None:
            node.kill()
    log = (tmp_path / "node.log").read_text()
    lines = log.splitlines()
    assert len([x for x in lines if f"no message on {ODOM}" in x]) == 1 and len([x for x in lines if f"no message on {INFO}" in x]) == 1, log
    errors = [x for x in lines if x.startswith("dem-graph: error:")]
    assert code == 2 and len(errors) == 1 and "the stamps went back" in errors[0] and str(out) in errors[0] and "Traceback" not in log, log
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["frames"] > 20 and metrics["live_source"]["clock_resets"] == 1
    assert json.loads(json.dumps(yaml.safe_load((out / "rig.yaml").read_text())["camera"]))["fx_px"] == camera["fx_px"]
    assert "odometry" not in yaml.safe_load((out / "rig.yaml").read_text())
    assert not (tmp_path / "run-2").exists()


def test_a_restart_starts_a_new_map_a_qos_mismatch_is_reported_and_a_kill_keeps_what_was_written(bag, tmp_path):
    from dem_graph.io.live_maps import read_live_maps
    from dem_graph.io.tum import read_tum

    domain = domain_id(3)
    env = loopback_env(tmp_path, domain)
    (tmp_path / "settings.yaml").write_text(yaml.safe_dump({"checkpoint_every_s": 0.5, "live_map": {"save_every_n_frames": 5}}))
    out = tmp_path / "run"
    collector = Collector(domain, env, [("/dem_graph/elevation_map", GRID_MAP, DEFAULT.with_depth(400))])
    # a tf_static publisher that offers best effort: the node's tf_static subscription asks reliable and transient local, as tf2's does
    collector.participant.writer("/tf_static", "tf2_msgs/msg/TFMessage", SENSOR_DATA)
    node = start_node(env, out, "--image-topic", IMAGE, "--scan-topic", SCAN, "--odometry-topic", ODOM, "--config", str(tmp_path / "settings.yaml"), *FAST_START, *EVERY_FRAME, log_path=tmp_path / "node.log")
    try:
        assert play(env, bag, "--wait-for-subscribers-s", "60").returncode == 0
        first = len(collector.received["/dem_graph/elevation_map"])
        time.sleep(1.0)
        player = start_player(env, bag)  # again: its clock goes back
        assert collector.wait_for("/dem_graph/elevation_map", first + 30, timeout_s=60)
        time.sleep(1.0)  # (a checkpoint of the second map)
        wait_node(node, sig=signal.SIGKILL)
        player.wait(timeout=60)
    finally:
        if node.poll() is None:
            node.kill()
        collector.close()
    log = (tmp_path / "node.log").read_text()
    assert "the stamps went back" in log and "a new map starts in" in log, log
    incompatible = [x for x in log.splitlines() if "/tf_static: a publisher with incompatible QoS (reliability) does not match this subscription" in x]
    assert len(incompatible) == 1, log
    metrics = json.loads((out / "metrics.json").read_text())  # the first map: whole
    assert metrics["live_source"]["clock_resets"] == 1 and metrics["frames"] >= first - 1
    assert any("incompatible QoS (reliability)" in x for x in metrics["live_source"]["incompatible_qos"])
    killed = tmp_path / "run-2"  # the second map, killed: what was written as it went
    assert not (killed / "metrics.json").exists() and not (killed / "live_maps.nc").exists()
    trajectory = read_tum(killed / "trajectory.tum")
    maps = read_live_maps(killed / "live_maps.nc")  # read from live_maps.part
    assert len(trajectory.t_s) >= 10 and len(maps["time"]) >= 3 and np.all(np.diff(trajectory.t_s) > 0)
    # at most the last second lost (a checkpoint every 0.5 s); the saved maps are the GridMaps the node had published
    assert abs(maps["time"].values[-1] - trajectory.t_s[-1]) < 1.0
    second = {}
    for _, msg, _ in collector.received["/dem_graph/elevation_map"][first:]:
        dem = outputs.dem_from_grid_map(msg)
        second[round(dem.meta["t_s"], 6)] = dem
    for i, t in enumerate(maps["time"].values):
        np.testing.assert_array_equal(second[round(float(t), 6)].layers["elevation"], maps["elevation"].values[i])


def test_a_node_slower_than_the_camera_skips_stale_frames_and_its_path_stays_on_the_truth(bag, tmp_path):
    """The player at 8 times the camera's rate (200 Hz: a machine 8 times too slow): the frames more
    than --max-frame-lag-s (0.2 s) behind the newest image are skipped, counted in the metrics and
    the diagnostics, and every image received is either mapped or skipped. The frames mapped are
    25 Hz / 8 apart; the path still follows the simulator's truth to 3 cm in x and y (unskipped, the
    same run is within 1 cm: 8 mm here)."""
    import dataclasses

    from robot_bags import EPOCH_S

    from dem_graph.datasets.folder import FolderSequence
    from dem_graph.evaluation.trajectory_metrics import trajectory_errors
    from dem_graph.io.tum import read_tum

    domain = domain_id(4)
    env = loopback_env(tmp_path, domain)
    out = tmp_path / "run"
    collector = Collector(domain, env, [("/diagnostics", "diagnostic_msgs/msg/DiagnosticArray", DEFAULT.with_depth(100))])
    node = start_node(env, out, "--image-topic", IMAGE, "--scan-topic", SCAN, "--odometry-topic", ODOM, *FAST_START, log_path=tmp_path / "node.log")
    try:
        assert play(env, bag, "--rate", "8", "--wait-for-subscribers-s", "60").returncode == 0
        time.sleep(2.0)  # (the diagnostics of a second)
        wait_node(node)
    finally:
        if node.poll() is None:
            node.kill()
        collector.close()
    metrics = json.loads((out / "metrics.json").read_text())
    source = metrics["live_source"]
    skipped, received = source["frames_skipped"], source["streams"]["camera"]["received"]
    sequence = FolderSequence(bag.parent / "ds")
    n_images = sequence.n_frames
    assert received == n_images and skipped > n_images // 2 and metrics["frames"] + skipped == received, source
    trajectory = read_tum(out / "trajectory.tum")
    errors = trajectory_errors(dataclasses.replace(trajectory, t_s=trajectory.t_s - EPOCH_S), sequence.ground_truth.trajectory)
    assert len(trajectory.t_s) == metrics["frames"] and np.abs(errors.position_error_m[:, :2]).max() < 0.03
    frame_time = [s for _, msg, _ in collector.received["/diagnostics"] for s in msg.status if s.name == "dem_graph: frame time"]
    last = {v.key: v.value for v in frame_time[-1].values}
    assert int(last["frames_skipped"]) == skipped and int(frame_time[-1].level) == outputs.WARN, frame_time[-1]
    log = (tmp_path / "node.log").read_text()
    assert len([x for x in log.splitlines() if "the node is behind the camera" in x]) == 1 and "Traceback" not in log, log
