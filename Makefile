# Two commands do everything on a fresh Debian/Ubuntu machine with Python >= 3.10:
#   make demo   set up, simulate the default scenario (dataset + picture), compare GM, PTPM, iSAM2 and iSAM2-batch on it (after the odometry alone)
#               (one table, run folders and a report under out/demo/compare/)
#   make test   set up, check the import layers (pyproject.toml), build the docs site (mkdocs build --strict:
#               a broken link or a stale API reference fails), then run the test suite (three workers,
#               pytest-xdist, a test file's tests on one worker so that its fixtures are made once, the
#               heaviest files first (tests/conftest.py); docs/benchmarks.md has the suite's time;
#               tests/test_docs_snippets.py runs the README's and the docs' Python snippets)
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
OUT ?= out

.PHONY: demo test bench setup system-deps clean

demo: setup
	$(BIN)/dem-graph simulate --scenario demo --out $(OUT)/demo/dataset --overwrite
	$(BIN)/dem-graph compare $(OUT)/demo/dataset --out $(OUT)/demo/compare

# the tests start many Python processes (the graph's, the CLI's, notebook kernels): let them keep the
# package's compiled bytecode rather than compile it again each time (0.1-0.3 s a process here)
test: export PYTHONDONTWRITEBYTECODE =
test: setup
	$(BIN)/lint-imports --no-logo
	NO_MKDOCS_2_WARNING=1 $(BIN)/mkdocs build --strict --quiet --site-dir $(OUT)/site
	$(BIN)/python -m pytest -q -n 3 --dist loadfile --no-loadscope-reorder

bench: setup
	$(BIN)/dem-graph research bench-sim
	$(BIN)/dem-graph research bench

setup: $(VENV)/.installed

# open3d needs the system library libusb-1.0 at import time
system-deps:
	@if ! { ldconfig -p || /sbin/ldconfig -p; } 2>/dev/null | grep -q 'libusb-1.0.so.0'; then \
		echo "installing libusb-1.0-0 (needed by open3d)"; \
		SUDO=""; [ "$$(id -u)" -ne 0 ] && SUDO="sudo"; \
		$$SUDO apt-get update -qq && $$SUDO apt-get install -y -qq libusb-1.0-0; \
	fi

$(VENV)/.installed: pyproject.toml | system-deps
	@$(PYTHON) -c 'import sys; sys.exit(0 if sys.version_info >= (3, 10) else "dem_graph needs Python >= 3.10")'
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip uv
	@# uv installs the same versions as pip, its downloads in parallel: 14 s against 117 s in a new venv here
	$(BIN)/uv pip install -q --python $(BIN)/python -e '.[dev,docs]'
	@touch $@

clean:
	rm -rf $(VENV) $(OUT) .pytest_cache site
