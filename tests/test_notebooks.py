"""The notebooks in notebooks/, executed top to bottom in a small configuration.

The cell tagged ``parameters`` is replaced by a small configuration (the `smoke` scenario, a few
frames) writing into a temporary folder; the kernel starts in the repository's root, so that the
package imported is this checkout's. A cell added at the end records the kernel's Python and the
package's file, to check both.
"""

from __future__ import annotations

import csv
import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest

nbformat = pytest.importorskip("nbformat", reason="executing the notebooks needs nbformat (pip install -e '.[dev]')")
nbclient = pytest.importorskip("nbclient", reason="executing the notebooks needs nbclient (pip install -e '.[dev]')")
pytest.importorskip("ipykernel", reason="executing the notebooks needs ipykernel (pip install -e '.[dev]')")

ROOT = Path(__file__).resolve().parents[1]
NOTEBOOKS = ROOT / "notebooks"
pytestmark = pytest.mark.slow


def _execute(name: str, parameters: str, out_dir: Path) -> dict:
    """Run the notebook with ``parameters`` in place of its parameters cell; return what the kernel
    reported about itself (its Python, the package's file)."""
    nb = nbformat.read(NOTEBOOKS / name, as_version=4)
    cells = [c for c in nb.cells if "parameters" in c.metadata.get("tags", [])]
    assert len(cells) == 1, "one cell tagged 'parameters'"
    assert all(c.cell_type != "code" or not c.get("outputs") for c in nb.cells), "notebooks are committed without outputs"
    cells[0].source = parameters
    probe = out_dir / "kernel.json"
    nb.cells.append(nbformat.v4.new_code_cell(
        f"import json, sys, dem_graph\nopen({str(probe)!r}, 'w').write(json.dumps({{'python': sys.executable, 'package': dem_graph.__file__}}))"
    ))
    client = nbclient.NotebookClient(nb, kernel_name="python3", timeout=300, resources={"metadata": {"path": str(ROOT)}})
    client.execute()
    return json.loads(probe.read_text())


def _check_kernel(kernel: dict) -> None:
    assert Path(kernel["python"]).resolve() == Path(sys.executable).resolve()
    assert Path(kernel["package"]).resolve() == ROOT / "dem_graph" / "__init__.py"


def test_paper_figures_notebook_draws_figs_8_10_11_12(tmp_path):
    estimators = ("gm", "ptpm", "isam2", "isam2-batch")
    points = (30, 60)
    parameters = "\n".join([
        'SCENARIO = "smoke"', "SEED = 5", "LENGTH_M = 1.0", "MAX_FRAMES = 12", f"ESTIMATORS = {estimators!r}",
        f"POINTS = {points!r}", 'BENCH_ESTIMATORS = ("gm", "ptpm")', "BENCH_FRAMES = 15", f"OUT_DIR = {str(tmp_path)!r}",
    ])
    _check_kernel(_execute("paper_figures.ipynb", parameters, tmp_path))
    figures = tmp_path / "compare" / "figures"
    for png in (figures / "trajectories.png", figures / "position_error.png", figures / "local_dem_error.png", tmp_path / "fig12_time_per_frame.png"):
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", png
    summary = json.loads((tmp_path / "compare" / "summary.json").read_text())
    assert summary["estimators"] == list(estimators) and summary["max_frames"] == 12
    for name in estimators:
        entry = summary["runs"][name]
        assert entry["status"] == "ok"
        # one row per estimator, with a finite, positive ATE (the smoke log drives 1 m: well under a metre of error)
        assert 0.0 < entry["headline"]["ate_anchored_rmse_m"] < 1.0


def test_estimator_study_notebook_table_figure_and_conclusion(tmp_path):
    estimators = ("gm", "ptpm", "isam2", "isam2-batch")
    seeds, speeds, budgets = (1, 2), (2.0,), (60,)
    parameters = "\n".join([
        'SCENARIO = "smoke"', f"SEEDS = {seeds!r}", f"SPEEDS_MPS = {speeds!r}", f"POINT_BUDGETS = {budgets!r}",
        f"ESTIMATORS = {estimators!r}", "LENGTH_M = 1.0", "MAX_FRAMES = 10", f"OUT_DIR = {str(tmp_path)!r}",
    ])
    _check_kernel(_execute("estimator_study.ipynb", parameters, tmp_path))
    with (tmp_path / "study.csv").open() as f:
        rows = list(csv.DictReader(f))
    # one row per estimator x seed x speed x budget, each with a finite ATE and time per frame
    expected = {(e, str(s), str(v), str(n)) for e in estimators for s in seeds for v in speeds for n in budgets}
    assert len(rows) == len(expected)
    assert {(r["estimator"], r["seed"], r["speed_mps"], r["max_points"]) for r in rows} == expected
    for r in rows:
        assert r["status"] == "ok"
        assert 0.0 < float(r["ate_m"]) < 1.0 and math.isfinite(float(r["frame_ms_median"])) and float(r["frame_ms_median"]) > 0.0
    # each seed and speed was simulated at its speed: the dataset's scenario says so
    for s in seeds:
        scenario_yaml = (tmp_path / "data" / f"smoke_seed{s}_2mps_1m" / "scenario.yaml").read_text()  # the drive shortened to 1 m: in the name
        assert "speed_mps: 2.0" in scenario_yaml and f"seed: {s}" in scenario_yaml
    assert (tmp_path / "accuracy_cost.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # the conclusion names the estimator with the lowest mean ATE of the table, and that mean
    mean_ate = {e: sum(float(r["ate_m"]) for r in rows if r["estimator"] == e) / len(seeds) for e in estimators}
    best = min(mean_ate, key=mean_ate.get)
    conclusion = (tmp_path / "conclusion.md").read_text()
    assert f"{best} had the lowest mean ATE, {mean_ate[best]:.3f} m over {len(seeds)} runs" in conclusion


def test_getting_started_notebook_runs_in_its_own_configuration_against_the_truth(tmp_path):
    """The getting-started notebook as a newcomer runs it (its own parameters, only the folder
    changed): the ATE it reports is the one the run folder's trajectory gives against the
    simulator's true trajectory (1e-9 m), small on this 4 m drive, and its DEM and live map errors are
    within bounds against the true terrain."""
    from dem_graph import open_dataset
    from dem_graph.io.tum import read_tum

    nb = nbformat.read(NOTEBOOKS / "getting_started.ipynb", as_version=4)
    own = next(c for c in nb.cells if "parameters" in c.metadata.get("tags", []))
    parameters = own.source.replace('OUT_DIR = "out/getting_started"', f"OUT_DIR = {str(tmp_path)!r}")
    assert parameters != own.source and "ESTIMATORS = (\"ptpm\", \"isam2\")" in parameters
    _check_kernel(_execute("getting_started.ipynb", parameters, tmp_path))
    summary = json.loads((tmp_path / "summary.json").read_text())
    truth = open_dataset(tmp_path / "dataset").ground_truth.trajectory
    for name in ("ptpm", "isam2"):
        # the notebook's ATE, again from the files: the run's trajectory against the true one at the same times
        estimate = read_tum(tmp_path / name / "trajectory.tum")
        error_m = np.linalg.norm(estimate.positions_xyz - truth.at(estimate.t_s)[:, :3, 3], axis=1)
        assert summary["ate_m"][name] == pytest.approx(float(np.sqrt(np.mean(error_m**2))), abs=1e-9)
        # and the run's own metrics agree to the TUM file's rounding
        metrics = json.loads((tmp_path / name / "metrics.json").read_text())
        assert summary["ate_m"][name] == pytest.approx(metrics["trajectory"]["ate_rmse_m"], abs=1e-6)
        assert summary["dem_rmse_m"][name] == pytest.approx(metrics["dem"]["height_error_laser_cells"]["rmse_m"], abs=1e-6)
        # on the 4 m smoke drive both estimators stay within 2 cm of the truth (measured 4 mm) and map within 2 cm (measured 1 cm)
        assert 0.0 < summary["ate_m"][name] < 0.02
        assert 0.0 < summary["dem_rmse_m"][name] < 0.02
    # the live map at 2 s: cells ahead known, within 3 cm of the terrain under them
    live = summary["live"]
    assert live["t_s"] == pytest.approx(2.0, abs=0.05) and live["cells"] > 50
    assert 0.0 < live["rmse_m"] < 0.03
