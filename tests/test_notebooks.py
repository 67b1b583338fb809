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
