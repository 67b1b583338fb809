"""The ROS 2 node's latency benchmark: from a camera message on the wire to the GridMap of that frame
on the wire, with the player, the node (and its graph process) and a subscriber in processes of
their own on one machine, over loopback.

A simulated drive (``paper``'s world at 640x480 and 25 Hz, the laser at 50 Hz, odometry and IMU)
is written once as a ROS 2 bag; each run then starts a subscriber (:func:`listen`, this module run
as a program), the node (``dem-graph ros2 node``, vehicle mode by default) and the player
(``dem-graph ros2 play --timing-csv``), and pairs each GridMap with its image by their stamp (the
node's outputs carry the image's own): the latency is the GridMap's arrival at the subscriber less
the image's write by the player, both on this machine's clock. The node's ``metrics.json`` gives the
transport's own cost per frame (messages taken and decoded, outputs encoded and written), the frame
time, and what it received against what the player sent.
"""

from __future__ import annotations

import csv
import json
import logging
import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dem_graph.evaluation.timing import TimingStats, format_table, machine_description
from dem_graph.sim.config import ScenarioConfig
from dem_graph.sim.scenarios import scenario

log = logging.getLogger(__name__)

IMAGE, SCAN, ODOM, IMU = "/camera/image_raw", "/scan", "/odom", "/imu/data"
ELEVATION_MAP = "/dem_graph/elevation_map"


def latency_scenario(duration_s: float = 30.0, seed: int = 0) -> ScenarioConfig:
    """``paper``'s world and vehicle with a 640x480 camera at 25 Hz (the intrinsics scaled from 800x600)
    and the laser at 50 Hz, for ``duration_s`` of driving."""
    config = scenario("paper", seed=seed)
    length_m = config.path.speed_mps * duration_s
    rig = config.rig
    s = 640 / rig.camera.width_px
    camera = rig.camera.model_copy(update={"width_px": 640, "height_px": 480, "fx_px": rig.camera.fx_px * s, "fy_px": rig.camera.fy_px * s, "cx_px": 319.5, "cy_px": 239.5})
    laser = rig.laser.model_copy(update={"rate_hz": 50.0})
    data = config.model_dump()
    data.update(name="ros2-latency", length_m=length_m, rig={**rig.model_dump(), "camera": camera.model_dump(), "laser": laser.model_dump()}, laser_time_offset_s=0.013 % (1 / 50.0))
    return ScenarioConfig.model_validate(data)


@dataclass
class Ros2BenchRun:
    """One run: the latency of each frame's GridMap, and the node's own figures."""

    latency: TimingStats  # the frames after the warm-up
    caught_up_s: float  # from the first image sent to the first GridMap within two camera periods of its image (the node's start: the rig, the estimator, the graph process, the backlog)
    frames_sent: int
    gridmaps_received: int
    transport_median_ms: float
    whole_frame_median_ms: float
    whole_frame_p95_ms: float
    sent: dict[str, int]
    received: dict[str, int]
    frames_skipped: int = 0  # images the node skipped, behind the camera (--max-frame-lag-s)

    @property
    def lost(self) -> int:
        """Messages the player sent that the node did not receive."""
        return sum(max(n - self.received.get(topic, 0), 0) for topic, n in self.sent.items())


@dataclass
class Ros2BenchResult:
    runs: list[Ros2BenchRun] = field(default_factory=list)
    machine: str = ""
    estimator: str = ""
    warmup_s: float = 10.0

    def table(self) -> str:
        rows = [
            [str(i + 1), f"{r.gridmaps_received}/{r.frames_sent}", f"{r.caught_up_s:.1f}", f"{r.latency.median_ms:.1f}", f"{r.latency.p95_ms:.1f}", f"{r.transport_median_ms:.2f}",
             f"{r.whole_frame_median_ms:.1f}", f"{r.whole_frame_p95_ms:.1f}", str(r.frames_skipped), str(r.lost)]
            for i, r in enumerate(self.runs)
        ]
        med = lambda values: float(np.median(values))  # noqa: E731
        rows.append(["median", "", f"{med([r.caught_up_s for r in self.runs]):.1f}", f"{med([r.latency.median_ms for r in self.runs]):.1f}", f"{med([r.latency.p95_ms for r in self.runs]):.1f}",
                     f"{med([r.transport_median_ms for r in self.runs]):.2f}", f"{med([r.whole_frame_median_ms for r in self.runs]):.1f}",
                     f"{med([r.whole_frame_p95_ms for r in self.runs]):.1f}", "", ""])
        return format_table(
            ["run", "GridMaps/frames", "caught up s", f"latency median ms (after {self.warmup_s:g} s)", "latency p95 ms", "transport ms/frame", "frame median ms", "frame p95 ms", "skipped", "lost"],
            rows, title=f"camera message -> GridMap on the wire, {self.estimator}, player/node/subscriber in 3 processes on {self.machine}",
        )


def _dem_graph(*args: str) -> list[str]:
    return [sys.executable, "-m", "dem_graph.cli", "--no-progress", *args]


def bench_ros2(work_dir: str | Path, duration_s: float = 40.0, runs: int = 3, seed: int = 0, estimator: str = "isam2-process", warmup_s: float = 10.0) -> Ros2BenchResult:
    """Simulate the drive once (kept in ``work_dir``), then ``runs`` runs of player, node and
    subscriber (see the module); the latency is of the frames sent ``warmup_s`` after the first
    (the node's start-up, timed apart). Traffic stays on loopback unless ``CYCLONEDDS_URI`` says otherwise."""
    from dem_graph.datasets.bag_writer import BagOptions, write_robot_bag
    from dem_graph.ros2.dds import LOOPBACK_CONFIG
    from dem_graph.sim.pipeline import simulate

    work = Path(work_dir)
    work.mkdir(parents=True, exist_ok=True)
    config = latency_scenario(duration_s, seed)
    folder, bag = work / f"{config.name}_seed{seed}_{duration_s:g}s", work / f"{config.name}_seed{seed}_{duration_s:g}s_bag"
    if not bag.exists():
        simulate(config, folder, overwrite=True, preview=False)
        write_robot_bag(bag, folder, "mcap", BagOptions(imu=True))
    env = dict(os.environ)
    if not env.get("CYCLONEDDS_URI"):
        (work / "cyclonedds_lo.xml").write_text(LOOPBACK_CONFIG)
        env["CYCLONEDDS_URI"] = (work / "cyclonedds_lo.xml").as_uri()
    env.setdefault("ROS_DOMAIN_ID", "77")
    result = Ros2BenchResult(machine=machine_description(), estimator=estimator, warmup_s=warmup_s)
    for k in range(runs):
        result.runs.append(_one_run(work / f"run_{k + 1}", bag, env, estimator, duration_s, warmup_s, config.rig.camera.rate_hz))
    return result


def _one_run(run_dir: Path, bag: Path, env: dict, estimator: str, duration_s: float, warmup_s: float, camera_rate_hz: float) -> Ros2BenchRun:
    import shutil

    shutil.rmtree(run_dir, ignore_errors=True)
    run_dir.mkdir(parents=True)
    listener = subprocess.Popen([sys.executable, "-m", "dem_graph.studies.bench_ros2", "listen", str(run_dir / "gridmaps.csv")], env=env)
    node_log = open(run_dir / "node.log", "w")  # noqa: SIM115 - closed below
    node = subprocess.Popen(
        _dem_graph("ros2", "node", "--image-topic", IMAGE, "--scan-topic", SCAN, "--odometry-topic", ODOM, "--imu-topic", IMU, "--estimator", estimator, "--out", str(run_dir / "node")),
        env=env, stdout=node_log, stderr=subprocess.STDOUT,
    )
    try:
        played = subprocess.run(_dem_graph("ros2", "play", str(bag), "--wait-for-subscribers-s", "120", "--timing-csv", str(run_dir / "sent.csv")), env=env, capture_output=True, text=True, timeout=duration_s * 4 + 180)
        if played.returncode != 0:
            raise RuntimeError(f"the player failed: {played.stderr[-500:]}")
        time.sleep(2.0)
    finally:
        for proc in (node, listener):
            if proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
        node.wait(timeout=120)
        listener.wait(timeout=30)
        node_log.close()
    sent_images: dict[tuple[int, int], int] = {}
    sent: dict[str, int] = {}
    with open(run_dir / "sent.csv") as fh:
        for row in csv.DictReader(fh):
            sent[row["topic"]] = sent.get(row["topic"], 0) + 1
            if row["topic"] == IMAGE:
                ns = int(row["stamp_ns"])
                sent_images[(ns // 10**9, ns % 10**9)] = int(row["written_ns"])
    with open(run_dir / "gridmaps.csv") as fh:
        rows = list(csv.DictReader(fh))
    first_ns = min(sent_images.values())
    pairs = sorted((sent_images[key], int(row["received_ns"])) for row in rows if (key := (int(row["sec"]), int(row["nanosec"]))) in sent_images)
    latencies = [(received - written) * 1e-9 for written, received in pairs if written - first_ns >= warmup_s * 1e9]
    caught_up = next(((written - first_ns) * 1e-9 for written, received in pairs if received - written < 2e9 / camera_rate_hz), float("nan"))
    metrics = json.loads((run_dir / "node" / "metrics.json").read_text())
    streams = metrics["live_source"]["streams"]
    received = {h["topic"]: h["received"] for h in streams.values()}
    live = metrics["live_map"]
    return Ros2BenchRun(
        TimingStats.from_seconds(latencies), caught_up, len(sent_images), len(rows), metrics["live_source"]["transport_median_ms"], live["whole_frame_median_ms"], live["whole_frame_p95_ms"],
        sent, received, metrics["live_source"].get("frames_skipped", 0),
    )


def listen(csv_path: str | Path, topic: str = ELEVATION_MAP) -> int:
    """The benchmark's subscriber (a process of its own): every GridMap's stamp and arrival (ns) to
    ``csv_path``, until SIGTERM. Returns how many came."""
    from dem_graph.ros2.dds import Participant
    from dem_graph.ros2.qos import DEFAULT

    participant = Participant()
    reader = participant.reader(topic, "grid_map_msgs/msg/GridMap", DEFAULT.with_depth(100))
    codec = participant.codec
    stop = []
    signal.signal(signal.SIGTERM, lambda *_: (stop.append(1), participant.wake()))
    rows = []
    while not stop:
        participant.wait(0.5)
        for rec in reader.take_all():
            header = codec.decode(rec.data, "grid_map_msgs/msg/GridMap").header
            rows.append((int(header.stamp.sec), int(header.stamp.nanosec), rec.received_ns))
    with open(csv_path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["sec", "nanosec", "received_ns"])
        w.writerows(rows)
    participant.close()
    return len(rows)


if __name__ == "__main__":  # the benchmark's subscriber: python -m dem_graph.studies.bench_ros2 listen OUT.csv
    if len(sys.argv) != 3 or sys.argv[1] != "listen":
        sys.exit("usage: python -m dem_graph.studies.bench_ros2 listen OUT.csv")
    listen(sys.argv[2])


__all__ = ["Ros2BenchResult", "Ros2BenchRun", "bench_ros2", "latency_scenario", "listen"]
