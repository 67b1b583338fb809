"""Studies on Dask (studies/grid.py, studies/study.py): the same rows as in series, a failed run
reported while the others go on, and a study started again keeping what is done."""

from __future__ import annotations

import json
import logging
from dataclasses import replace

import pytest

from dem_graph.errors import DemGraphError
from dem_graph.studies.grid import GridJob, JobFailure, run_grid
from dem_graph.studies.study import estimator_study, run_job

GRID = dict(scenario_name="smoke", seeds=(3, 4), speeds_mps=(1.5,), estimators=("ptpm", "isam2"), max_frames=15, length_m=1.2)


def _accuracy(rows):
    """The rows without their timings (which depend on the machine's load, not on the engine)."""
    return [replace(r, frame_ms_median=0.0, frame_ms_p95=0.0) for r in rows]


@pytest.fixture(scope="module")
def serial_study(tmp_path_factory):
    """The study in series in a folder of its own, and its rows: the tests below read the folder and
    leave it as it is (one copies it to start the study again)."""
    folder = tmp_path_factory.mktemp("serial")
    return folder, estimator_study(folder, scheduler="serial", **GRID).rows


@pytest.fixture(scope="module")
def serial_rows(serial_study):
    return serial_study[1]


def test_a_local_cluster_of_two_workers_gives_the_serial_rows(tmp_path, serial_rows):
    rows = estimator_study(tmp_path, scheduler="local", n_workers=2, **GRID).rows
    assert len(rows) == 4 and all(r.status == "ok" for r in rows)
    assert _accuracy(rows) == _accuracy(serial_rows)  # ATE, drift, live points: equal to the bit


def test_a_study_started_again_keeps_what_is_done(tmp_path, serial_study, monkeypatch):
    import shutil

    # the study in series, as it was left (a copy of the fixture's folder: the same study, made once)
    folder, first = serial_study
    shutil.copytree(folder, tmp_path, dirs_exist_ok=True, symlinks=True)
    results = sorted(p.name for p in (tmp_path / "study_results").iterdir())
    assert len(results) == 6  # two datasets simulated, four runs
    # one run's result lost (a study stopped part way): only that run is made again
    (tmp_path / "study_results" / "run_smoke_seed4_1.5mps_1.2m_isam2_default_f15.json").unlink()
    ran = []
    import dem_graph.studies.study as study

    real = study.run_job
    monkeypatch.setattr(study, "run_job", lambda *a: ran.append(a[1:3]) or real(*a))
    again = estimator_study(tmp_path, scheduler="serial", **GRID).rows
    assert ran == [("isam2", 4)]
    assert again[:3] == first[:3]  # the kept rows come back as they were, timings included
    assert _accuracy(again) == _accuracy(first)  # and the one made again gives the same accuracy


def test_a_failed_job_is_reported_and_the_others_go_on(tmp_path, caplog):
    jobs = [
        GridJob("good", run_job, (str(tmp_path / "nowhere"), "ptpm", 1, 1.5, 140, 5)),
    ]
    with caplog.at_level(logging.ERROR):
        out = run_grid(jobs + [GridJob("sum", sum, ([1, 2],))], tmp_path / "results", scheduler="serial")
    assert isinstance(out["good"], JobFailure) and "DatasetError" in out["good"].error and "nowhere" in out["good"].error
    assert out["sum"] == 3 and json.loads((tmp_path / "results" / "sum.json").read_text()) == 3
    assert not (tmp_path / "results" / "good.json").exists()  # a failure is not kept: it runs again next time
    assert any("job good failed" in r.getMessage() for r in caplog.records)


def test_a_scheduler_that_does_not_answer_is_one_line(monkeypatch):
    import dem_graph.studies.grid as grid

    monkeypatch.setattr(grid, "CONNECT_TIMEOUT_S", 2.0)
    with pytest.raises(DemGraphError, match=r"no Dask scheduler answers at tcp://127.0.0.1:1 "):
        run_grid([GridJob("x", sum, ([1],))], None, scheduler="tcp://127.0.0.1:1")
