"""The package's layers (pyproject.toml, [tool.importlinter]): kept by the code, and broken by an
import that runs up a layer."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
LINT = Path(sys.executable).with_name("lint-imports")

pytestmark = pytest.mark.skipif(not LINT.exists(), reason="import-linter is not installed (pip install -e '.[dev]')")


def _lint(root: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(root)}
    return subprocess.run([str(LINT), "--no-logo", "--no-cache", str(root / "pyproject.toml")], cwd=root, env=env, capture_output=True, text=True, timeout=120)


def test_the_package_keeps_its_layers():
    out = _lint(ROOT)
    assert out.returncode == 0, out.stdout + out.stderr
    assert "2 kept, 0 broken" in out.stdout


def test_an_import_up_a_layer_breaks_the_contract(tmp_path):
    shutil.copytree(ROOT / "dem_graph", tmp_path / "dem_graph", ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copy(ROOT / "pyproject.toml", tmp_path / "pyproject.toml")
    views = tmp_path / "dem_graph" / "dem" / "views.py"
    views.write_text(views.read_text() + "\nfrom dem_graph.pipeline import run_config  # noqa: E402 - the deliberate violation\n")
    out = _lint(tmp_path)
    assert out.returncode != 0
    assert "dem_graph.dem is not allowed to import dem_graph.pipeline" in out.stdout
    assert "0 kept, 2 broken" in out.stdout
