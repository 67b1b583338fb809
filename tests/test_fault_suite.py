"""The adversarial harness's findings, one test each: every bad input refused in one line naming the
file and the problem, every fault survived with a warning saying what was skipped."""

from __future__ import annotations

import logging
import shutil

import numpy as np
import pytest
import yaml
from click.testing import CliRunner

from dem_graph.cli import main
from dem_graph.datasets.events import CameraFrame
from dem_graph.datasets.faults import Faults, FaultSequenceError, write_faulty_dataset
from dem_graph.datasets.folder import FolderSequence
from dem_graph.datasets.open import DatasetOptions, check_options_used, open_dataset
from dem_graph.errors import DatasetError
from dem_graph.evaluation.dem_metrics import HeightErrors
from dem_graph.pipeline import RunConfig, run_estimator
from dem_graph.pipeline.config import RunOverrides
from dem_graph.pipeline.metrics import laser_cells_error_text
from dem_graph.pipeline.run import run_dataset


@pytest.fixture
def folder(smoke_folder, tmp_path):
    """A copy of the `smoke` dataset folder (63 frames at 25 Hz over 0 to 2.48 s, 31 scans) to break."""
    return shutil.copytree(smoke_folder, tmp_path / "data")


@pytest.fixture(scope="module")
def gm_run(smoke_folder, tmp_path_factory):
    """A short GM run folder of the smoke dataset (12 frames), for the commands that read one."""
    out = tmp_path_factory.mktemp("gm_run") / "run"
    run_dataset(smoke_folder, RunOverrides(estimator="gm", max_frames=12), out_dir=out)
    return out


def _cli(*args):
    return CliRunner().invoke(main, ["--no-progress", *map(str, args)])


def _one_line_error(r, *fragments) -> str:
    """The command failed with exit code 2 and one stderr line holding every fragment."""
    assert r.exit_code == 2, (r.exit_code, r.output, r.stderr)
    assert r.stderr.count("\n") == 1 and r.stderr.startswith("dem-graph: error: "), r.stderr
    for fragment in fragments:
        assert str(fragment) in r.stderr, f"{fragment!r} not in {r.stderr!r}"
    return r.stderr


def _run(dataset, out, *extra):
    return _cli("run", dataset, "--estimator", "gm", "--max-frames", 5, "--out", out, *extra)


def _warnings(caplog, logger: str) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.name == logger and r.levelno == logging.WARNING]


def _csv_lines(folder):
    return (folder / "camera.csv").read_text().splitlines()


def _set_csv_file(folder, line_no: int, file_text: str) -> None:
    lines = _csv_lines(folder)
    cols = lines[line_no - 1].split(",")
    cols[2] = file_text
    lines[line_no - 1] = ",".join(cols)
    (folder / "camera.csv").write_text("\n".join(lines) + "\n")


def _edit_npz(path, edit):
    arrays = dict(np.load(path))
    edit(arrays)
    np.savez(path, **arrays)


# 1. a log with no camera frame -------------------------------------------------------------------


def test_a_camera_csv_with_only_its_header_is_refused_naming_it(folder, tmp_path):
    (folder / "camera.csv").write_text(_csv_lines(folder)[0] + "\n")
    meta = yaml.safe_load((folder / "dataset.yaml").read_text())
    meta["counts"]["frames"] = 0
    (folder / "dataset.yaml").write_text(yaml.safe_dump(meta))
    _one_line_error(_run(folder, tmp_path / "out"), folder / "camera.csv", "holds no camera frame (only the header): a run needs at least one")
    assert not (tmp_path / "out").exists()


def test_degrade_refuses_faults_that_take_out_every_frame_before_writing(smoke_folder, tmp_path):
    r = _cli("degrade", smoke_folder, "--out", tmp_path / "deg", "--camera-gap", "-1:100")
    _one_line_error(r, "the camera gaps (-1:100 s) take out every camera frame of the log (0.000 to 2.480 s)")
    assert not (tmp_path / "deg").exists()


def test_faults_leaving_no_frame_of_a_log_in_memory_are_refused_and_nothing_is_left(smoke_log, tmp_path):
    with pytest.raises(FaultSequenceError, match=r"take out every camera frame of the log \(0.000 to 2.560 s\)"):
        write_faulty_dataset(smoke_log, Faults(camera_gaps=((-1.0, 100.0),)), tmp_path / "deg")
    assert not (tmp_path / "deg").exists()


def test_an_interval_outside_the_log_is_written_with_a_warning(smoke_folder, tmp_path, caplog):
    caplog.set_level(logging.WARNING)
    out = write_faulty_dataset(FolderSequence(smoke_folder), Faults(camera_gaps=((100.0, 200.0),), laser_gaps=((0.3, 0.5),)), tmp_path / "deg")
    assert _warnings(caplog, "dem_graph.datasets.faults") == [
        "camera gap 100:200 s holds no camera frame (the log's camera frames span 0.000 to 2.480 s): the fault changes nothing"
    ]
    written = FolderSequence(out)
    assert written.n_frames == 63 and written.n_scans < 31  # nothing skipped by the gap outside; the laser gap applied


# 2. a byte-order mark --------------------------------------------------------------------------


def test_a_camera_csv_with_a_utf8_byte_order_mark_opens(folder):
    text = (folder / "camera.csv").read_text()
    (folder / "camera.csv").write_text("\ufeff" + text, encoding="utf-8")
    sequence = FolderSequence(folder)
    assert sequence.n_frames == 63 and sequence.camera_times()[0] == 0.0


# 3. scans without a valid return ---------------------------------------------------------------


@pytest.mark.parametrize(
    "edit, why",
    [
        (lambda r: r.__setitem__(Ellipsis, np.nan), "every range is NaN (no return)"),
        (lambda r: r.__imul__(np.float32(1000.0)), "finite ranges lie beyond laser.range_max_m = 30 m"),
    ],
    ids=["all_nan", "in_mm"],
)
def test_scans_without_a_valid_return_are_said_on_open(folder, caplog, edit, why):
    _edit_npz(folder / "laser.npz", lambda z: edit(z["ranges_m"]))
    caplog.set_level(logging.WARNING)
    FolderSequence(folder)
    (warning,) = _warnings(caplog, "dem_graph.datasets.checks")
    assert warning.startswith(f"{folder / 'laser.npz'}: none of the 31 scans has a valid return: ")
    assert why in warning and warning.endswith("; no laser return is used, the map will hold only camera points")
    if "range_max_m" in why:
        assert "are they in millimetres, not metres?" in warning


def test_a_few_scans_beyond_range_are_no_fault(folder, caplog):
    _edit_npz(folder / "laser.npz", lambda z: z["ranges_m"].__setitem__((slice(None), slice(0, 20)), 65.0))
    caplog.set_level(logging.WARNING)
    FolderSequence(folder)
    assert not _warnings(caplog, "dem_graph.datasets.checks")


# 4. a frozen camera ----------------------------------------------------------------------------


def test_frames_repeating_the_one_before_are_marked_predicted_and_warned_once_per_stretch(folder, caplog):
    images = folder / "images"
    for k in (10, 11, 12):
        shutil.copyfile(images / "000009.png", images / f"{k:06d}.png")
    shutil.copyfile(images / "000030.png", images / "000031.png")
    caplog.set_level(logging.WARNING)
    frames = [e for e in FolderSequence(folder).events() if isinstance(e, CameraFrame)]
    assert [f.index for f in frames if f.textureless] == [10, 11, 12, 31]
    warnings = _warnings(caplog, "dem_graph.datasets.checks")
    assert len(warnings) == 2
    assert warnings[0].startswith(f"{images / '000010.png'}: frame 10 at 0.400 s is bit-identical to frame 9 (a frozen camera driver")
    assert warnings[0].endswith("not tracked, its pose predicted, until a frame that differs comes")
    assert warnings[1].startswith(f"{images / '000031.png'}: frame 31 at 1.240 s is bit-identical to frame 30")

    caplog.clear()
    run = run_estimator(FolderSequence(folder), RunConfig(estimator="gm", max_frames=16), with_dem=False)
    records = run.estimator.frames
    assert [r.n_tracked for r in records[10:13]] == [0, 0, 0]  # predicted only, as a frame without texture
    assert min(r.n_tracked for r in records[13:16]) > 0  # tracking resumes with the first frame that differs


# 5. a dataset given for a run folder -----------------------------------------------------------


@pytest.mark.parametrize("extra", [[], ["--at-s", "1.0"]], ids=["global", "live"])
def test_dem_on_a_dataset_folder_says_it_is_not_a_run_folder(smoke_folder, tmp_path, extra):
    r = _cli("dem", smoke_folder, "--out", tmp_path / "dem", *extra)
    _one_line_error(r, f"{smoke_folder}: not a run folder written by `dem-graph run` (no poses.npz)")


# 6. a live-maps file that is not one -----------------------------------------------------------


def test_a_live_maps_file_that_is_text_is_refused_in_one_line(gm_run, tmp_path):
    run = shutil.copytree(gm_run, tmp_path / "run")
    (run / "live_maps.nc").write_text("not netcdf\n")
    r = _cli("dem", run, "--at-s", "0.2", "--out", tmp_path / "dem")
    msg = _one_line_error(r, f"{run / 'live_maps.nc'}: not a NetCDF live-maps file")
    assert "pip" not in msg


# 7. graph options given to an EKF --------------------------------------------------------------


@pytest.mark.parametrize(
    "estimator, flag",
    [("ptpm", ["--lag-s", "3"]), ("gm", ["--graph-process"]), ("gm", ["--keyframe-every", "2"])],
    ids=["lag_ptpm", "graph_process_gm", "keyframe_every_gm"],
)
def test_a_graph_option_with_an_ekf_is_a_usage_error(smoke_folder, tmp_path, monkeypatch, estimator, flag):
    import dem_graph.pipeline.run as run_module

    monkeypatch.setattr(run_module, "run_dataset", lambda *a, **k: pytest.fail("the run started"))
    r = _cli("run", smoke_folder, "--estimator", estimator, "--out", tmp_path / "out", *flag)
    assert r.exit_code == 2
    (line,) = [x for x in r.stderr.splitlines() if x.startswith("Error:")]
    assert line == f"Error: {flag[0]}: used only by --estimator isam2 or isam2-batch, not by {estimator} (the run's estimator): leave it out or choose one of those"


def test_the_estimator_of_the_config_file_counts(smoke_folder, tmp_path, monkeypatch):
    import dem_graph.pipeline.run as run_module
    from dem_graph.errors import DemGraphError

    def reached(*args, **kwargs):
        raise DemGraphError("the run was reached")

    monkeypatch.setattr(run_module, "run_dataset", reached)
    config = tmp_path / "c.yaml"
    config.write_text("estimator: gm\n")
    r = _cli("run", smoke_folder, "--config", config, "--lag-s", "2", "--out", tmp_path / "out")
    assert r.exit_code == 2 and "--lag-s: used only by --estimator isam2 or isam2-batch, not by gm" in r.stderr
    config.write_text("estimator: isam2\n")
    _one_line_error(_cli("run", smoke_folder, "--config", config, "--lag-s", "2", "--out", tmp_path / "out"), "the run was reached")


# 8. dataset options the format does not read ---------------------------------------------------


@pytest.mark.parametrize(
    "option, flag, users",
    [
        (["--rig", "other.yaml"], "--rig", "rosbag"),
        (["--ring", "5"], "--ring", "kitti-odometry, kitti-raw"),
        (["--sequence", "04"], "--sequence", "kitti-odometry"),
        (["--camera", "2"], "--camera", "kitti-raw"),
    ],
    ids=["rig", "ring", "sequence", "camera"],
)
def test_an_option_the_folder_format_does_not_read_is_refused(smoke_folder, tmp_path, option, flag, users):
    r = _run(smoke_folder, tmp_path / "out", *option)
    _one_line_error(r, f"{smoke_folder}: {flag}: not used by the folder format (the format told from the path; give --format to choose another), only by {users}")


def test_kitti_and_rosbag_options_are_checked_for_their_own_format(tmp_path):
    with pytest.raises(DatasetError, match=r"--sequence: not used by the kitti-raw format, only by kitti-odometry"):
        check_options_used(tmp_path, "kitti-raw", DatasetOptions(sequence="04"))
    with pytest.raises(DatasetError, match=r"--image-topic, --scan-topic: not used by the kitti-odometry format"):
        open_dataset(tmp_path, "kitti-odometry", DatasetOptions(image_topic="/cam", scan_topic="/scan"))
    check_options_used(tmp_path, "rosbag", DatasetOptions(rig=tmp_path / "rig.yaml", image_topic="/cam", scan_topic="/scan"))


# 9. an image outside the dataset folder --------------------------------------------------------


@pytest.mark.parametrize("where", ["absolute", "dotdot"])
def test_an_image_path_leading_out_of_the_folder_is_refused(folder, smoke_folder, tmp_path, where):
    file_text = str(smoke_folder / "images" / "000005.png") if where == "absolute" else "../outside/000005.png"
    _set_csv_file(folder, 7, file_text)
    r = _run(folder, tmp_path / "out")
    _one_line_error(r, f"{folder / 'camera.csv'}: line 7: file {file_text!r} lies outside the dataset folder")


def test_an_absolute_image_path_inside_the_folder_opens(folder):
    _set_csv_file(folder, 7, str(folder / "images" / "000005.png"))
    _set_csv_file(folder, 8, "images/../images/000006.png")
    assert FolderSequence(folder).n_frames == 63


# 10. no laser-swept cell -----------------------------------------------------------------------


def test_a_dem_without_laser_swept_cells_prints_no_nan(folder, tmp_path):
    _edit_npz(folder / "laser.npz", lambda z: z["ranges_m"].__setitem__(Ellipsis, np.nan))
    r = _cli("run", folder, "--estimator", "gm", "--max-frames", 10, "--out", tmp_path / "out")
    assert r.exit_code == 0, r.stderr
    assert "no laser-swept cell (no height RMSE)" in r.output and "nan cm" not in r.output
    nan = float("nan")
    assert laser_cells_error_text(HeightErrors(cells=0, rmse_m=nan, mean_m=nan, std_m=nan, p95_abs_m=nan, max_abs_m=nan)) == "no laser-swept cell (no height RMSE)"


# 11. a field in a tagged union -----------------------------------------------------------------


def test_a_beam_field_is_named_as_in_the_rig_file(folder, tmp_path):
    rig = yaml.safe_load((folder / "rig.yaml").read_text())
    rig["laser"]["beams"]["count"] = 0
    (folder / "rig.yaml").write_text(yaml.safe_dump(rig))
    msg = _one_line_error(_run(folder, tmp_path / "out"), f"{folder / 'rig.yaml'}: laser.beams.count: Input should be greater than 0")
    assert "planar" not in msg


# 12. a resolution that is not a number ---------------------------------------------------------


@pytest.mark.parametrize("value", ["nan", "inf"])
def test_a_dem_resolution_that_is_not_a_number_is_said_so(gm_run, tmp_path, value):
    r = _cli("dem", gm_run, "--resolution-m", value, "--out", tmp_path / "dem")
    _one_line_error(r, "invalid DEM resolution: resolution_m: Input should be a finite number")
