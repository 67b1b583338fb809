"""Nothing lost, no traceback: the run folder written as the run goes, Ctrl-C and SIGTERM keeping the
work, an earlier run never mixed with a new one, partial ground truth and bad output folders."""

from __future__ import annotations

import logging
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
from click.testing import CliRunner

from dem_graph.cli import main
from dem_graph.datasets.base import GroundTruth
from dem_graph.datasets.folder import FolderSequence
from dem_graph.datasets.memory import InMemorySequence
from dem_graph.dem.fusion import FusionConfig, covering_geometry
from dem_graph.dem.returns import GroundReturns
from dem_graph.errors import DatasetError, DemGraphError
from dem_graph.estimators.isam2 import ONLINE_PASS_ONLY
from dem_graph.evaluation.trajectory_metrics import accuracy_summary
from dem_graph.io.ply import read_points_ply
from dem_graph.io.tum import read_tum
from dem_graph.pipeline import RunConfig, run_estimator
from dem_graph.pipeline.run import run_dataset
from dem_graph.pipeline.run_folder import prepare_run_folder, read_run_metrics


@pytest.fixture(scope="module")
def full_run(smoke_folder, tmp_path_factory):
    """An uninterrupted PTPM run of the smoke folder: the truth an interrupted one is held to."""
    out = tmp_path_factory.mktemp("full") / "run"
    return run_dataset(smoke_folder, out_dir=out), out


# --- the output folder ---------------------------------------------------------------------------


def test_an_earlier_run_is_refused_without_overwrite_and_emptied_with_it(full_run, tmp_path):
    import shutil

    _, out = full_run
    folder = tmp_path / "run"
    shutil.copytree(out, folder)
    with pytest.raises(DatasetError, match=r"holds an earlier run \(.*metrics.json.*\): give --overwrite"):
        prepare_run_folder(folder)
    (folder / "dem_at_1").mkdir()
    prepare_run_folder(folder, overwrite=True)
    assert list(folder.iterdir()) == []  # no file of the earlier run can pass for the new one's


def test_a_folder_of_other_files_is_never_emptied(tmp_path):
    (tmp_path / "thesis.tex").write_text("precious")
    with pytest.raises(DatasetError, match="not a run's"):
        prepare_run_folder(tmp_path, overwrite=True)
    assert (tmp_path / "thesis.tex").read_text() == "precious"


def test_an_unwritable_out_is_refused_before_estimating(smoke_folder, tmp_path, monkeypatch):
    import dem_graph.pipeline.run as run_module

    def no_estimating(*args, **kwargs):
        raise AssertionError("the estimator was run before the run folder was checked")

    monkeypatch.setattr(run_module, "run_estimator", no_estimating)
    blocker = tmp_path / "file"
    blocker.write_text("")
    r = CliRunner().invoke(main, ["--no-progress", "run", str(smoke_folder), "--estimator", "gm", "--out", str(blocker / "run")])
    assert r.exit_code == 2 and r.stderr.count("\n") == 1
    assert "cannot write the run folder here" in r.stderr and str(blocker) in r.stderr


def test_the_cli_refuses_an_earlier_run_and_replaces_it_with_overwrite(full_run, tmp_path, smoke_folder):
    import shutil

    _, out = full_run
    folder = tmp_path / "run"
    shutil.copytree(out, folder)
    args = ["--no-progress", "run", str(smoke_folder), "--estimator", "gm", "--max-frames", "5", "--out", str(folder)]
    r = CliRunner().invoke(main, args)
    assert r.exit_code == 2 and "give --overwrite" in r.stderr
    r = CliRunner().invoke(main, [*args, "--overwrite"])
    assert r.exit_code == 0
    m = read_run_metrics(folder)
    assert m["estimator"] == "ekf-gm" and m["frames"] == 5
    assert len(read_tum(folder / "trajectory.tum").t_s) == 5


# --- written as the run goes -----------------------------------------------------------------------


def test_the_checkpoint_holds_every_frame_so_far(smoke_folder, tmp_path, full_run):
    run, _ = full_run
    out = tmp_path / "run"
    out.mkdir()
    part = run_estimator(
        FolderSequence(smoke_folder),
        RunConfig(estimator="ptpm", max_frames=30, checkpoint_every_s=1e-6),
        with_dem=False,
        checkpoint_dir=out,
    )
    saved = read_tum(out / "trajectory.tum")
    # the last checkpoint was written at the last frame: the same poses as the run's, and as the
    # uninterrupted run's first frames (the EKF does not revise a frame once output). The 30th
    # differs: a cut run ends without the odometry after its last frame, which that frame waits for
    np.testing.assert_allclose(saved.positions_xyz, part.estimator.trajectory().positions_xyz, atol=1e-12)
    np.testing.assert_allclose(saved.positions_xyz[:29], run.estimator.trajectory().positions_xyz[:29], atol=1e-12)
    xyz, attributes = read_points_ply(out / "points.ply")
    assert len(xyz) > 0 and set(attributes) >= {"var_z_m2", "created_t_s"} and np.all(attributes["created_t_s"] <= saved.t_s[-1])


def _start(args, tmp_path):
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    return subprocess.Popen(
        [sys.executable, "-m", "dem_graph.cli", "--no-progress", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
        cwd=tmp_path,
    )


@pytest.mark.skipif(sys.platform == "win32", reason="POSIX signals")
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_a_signal_ends_the_run_between_frames_and_keeps_it(smoke_folder, tmp_path, full_run, sig):
    run, _ = full_run
    out = tmp_path / "run"
    (tmp_path / "checkpoints.yaml").write_text("checkpoint_every_s: 0.2\n")
    p = _start(["run", str(smoke_folder), "--estimator", "ptpm", "--realtime", "--config", str(tmp_path / "checkpoints.yaml"), "--out", str(out)], tmp_path)
    deadline = time.monotonic() + 60
    while not (out / "trajectory.tum").is_file() and time.monotonic() < deadline:  # the first checkpoint: frames are being estimated
        time.sleep(0.05)
    time.sleep(0.5)  # about 12 frames more of the 64, fed at the camera's rate
    p.send_signal(sig)
    stdout, stderr = p.communicate(timeout=60)
    assert "Traceback" not in stderr
    assert p.returncode == 130 and stderr.strip().splitlines()[-1].startswith("dem-graph: error: interrupted after")
    m = read_run_metrics(out)
    n = m["frames"]
    assert 1 <= n < 64 and m["error"].startswith("interrupted")  # stopped part-way (how far depends on the machine's load)
    saved = read_tum(out / "trajectory.tum")  # the frames done, exactly as an uninterrupted run made them
    np.testing.assert_allclose(saved.positions_xyz, run.estimator.trajectory().positions_xyz[:n], atol=1e-9)
    assert (out / "dem.tif").is_file() and (out / "live_map.tif").is_file()


@pytest.mark.skipif(sys.platform == "win32", reason="POSIX signals")
def test_a_signal_while_the_estimator_starts_stops_the_run_before_its_first_frame(smoke_log):
    """A SIGTERM while the estimator is being made (its kernels loaded, a graph process started: a
    second or more) stops the run at its first event, said so, instead of killing the process."""
    run = run_estimator(smoke_log, RunConfig(estimator="ptpm"), with_dem=False, instrument=lambda _: os.kill(os.getpid(), signal.SIGTERM))
    assert run.interrupted and run.error == "interrupted after 0 frames (SIGTERM)" and len(run.estimator.frames) == 0
    assert signal.getsignal(signal.SIGTERM) is signal.SIG_DFL  # the handler the process had is back


def test_an_isam2_batch_stopped_early_says_it_is_the_online_pass(smoke_log):
    class Stops(InMemorySequence):
        def events(self):
            for k, event in enumerate(super().events()):
                if k == 60:
                    raise DatasetError("camera.csv", "line 61: corrupt (a test)")
                yield event

    log = Stops(smoke_log.rig, list(smoke_log.events()), smoke_log.T_world_body_initial, smoke_log.t_start_s, smoke_log.ground_truth)
    run = run_estimator(log, RunConfig(estimator="isam2-batch"), with_dem=False)
    assert run.error is not None and run.estimator.frames
    assert run.metrics.estimator == ONLINE_PASS_ONLY


# --- ground truth over part of the run, and another dataset's truth --------------------------------


def test_truth_over_half_the_run_gives_metrics_over_that_half(smoke_log, caplog):
    gt = smoke_log.ground_truth
    t_half = gt.trajectory.t_s[len(gt.trajectory.t_s) // 2]
    half = GroundTruth(gt.trajectory.slice(gt.trajectory.t_s[0], t_half), gt.elevation)
    log = InMemorySequence(smoke_log.rig, list(smoke_log.events()), smoke_log.T_world_body_initial, smoke_log.t_start_s, half)
    with caplog.at_level(logging.WARNING):
        run = run_estimator(log, RunConfig(estimator="ptpm"), with_dem=False)
    assert run.error is None and any("covers" in r.message and "trajectory metrics are over those" in r.message for r in caplog.records)
    est = run.estimator.trajectory()
    expected = accuracy_summary(est.slice(-np.inf, t_half), half.trajectory)
    assert run.metrics.trajectory.ate_rmse_m == pytest.approx(expected.ate_rmse_m, rel=1e-12)
    assert run.metrics.trajectory.n_poses == int(np.sum(est.t_s <= t_half))


def test_evaluating_against_another_dataset_warns(full_run, tiny_folder, caplog):
    from dem_graph.studies.evaluate import evaluate_run

    _, out = full_run
    with caplog.at_level(logging.WARNING):
        evaluate_run(out, tiny_folder, with_dem=False)
    assert any("was made from" in r.message and "another dataset's truth" in r.message for r in caplog.records)


# --- a DEM grid too large to allocate ---------------------------------------------------------------


def test_a_grid_beyond_max_cells_is_refused_before_allocation():
    xyz = np.array([[0.0, 0.0, 0.0], [2000.0, 1000.0, 0.0]])
    returns = GroundReturns(xyz, np.full(2, 1e-4), np.zeros(2), np.zeros(2, dtype=np.uint8))
    with pytest.raises(
        DemGraphError, match=r"2001.0 x 1001.0 m in cells of 0.01 m would have 2e\+10 cells, more than dem.fusion.max_cells"
    ):
        covering_geometry(returns, FusionConfig(resolution_m=0.01))
    g = covering_geometry(returns, FusionConfig(resolution_m=1.0))  # the same extent at 1 m: 2e6 cells
    assert (g.n_rows, g.n_cols) == (1002, 2002)  # edges on whole metres, 0.5 m of margin


# --- frames without texture ----------------------------------------------------------------------


@pytest.mark.parametrize("estimator", ["ptpm", "isam2"])
def test_frames_without_texture_are_predicted_and_lose_no_point(smoke_log, estimator):
    import dataclasses

    from dem_graph.datasets.events import CameraFrame

    frames = [e for e in smoke_log.events() if isinstance(e, CameraFrame)]
    dark = {f.t_s for f in frames[20:30]}  # 0.4 s of black frames, as the reader marks them
    events = [dataclasses.replace(e, image=np.zeros_like(e.image), textureless=True) if isinstance(e, CameraFrame) and e.t_s in dark else e for e in smoke_log.events()]
    run = run_estimator(smoke_log.replace_events(events), RunConfig(estimator=estimator), with_dem=False)
    records = run.estimator.frames
    gap = [r for r in records if r.t_s in dark]
    assert len(gap) == 10 and all(r.n_tracked == 0 for r in gap)
    assert len({r.n_live for r in gap}) == 1  # no point lost or started in the dark
    after = [r for r in records if r.t_s > max(dark)][:3]
    assert max(r.n_tracked for r in after) > 0.5 * gap[0].n_live  # tracking resumes when the texture returns
