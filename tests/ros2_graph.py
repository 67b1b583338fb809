"""A ROS 2 graph on this machine's loopback for the node's tests (tests' helper, not a test module).

Every participant of a test (the node and the player in their processes, the test's own subscriber)
binds Cyclone to ``lo`` and finds the others by unicast to 127.0.0.1 (``CYCLONEDDS_URI``, the
loopback configuration of :mod:`dem_graph.ros2.dds`): no traffic leaves the machine. Each test
module takes a domain id of its own, different on each xdist worker, so that concurrent tests
never hear each other.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

from dem_graph.ros2.dds import LOOPBACK_CONFIG, Participant

DOMAIN_BASE = 40  # domains 40 to 99: inside ROS 2's range for Linux (0-101)


def domain_id(offset: int) -> int:
    """A domain for a test module (``offset`` 0-4), distinct across xdist workers."""
    worker = os.environ.get("PYTEST_XDIST_WORKER", "gw0")
    n = int(worker[2:]) if worker.startswith("gw") and worker[2:].isdigit() else 0
    return DOMAIN_BASE + (5 * n + offset) % 60


def loopback_env(folder: Path, domain: int) -> dict[str, str]:
    """The environment of a process on the test's graph: ``lo`` only, ``ROS_DOMAIN_ID`` the test's."""
    config = folder / "cyclonedds_lo.xml"
    config.write_text(LOOPBACK_CONFIG)
    return {**os.environ, "CYCLONEDDS_URI": config.as_uri(), "ROS_DOMAIN_ID": str(domain), "PYTHONUNBUFFERED": "1"}


def dem_graph(*args: str) -> list[str]:
    return [sys.executable, "-m", "dem_graph.cli", "--no-progress", *args]


def start_node(env: dict, out_dir: Path, *args: str, log_path: Path) -> subprocess.Popen:
    """``dem-graph ros2 node`` in its own process, its output to ``log_path``."""
    fh = open(log_path, "w")  # noqa: SIM115 - closed with the process (wait_node)
    return subprocess.Popen(dem_graph("ros2", "node", "--out", str(out_dir), *args), env=env, stdout=fh, stderr=subprocess.STDOUT)


def wait_node(proc: subprocess.Popen, sig: int | None = signal.SIGTERM, timeout_s: float = 120.0) -> int:
    """Stop the node with ``sig`` (None: let it end by itself) and wait for it; its exit code."""
    if sig is not None and proc.poll() is None:
        proc.send_signal(sig)
    try:
        return proc.wait(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        proc.kill()
        raise


def play(env: dict, bag: Path, *args: str, timeout_s: float = 120.0) -> subprocess.CompletedProcess:
    """``dem-graph ros2 play BAG`` to its end."""
    return subprocess.run(dem_graph("ros2", "play", str(bag), *args), env=env, capture_output=True, text=True, timeout=timeout_s)


def start_player(env: dict, bag: Path, *args: str) -> subprocess.Popen:
    """``dem-graph ros2 play BAG`` in the background."""
    return subprocess.Popen(dem_graph("ros2", "play", str(bag), *args), env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


class Collector:
    """The test's own subscriber: a participant in this process taking what the node publishes in a
    thread, raw and decoded, each with the time it was received."""

    def __init__(self, domain: int, env: dict, subscriptions: list[tuple[str, str, object]]):
        self._previous_uri = os.environ.get("CYCLONEDDS_URI")
        os.environ["CYCLONEDDS_URI"] = env["CYCLONEDDS_URI"]  # (read when the domain is made, in this process)
        self.participant = Participant(domain)
        self.readers = {topic: (msgtype, self.participant.reader(topic, msgtype, qos)) for topic, msgtype, qos in subscriptions}
        self.received: dict[str, list] = {topic: [] for topic in self.readers}  # (bytes, message, received_ns)
        self._running = True
        self._thread = threading.Thread(target=self._loop, daemon=True)
        self._thread.start()

    def _loop(self) -> None:
        codec = self.participant.codec
        while self._running:
            self.participant.wait(0.05)
            for topic, (msgtype, reader) in self.readers.items():
                for rec in reader.take_all():
                    self.received[topic].append((rec.data, codec.decode(rec.data, msgtype), rec.received_ns))

    def wait_for(self, topic: str, count: int, timeout_s: float) -> bool:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if len(self.received[topic]) >= count:
                return True
            time.sleep(0.05)
        return False

    def close(self) -> None:
        self._running = False
        self.participant.wake()
        self._thread.join(timeout=5)
        self.participant.close()
        if self._previous_uri is None:
            os.environ.pop("CYCLONEDDS_URI", None)
        else:
            os.environ["CYCLONEDDS_URI"] = self._previous_uri
