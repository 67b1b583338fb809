"""The configuration in the open: `dem-graph config` prints every setting under its description, the
text reads back to the defaults bit for bit, `run --config` with it gives the same run (on a simulated
log and on KITTI, whose own settings still apply), and the example files under examples/ validate."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml
from click.testing import CliRunner
from pydantic import BaseModel

from dem_graph.cli import main
from dem_graph.geometry.rig import load_rig
from dem_graph.pipeline.config import RunConfig, run_config, without_restated_defaults
from dem_graph.pipeline.config_yaml import config_yaml

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"


def _leaves(model: BaseModel, prefix: str = ""):
    for name, info in type(model).model_fields.items():
        value = getattr(model, name)
        if isinstance(value, BaseModel):
            yield from _leaves(value, f"{prefix}{name}.")
        else:
            yield f"{prefix}{name}", info.description


def test_the_printed_configuration_reads_back_to_the_defaults_exactly():
    text = CliRunner().invoke(main, ["config"]).output
    assert text == config_yaml()
    assert RunConfig.model_validate(yaml.safe_load(text)).model_dump(mode="json") == RunConfig().model_dump(mode="json")
    # every setting is there, each under its own description as a comment
    comments, stack, pending = {}, [], []
    for line in text.splitlines():
        indent = len(line) - len(line.lstrip())
        if line.lstrip().startswith("#"):
            pending.append(line.strip()[2:])
            continue
        key = line.strip().split(":", 1)[0]
        stack = [(i, k) for i, k in stack if i < indent] + [(indent, key)]
        comments[".".join(k for _, k in stack)] = " ".join(pending)
        pending = []
    leaves = list(_leaves(RunConfig()))
    assert len(leaves) > 100
    for path, description in leaves:
        assert path in comments, path
        assert comments[path] == " ".join((description or "").split()), path


def test_run_with_the_printed_configuration_is_bit_identical(tmp_path, tiny_folder):
    runner = CliRunner()
    (tmp_path / "c.yaml").write_text(runner.invoke(main, ["config"]).output)
    plain = runner.invoke(main, ["run", str(tiny_folder), "--out", str(tmp_path / "plain")])
    configured = runner.invoke(main, ["run", str(tiny_folder), "--config", str(tmp_path / "c.yaml"), "--out", str(tmp_path / "configured")])
    assert plain.exit_code == 0 and configured.exit_code == 0, configured.output
    assert (tmp_path / "plain" / "trajectory.tum").read_bytes() == (tmp_path / "configured" / "trajectory.tum").read_bytes()
    assert len((tmp_path / "plain" / "trajectory.tum").read_text().splitlines()) >= 7


def test_on_kitti_a_file_restating_the_defaults_leaves_the_datasets_settings(tmp_path, kitti_sample, caplog):
    from dem_graph.datasets.kitti import open_kitti

    sequence = open_kitti(kitti_sample)
    (tmp_path / "c.yaml").write_text(config_yaml())
    with caplog.at_level("INFO"):
        configured = run_config(sequence, tmp_path / "c.yaml")
    assert configured.model_dump(mode="json") == run_config(sequence).model_dump(mode="json")
    # KITTI gives no speed: the search cap stays the default's 40 and follows the speed the estimator holds
    assert configured.frontend.tracker.max_search_half_size_px == 40 and configured.frontend.tracker.search_cap_follows_speed
    assert any("motion.initial_speed_from_dataset" in r.getMessage() and "10 values restate a default" in r.getMessage() for r in caplog.records)


@pytest.mark.shared_data
def test_on_kitti_the_printed_configuration_gives_the_same_trajectory_to_the_byte(tmp_path, kitti_sample):
    """`dem-graph config > c.yaml; dem-graph run KITTI --config c.yaml` runs what `dem-graph run KITTI`
    runs: KITTI's own settings (a car's speed, the Velodyne's starting speed, ...) stay under the
    file's restated defaults, and the settings derived from vehicle.speed_mps come out the same."""
    runner = CliRunner()
    (tmp_path / "c.yaml").write_text(runner.invoke(main, ["config"]).output)
    first_frames = ["--max-frames", "12"]
    plain = runner.invoke(main, ["--no-progress", "run", str(kitti_sample), *first_frames, "--out", str(tmp_path / "plain")])
    configured = runner.invoke(main, ["--no-progress", "run", str(kitti_sample), *first_frames, "--config", str(tmp_path / "c.yaml"), "--out", str(tmp_path / "configured")])
    assert plain.exit_code == 0 and configured.exit_code == 0, configured.output
    trajectory = (tmp_path / "plain" / "trajectory.tum").read_bytes()
    assert trajectory == (tmp_path / "configured" / "trajectory.tum").read_bytes()
    assert len([line for line in trajectory.decode().splitlines() if not line.startswith("#")]) == 12
    assert (tmp_path / "plain" / "config.yaml").read_text() == (tmp_path / "configured" / "config.yaml").read_text()


def test_a_value_other_than_the_default_wins_over_the_datasets():
    defaults = RunConfig().model_dump(mode="json")
    dataset = {"motion": {"sigma_angular_acc_radps2": 0.2}, "frontend": {"focus": {"corridor_width_m": 6.0}}}
    restated = {"motion": {"sigma_angular_acc_radps2": defaults["motion"]["sigma_angular_acc_radps2"], "use_imu": True}, "frontend": {"focus": {"corridor_width_m": 2.0}}}
    given, kept = without_restated_defaults(restated, dataset, defaults)
    assert kept == ["motion.sigma_angular_acc_radps2"]
    assert given == {"motion": {"use_imu": True}, "frontend": {"focus": {"corridor_width_m": 2.0}}}


def _flat(mapping: dict, prefix: str = "") -> dict:
    """A nested mapping as dotted names and values."""
    out = {}
    for key, value in mapping.items():
        out.update(_flat(value, f"{prefix}{key}.") if isinstance(value, dict) else {f"{prefix}{key}": value})
    return out


def test_the_examples_validate():
    rig = load_rig(EXAMPLES / "rig.yaml")
    assert (rig.camera.width_px, rig.laser.beams.count) == (640, 1081) and rig.odometry is not None
    car = run_config(None, EXAMPLES / "car_10hz.yaml")
    slow = run_config(None, EXAMPLES / "slow_robot.yaml")
    default = RunConfig()
    assert car.vehicle.speed_mps == 12.0 and slow.vehicle.speed_mps == 0.5
    # the search cap is left to the derivation from the speed (test_derived_settings.py), and the slow robot's focus speed too
    assert car.frontend.tracker == default.frontend.tracker.model_copy(update={"min_patch_std_dn": 2.0})
    assert slow.frontend.focus.nominal_speed_mps == default.frontend.focus.nominal_speed_mps and car.frontend.focus.nominal_speed_mps == 4.0
    # the car's settings are KITTI's own but for these (docs/real_data.md, "One car example on both drives"): a
    # steadier speed, a near start, and no starting speed read from KITTI's Velodyne
    kitti = _flat(yaml.safe_load((Path(__file__).resolve().parent.parent / "dem_graph" / "datasets" / "settings" / "kitti.yaml").read_text()))
    example = _flat(yaml.safe_load((EXAMPLES / "car_10hz.yaml").read_text()))
    assert sorted(set(example) - set(kitti)) == ["frontend.focus.nominal_speed_mps", "motion.initial_speed_mps", "vehicle.speed_mps"]  # the example tells the speed
    assert sorted(set(kitti) - set(example)) == ["motion.initial_speed_from_dataset"]
    assert {k for k in kitti.keys() & example.keys() if kitti[k] != example[k]} == {"motion.sigma_linear_acc_mps2"}
    assert example["motion.sigma_linear_acc_mps2"] == 0.5 < kitti["motion.sigma_linear_acc_mps2"]
