"""The run folder: every file written and readable back; timing summary."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from dem_graph.errors import DemGraphError
from dem_graph.evaluation.timing import frame_timing_summary
from dem_graph.geometry.trajectory import Trajectory
from dem_graph.io.ply import read_points_ply
from dem_graph.io.tum import read_tum
from dem_graph.pipeline.run_folder import write_run_outputs


def make_trajectory(n: int = 20, seed: int = 0) -> Trajectory:
    rng = np.random.default_rng(seed)
    t = 1.7e9 + np.cumsum(rng.uniform(0.01, 0.1, n))
    return Trajectory(t, rng.normal(scale=10.0, size=(n, 3)), Rotation.random(n, random_state=seed).as_quat())


def test_run_folder_is_written_and_reads_back(tmp_path):
    trajectory = make_trajectory()
    odometry = make_trajectory(seed=1)
    points = np.random.default_rng(2).normal(size=(30, 3))
    attributes = {"sigma_m": np.full(30, 0.01), "source": np.arange(30, dtype=np.uint8) % 2}
    metrics = {
        "trajectory": {"ate_rmse_m": 0.12, "drift_percent": float("nan")},
        "n_frames": np.int64(7),
        "scale": np.float32(1.5),
        "inf": float("inf"),
        "per_frame_ms": np.array([1.0, np.nan]),
    }
    config = {"estimator": "graph", "window": 10, "sigmas": (0.1, 0.2), "nested": {"b": 1, "a": 2}}
    out = tmp_path / "runs" / "r1"  # parents are created
    paths = write_run_outputs(out, trajectory, points, attributes, metrics, config, {"odometry": odometry})

    assert set(paths) == {"trajectory", "points", "metrics", "config", "odometry"}
    assert paths["trajectory"] == out / "trajectory.tum"
    assert paths["odometry"] == out / "odometry.tum"
    assert all(p.is_file() for p in paths.values())

    back = read_tum(paths["trajectory"])
    np.testing.assert_array_equal(back.t_s, trajectory.t_s)
    np.testing.assert_array_equal(back.positions_xyz, trajectory.positions_xyz)
    np.testing.assert_array_equal(back.orientations_quat_xyzw, trajectory.orientations_quat_xyzw)
    np.testing.assert_array_equal(read_tum(paths["odometry"]).positions_xyz, odometry.positions_xyz)

    points_back, attributes_back = read_points_ply(paths["points"])
    np.testing.assert_array_equal(points_back, points)
    np.testing.assert_array_equal(attributes_back["source"], attributes["source"])

    text = paths["metrics"].read_text()
    assert "NaN" not in text and "Infinity" not in text
    parsed = json.loads(text)
    assert parsed == {
        "trajectory": {"ate_rmse_m": 0.12, "drift_percent": None},
        "n_frames": 7,
        "scale": 1.5,
        "inf": None,
        "per_frame_ms": [1.0, None],
    }
    assert list(parsed) == sorted(parsed)  # sorted keys
    assert text.startswith("{\n  ")  # pretty

    config_text = paths["config"].read_text()
    assert yaml.safe_load(config_text) == {"estimator": "graph", "window": 10, "sigmas": [0.1, 0.2], "nested": {"b": 1, "a": 2}}
    assert config_text.index("estimator") < config_text.index("window")  # insertion order kept
    assert config_text.index("b:") < config_text.index("a:")


def test_empty_points_and_existing_folder(tmp_path):
    paths = write_run_outputs(tmp_path, make_trajectory(), np.empty((0, 3)), {}, {}, {})
    assert read_points_ply(paths["points"])[0].shape == (0, 3)
    assert json.loads(paths["metrics"].read_text()) == {}


@pytest.mark.parametrize("name", ["trajectory", "metrics", "../evil", "", ".hidden"])
def test_bad_extra_trajectory_names_are_refused(tmp_path, name):
    with pytest.raises(DemGraphError, match="extra trajectory name"):
        write_run_outputs(tmp_path / "r", make_trajectory(), np.zeros((1, 3)), {}, {}, {}, {name: make_trajectory()})
    assert not (tmp_path / "r").exists()  # nothing written


def test_frame_timing_summary():
    per_frame = {"total": [0.010, 0.020, 0.030, 0.040], "update": [0.001] * 5, "tracking": []}
    summary = frame_timing_summary(per_frame)
    assert list(summary) == ["total", "update", "tracking"]
    assert summary["total"].median_ms == pytest.approx(25.0)
    assert summary["total"].mean_ms == pytest.approx(25.0)
    assert summary["total"].p95_ms == pytest.approx(np.percentile([10, 20, 30, 40], 95))
    assert summary["update"].to_json_dict() == pytest.approx({"median_ms": 1.0, "p95_ms": 1.0, "mean_ms": 1.0})
    assert all(math.isnan(v) for v in summary["tracking"].to_json_dict().values())
    assert all(type(v) is float for s in summary.values() for v in s.to_json_dict().values())
