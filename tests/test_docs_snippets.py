"""The README's and the docs' Python snippets run, and say what they claim.

Every ```python block of README.md and docs/**/*.md runs, the blocks of one page in order and in
one namespace (a later block may use an earlier one's names), in a temporary working folder. A
block preceded by the line ``<!-- no-test: why -->`` is skipped (a 100 m log, a vehicle's
drivers). Where a block computes something, ``CHECKS`` asserts it against the known value. The
README's relative links must point at files that exist (the docs' own links are checked by
``mkdocs build --strict`` in ``make test``).
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
FENCE = re.compile(r"^```python[^\n]*\n(.*?)^```", re.MULTILINE | re.DOTALL)
NO_TEST = re.compile(r"<!--\s*no-test\b[^>]*-->\s*$")


def python_blocks(page: Path) -> list[tuple[int, str, bool]]:
    """The page's python blocks: (line, code, skipped)."""
    text = page.read_text()
    blocks = []
    for m in FENCE.finditer(text):
        before = text[: m.start()].rstrip("\n").rsplit("\n", 1)[-1]
        blocks.append((text.count("\n", 0, m.start()) + 1, m.group(1), bool(NO_TEST.search(before))))
    return blocks


def _check_readme(ns: dict, out: str) -> None:
    run, live = ns["run"], ns["live"]
    assert run.error is None
    assert 0.0 < run.metrics.trajectory.ate_rmse_m < 0.01  # PTPM over 1 m of `smoke`: about 2 mm
    assert 0.0 < run.metrics.dem.height_error_laser_cells.rmse_m < 0.03  # about 1 cm
    assert "ATE 0.00" in out and " cm" in out
    local = live.latest.local.layers["elevation"]
    assert local.ndim == 2 and np.isfinite(local).any()
    assert Path("out/tiny_ptpm/dem.tif").is_file() and Path("out/tiny_ptpm/trajectory.tum").is_file()


def _check_getting_started(ns: dict, out: str) -> None:
    run, again = ns["run"], ns["again"]
    assert run.error is None and run.metrics.trajectory.ate_rmse_m < 0.02
    assert again.metrics.trajectory.ate_rmse_m == pytest.approx(run.metrics.trajectory.ate_rmse_m, abs=1e-6)
    assert {"trajectory", "metrics", "dem_tif"} <= set(run.paths)


def _check_frames(ns: dict, out: str) -> None:
    rig = ns["rig"]
    assert out.splitlines()[0] == "800 600 25.0 361"
    assert rig.T_cam_laser.shape == (4, 4)
    np.testing.assert_allclose(rig.T_cam_laser[3], [0, 0, 0, 1])


# page (relative to the repository) -> a check of its namespace and printed output after its blocks ran
CHECKS = {
    "README.md": _check_readme,
    "docs/getting_started.md": _check_getting_started,
    "docs/concepts/frames.md": _check_frames,
}

RUNNABLE = [p for p in PAGES if any(not skip for _, _, skip in python_blocks(p))]


def test_the_checked_pages_have_their_snippets():
    assert set(CHECKS) <= {str(p.relative_to(ROOT)) for p in RUNNABLE}


@pytest.mark.parametrize("page", RUNNABLE, ids=lambda p: str(p.relative_to(ROOT)))
def test_snippets_run(page, tmp_path, capsys):
    here = os.getcwd()
    os.chdir(tmp_path)
    namespace: dict = {"__name__": "__snippet__"}
    try:
        for line, code, skipped in python_blocks(page):
            if not skipped:
                exec(compile(code, f"{page.relative_to(ROOT)}:{line}", "exec"), namespace)
        out = capsys.readouterr().out
        check = CHECKS.get(str(page.relative_to(ROOT)))
        if check is not None:
            check(namespace, out)
    finally:
        os.chdir(here)


def test_skipped_snippets_say_why():
    for page in PAGES:
        for line, _, skipped in python_blocks(page):
            if skipped:
                text = page.read_text().splitlines()[line - 2]
                assert re.search(r"no-test:\s*\S", text), f"{page}:{line}: say why the snippet does not run"


def test_the_readme_links_point_at_files():
    text = (ROOT / "README.md").read_text()
    targets = re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", text)
    missing = [t for t in targets if "://" not in t and not (ROOT / t).exists()]
    assert targets and not missing, missing


def test_the_package_exports_what_a_notebook_needs():
    import dem_graph

    names = {"run_dataset", "open_dataset", "LivePipeline", "load_rig", "RunOverrides", "RunConfig", "scenario", "simulate", "evaluate_run"}
    assert set(dem_graph._EXPORTS) == set(dem_graph.__all__) - {
        "ConfigError",
        "DatasetError",
        "DemGraphError",
        "MissingDependencyError",
        "__version__",
    }
    assert names <= set(dem_graph.__all__)
    from dem_graph.pipeline.run import run_dataset

    assert dem_graph.run_dataset is run_dataset  # the function `dem-graph run` calls, not a copy
