"""``dem-graph ros2``: the node on a robot's ROS 2 graph, and a player of bags for it (the ``[ros2]``
extra; no ROS installation). ``ROS_DOMAIN_ID`` chooses the graph, as for any ROS 2 node."""

from __future__ import annotations

import sys
from pathlib import Path

import click

from dem_graph.cli.commands import RUN_ESTIMATORS, _refuse_graph_flags_without_graph, _run_overrides
from dem_graph.cli.options import option, realtime_option
from dem_graph.cli.out_folder import out_folder, out_option
from dem_graph.cli.root import friendly_errors, main

TOPICS, OUTPUT, TIMING, ESTIMATOR = "Robot's topics and frames", "What it publishes", "Timing", "Estimator"


@main.group(short_help="The ROS 2 node and a bag player (no ROS needed).")
def ros2() -> None:
    """Map on a robot's ROS 2 graph (`dem-graph ros2 node`), and publish a bag on one (`dem-graph ros2 play`).
    Over Eclipse Cyclone DDS: no ROS installation; ROS_DOMAIN_ID as ROS 2 reads it (docs/guide/ros2.md)."""


@ros2.command("node", short_help="Map from a robot's ROS 2 topics; publish the GridMap, cost map, odometry, tf.")
@option("--image-topic", required=True, metavar="TOPIC", group=TOPICS, help="sensor_msgs/Image topic (CompressedImage when it ends in /compressed).")
@option("--scan-topic", required=True, metavar="TOPIC", group=TOPICS, help="sensor_msgs/LaserScan topic.")
@option("--odometry-topic", metavar="TOPIC", default=None, group=TOPICS, help="nav_msgs/Odometry topic (optional).")
@option("--imu-topic", metavar="TOPIC", default=None, group=TOPICS, help="sensor_msgs/Imu topic (optional; T_body_imu from tf).")
@option("--camera-info-topic", metavar="TOPIC", default=None, group=TOPICS, help="CameraInfo topic [default: the image topic's sibling camera_info].")
@option("--body-frame", metavar="FRAME", default=None, group=TOPICS, help="The body's tf frame, on the ground, z up [default: base_footprint, else base_link].")
@option("--camera-frame", metavar="FRAME", default=None, group=TOPICS, help="The camera's tf frame [default: the images'].")
@option("--laser-frame", metavar="FRAME", default=None, group=TOPICS, help="The laser's tf frame [default: the scans'].")
@option("--rig", "rig_path", type=click.Path(dir_okay=False, path_type=Path), default=None, group=TOPICS, help="A rig YAML over the rig read from the messages, whole or in part.")
@option("--map-frame", default="map", show_default=True, group=OUTPUT, help="The frame of the map and the poses (REP 105).")
@option("--odom-frame", default="odom", show_default=True, group=OUTPUT, help="The robot's odometry frame: the node publishes map -> odom.")
@option("--namespace", default="/dem_graph", show_default=True, group=OUTPUT, help="Where elevation_map, global_map, cost_map and odometry go.")
@option("--global-map-period-s", type=float, default=10.0, show_default=True, group=OUTPUT, help="Seconds between global maps (latched).")
@option("--config", "config_path", type=click.Path(dir_okay=False, path_type=Path), default=None, group=ESTIMATOR, help="YAML run settings (`dem-graph config` prints them).")
@option(
    "--estimator", type=click.Choice(RUN_ESTIMATORS), metavar="NAME", default="isam2-process", show_default=True, group=ESTIMATOR,
    help="gm, ptpm, isam2, isam2-process (the graph on another core: the vehicle's), isam2-batch, odometry.",
)
@option("--max-points", type=int, metavar="N", default=None, group=ESTIMATOR, help="Cap on live points.")
@option("--max-frames", type=int, metavar="N", default=None, group=ESTIMATOR, help="Stop after this many frames.")
@realtime_option(True, "a frame's deferred work done between frames, as on the vehicle; --as-fast-as-possible does each frame's whole work in it, as `run` does", group=ESTIMATOR)
@option("--reorder-window-s", type=float, default=0.1, show_default=True, group=TIMING, help="An event waits at most this long for the other streams to catch up.")
@option(
    "--max-frame-lag-s", type=float, default=0.2, show_default=True, group=TIMING,
    help="A frame this far behind the newest image received is skipped, so the map stays current when the machine is slower than the camera; 0 or less: every frame.",
)
@option("--startup-s", type=float, default=1.0, show_default=True, group=TIMING, help="Seconds of images and scans taken before the rig is derived.")
@option("--topic-timeout-s", type=float, default=5.0, show_default=True, group=TIMING, help="A topic silent this long from the start is reported (refused if the rig needs it).")
@option("--warm-up/--no-warm-up", default=True, show_default=True, group=TIMING, help="Compile or load the estimator's kernels before subscribing (2-3 s; 20 s on a new installation), not while the robot's messages wait.")
@option("--on-clock-back", type=click.Choice(["new-map", "stop"]), default="new-map", show_default=True, group=TIMING, help="When the stamps go back (a player or a robot restarted): a new map in RUN-2, or stop.")
@out_option("Run folder, kept current as the node runs.", "ros2-node", "<domain>", group="Output")
@option("--overwrite", is_flag=True, group="Output", help="Replace an earlier run in --out.")
@friendly_errors
def node_command(image_topic, scan_topic, odometry_topic, imu_topic, camera_info_topic, body_frame, camera_frame, laser_frame, rig_path, map_frame, odom_frame, namespace, global_map_period_s, config_path, estimator, max_points, max_frames, realtime, reorder_window_s, max_frame_lag_s, startup_s, topic_timeout_s, warm_up, on_clock_back, out_dir, overwrite) -> None:
    """Join the robot's ROS 2 graph and map from its topics while it drives: the local GridMap ahead
    (/dem_graph/elevation_map), the global one (latched), a cost map for Nav2, the odometry, tf
    (map -> odom) and /diagnostics. Ctrl-C or SIGTERM writes the run folder (docs/guide/ros2.md)."""
    from dem_graph.datasets.bag_rig import BagTopics
    from dem_graph.ros2.dds import ros_domain_id
    from dem_graph.ros2.node import NodeOptions, run_node
    from dem_graph.ros2.publisher import OutputTopics

    overrides = _run_overrides(estimator, False, max_frames=max_frames, max_points=max_points, realtime=realtime)
    _refuse_graph_flags_without_graph(overrides, config_path)
    domain = ros_domain_id()
    out_dir = out_folder(out_dir, "ros2-node", f"domain{domain}")
    topics = BagTopics(image_topic, scan_topic, odometry_topic, imu_topic, camera_info_topic, body_frame, camera_frame, laser_frame)
    options = NodeOptions(
        topics, out_dir, rig_path, config_path, overrides, OutputTopics(namespace=namespace), map_frame=map_frame, odom_frame=odom_frame,
        reorder_window_s=reorder_window_s, max_frame_lag_s=max_frame_lag_s if max_frame_lag_s > 0 else None, startup_s=startup_s, topic_timeout_s=topic_timeout_s, global_map_period_s=global_map_period_s,
        on_clock_back=on_clock_back, domain_id=domain, overwrite=overwrite, warm_up=warm_up,
    )
    click.echo(f"dem_graph node on ROS 2 domain {domain}: {'its kernels made ready, then ' if warm_up else ''}waiting for {image_topic} and {scan_topic} (Ctrl-C to stop)", err=True)
    runs = run_node(options)
    for run in runs:
        click.echo(f"map: {run.frames} frames in {run.out_dir}{f' ({run.error})' if run.error else ''}")
    if any(r.error and not r.error.startswith("interrupted") for r in runs[-1:]):
        sys.exit(2)


@ros2.command("play", short_help="Publish a ROS 1 or ROS 2 bag on the ROS 2 graph at its pace.")
@click.argument("bag", type=click.Path(path_type=Path))
@option("--rate", type=float, default=1.0, show_default=True, help="Times the recording's pace.")
@option("--topics", default=None, metavar="T1,T2", help="Only these topics, comma-separated [default: all].")
@option("--wait-for-subscribers-s", type=float, default=0.0, show_default=True, help="Wait up to this long for a subscription on the bag's image and scan topics before playing.")
@option("--timing-csv", type=click.Path(dir_okay=False, path_type=Path), default=None, help="Write each message's topic, header stamp and the time it was sent (ns).")
@friendly_errors
def play_command(bag, rate, topics, wait_for_subscribers_s, timing_csv) -> None:
    """Publish a ROS 1 or ROS 2 bag on the ROS 2 graph (ROS_DOMAIN_ID) at its own pace with the QoS ROS 2
    drivers use, as `ros2 bag play` does, so that `dem-graph ros2 node` can be tried on any recording."""
    from dem_graph.ros2.player import PlayOptions, play_bag

    chosen = tuple(t.strip() for t in topics.split(",") if t.strip()) if topics else None
    result = play_bag(PlayOptions(bag, rate, chosen, wait_for_subscribers_s, None, timing_csv))
    total = sum(result.messages.values())
    click.echo(f"played {total} messages on {len(result.messages)} topics in {result.duration_s:.1f} s" + (f"; left out: {', '.join(result.left_out)}" if result.left_out else ""))
