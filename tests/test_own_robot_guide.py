"""docs/guide/own_robot.md, run: every `dem-graph` command of its bash blocks, in order, on a robot's bag
the tests write (tests/robot_bags.py: a simulated drive as a ROS 1 bag with CameraInfo, LaserScan,
zero-covariance Odometry, /tf in two message types and /tf_static) and a checkerboard recording
written as a bag (tests/test_calibration_rosbag.py's helpers), each with exit code 0 and what it claims."""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from dem_graph.cli import main

pytest.importorskip("rosbags")
from robot_bags import write_robot_bag  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
GUIDE = ROOT / "docs" / "guide" / "own_robot.md"


def guide_commands() -> list[str]:
    """The `dem-graph` lines of the guide's ```bash blocks, in order."""
    blocks = re.findall(r"^```bash\n(.*?)^```", GUIDE.read_text(), re.MULTILINE | re.DOTALL)
    return [line.strip() for block in blocks for line in block.splitlines() if line.strip().startswith("dem-graph")]


def _calibration_bag(path: Path) -> Path:
    """A 9x6 board of 9 cm squares seen in 6 views, as test_calibration_rosbag writes it (topics as the guide names them)."""
    from test_calibration_rosbag import _bag_ready, _messages, _store, _write_bag

    from dem_graph.calibration.simulate import simulate_calibration, write_recording

    sim = _bag_ready(simulate_calibration(seed=5, n_views=6, range_sigma_m=0.01))
    folder = write_recording(sim, path.parent / "calib_rec", seed=5, samples=1)
    images = [cv2.imread(str(folder / "data" / f"RGB{k + 1}.png"), cv2.IMREAD_UNCHANGED) for k in range(6)]
    store = _store(True)
    return _write_bag(path, True, _messages(store, True, sim, images), store)


def test_every_command_of_the_guide_runs(tmp_path, monkeypatch):
    from dem_graph.sim.pipeline import simulate
    from dem_graph.sim.scenarios import scenario

    simulate(scenario("smoke", seed=5, length_m=2.0, with_imu=False), tmp_path / "drive", preview=False)
    monkeypatch.chdir(tmp_path)
    write_robot_bag(tmp_path / "robot.bag", tmp_path / "drive", "ros1")
    _calibration_bag(tmp_path / "calib.bag")
    (tmp_path / "examples").symlink_to(ROOT / "examples")
    commands = guide_commands()
    assert len(commands) >= 7 and any(c.startswith("dem-graph bag-info") for c in commands) and any(c.startswith("dem-graph calibrate") for c in commands)
    runner = CliRunner()
    outputs = {}
    for command in commands:
        args = shlex.split(command)
        target = None
        if ">" in args:
            target = args[args.index(">") + 1]
            args = args[: args.index(">")]
        result = runner.invoke(main, args[1:])
        assert result.exit_code == 0, (command, result.output)
        if target is not None:
            Path(target).write_text(result.stdout)
        outputs[args[1] + " " + (args[-1] if args[1] != "config" else "")] = result.output
    info = next(v for k, v in outputs.items() if k.startswith("bag-info"))
    assert "proposed: dem-graph run robot.bag --image-topic /camera/image_raw --scan-topic /scan --odometry-topic /odom --out RUN" in info
    assert "tf2_msgs/msg/TFMessage + tf/msg/tfMessage" in info and "fx_px: 224.0" in info
    # the first run's rig, given back, gives the same trajectory
    assert (tmp_path / "first" / "trajectory.tum").read_text() == (tmp_path / "again" / "trajectory.tum").read_text()
    # the printed defaults change nothing
    assert (tmp_path / "first" / "trajectory.tum").read_text() == (tmp_path / "tuned" / "trajectory.tum").read_text()
    # the calibration put the body on the ground, 0.8 m under the camera
    from dem_graph.geometry.rig import load_rig

    rig = load_rig(tmp_path / "calib" / "rig.yaml")
    np.testing.assert_allclose(rig.T_body_cam[:3, 3], [0.0, 0.0, 0.8], atol=1e-12)
