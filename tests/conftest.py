"""Shared fixtures: small simulated logs recorded once per test session."""

from __future__ import annotations

import os
import pickle
from pathlib import Path

import cv2  # noqa: F401 - (its BLAS loaded before the limit below)
import pytest
import scipy.linalg  # noqa: F401 - (its BLAS loaded before the limit below)
from threadpoolctl import threadpool_limits

from dem_graph.datasets.memory import InMemorySequence
from dem_graph.progress import set_progress_enabled
from dem_graph.sim.scenarios import scenario
from dem_graph.sim.simulator import SimulatedSequence

set_progress_enabled(False)

# One BLAS thread in each test process. The suite runs three processes on two cores (`make test`), and
# OpenBLAS's threads, waiting busily for work, took the cores from the other processes: the calibration
# tests used 2.5 times the CPU with two threads as with one, for the same numbers. A run limits BLAS to
# its own `blas_threads` (1) while its estimator works; this is for the rest (simulation, calibration).
_ONE_BLAS_THREAD = threadpool_limits(limits=1, user_api="blas")


@pytest.fixture(scope="session", autouse=True)
def _one_blas_thread_in_child_processes():
    """The processes the tests start (`dem-graph` commands, graph processes, notebook kernels) get the
    same limit. Set here, in the process that runs the tests (an xdist worker, not the controller that
    starts the workers: the workers keep the machine's default, which tests/test_run_threads.py reads)."""
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    yield


@pytest.fixture(autouse=True)
def _machine_blas_threads_for_test_run_threads(request):
    """tests/test_run_threads.py checks that a run sets BLAS to its `blas_threads` and gives the
    machine's threads back after: it runs with the machine's default, as without the limit above."""
    if request.node.path.name != "test_run_threads.py":
        yield
        return
    _ONE_BLAS_THREAD.restore_original_limits()
    try:
        yield
    finally:
        threadpool_limits(limits=1, user_api="blas")


# The heavier files and their seconds in `make test` (the sum of a file's --durations there, on the 2-core
# machine it was timed on). The files run heaviest first: `make test` hands each xdist worker a whole
# file (--dist loadfile, so that its module fixtures are made once) in the order collected
# (--no-loadscope-reorder), and a heavy file handed out late kept one worker busy long after the others
# had finished. Only the order changes: every test runs, and a file's tests keep their order. A file not
# listed takes less than 8 s; the figures need only be roughly right.
FILE_COST_S = {
    "test_graph_worker.py": 96,
    "test_ros2_faults.py": 80,  # three runs of the node over DDS (alone: 70 s)
    "test_isam2.py": 62,
    "test_notebooks.py": 48,
    "test_calibration_robust.py": 40,
    "test_kitti_shared.py": 39,
    "test_study_grid.py": 37,
    "test_ablation.py": 34,
    "test_ros2_node.py": 30,
    "test_run_robustness.py": 29,
    "test_live_pipeline.py": 26,
    "test_ekf_imu.py": 24,
    "test_calibration.py": 22,
    "test_imu.py": 20,
    "test_sim_sensors.py": 18,
    "test_sim_world.py": 17,
    "test_config_yaml.py": 16,
    "test_run_config.py": 15,
    "test_track_many.py": 14,
    "test_ros2_player.py": 14,
    "test_ekf_run.py": 13,
    "test_calibration_io.py": 12,
    "test_bag_rig.py": 12,
    "test_own_robot_guide.py": 11,
    "test_gap_bridge.py": 10,
    "test_cli_run.py": 10,
    "test_kitti.py": 8,
}


def pytest_collection_modifyitems(config, items):
    """The heaviest files first (see :data:`FILE_COST_S`); a stable sort, so the rest keep their order."""
    items.sort(key=lambda item: -FILE_COST_S.get(item.path.name, 0))


def _made_once_per_session(tmp_path_factory, name: str, make) -> Path:
    """The folder ``name`` that ``make(folder)`` fills, made once in the test session: by the first
    process to ask for it, the others (xdist workers) waiting for it and then reading what it made
    (the session's simulated logs are inputs only; no test writes into them). It lies in the session's
    temporary folder, which holds the workers' own (a new one each session)."""
    try:
        import fcntl
    except ImportError:  # (not POSIX: each process makes its own)
        fcntl = None
    base = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER") and fcntl is not None:
        base = base.parent
    folder, done = base / name, base / f"{name}.done"
    with open(base / f"{name}.lock", "w") as lock:
        if fcntl is not None:
            fcntl.flock(lock, fcntl.LOCK_EX)  # (released when the file closes)
        if not done.exists():
            make(folder)
            done.touch()
    return folder


@pytest.fixture(scope="session")
def smoke_log(tmp_path_factory) -> InMemorySequence:
    """The `smoke` scenario (4 m, 320x240, odometry), every event in memory (simulated once per
    session and handed to each process as a pickle: the same events, bit for bit)."""

    def record(folder: Path) -> None:
        folder.mkdir()
        log = InMemorySequence.record(SimulatedSequence.from_config(scenario("smoke", seed=3)))
        (folder / "log.pickle").write_bytes(pickle.dumps(log, protocol=pickle.HIGHEST_PROTOCOL))

    return pickle.loads((_made_once_per_session(tmp_path_factory, "smoke_log", record) / "log.pickle").read_bytes())


@pytest.fixture(scope="session")
def tiny_folder(tmp_path_factory):
    """The `smoke` scenario cut to 0.5 m (8 camera frames), written as a dataset folder with ground truth."""
    from dem_graph.sim.pipeline import simulate

    def write(folder: Path) -> None:
        simulate(scenario("smoke", seed=5, length_m=0.5), folder / "smoke", preview=False)

    return _made_once_per_session(tmp_path_factory, "tiny", write) / "smoke"


@pytest.fixture(scope="session")
def smoke_folder(tmp_path_factory):
    """The `smoke` scenario (4 m, 2.5 s) as a dataset folder, as `dem-graph simulate` writes it."""
    from dem_graph.sim.pipeline import simulate

    def write(folder: Path) -> None:
        simulate(scenario("smoke", seed=5), folder / "smoke", preview=False)

    return _made_once_per_session(tmp_path_factory, "smoke_folder", write) / "smoke"


@pytest.fixture(scope="session")
def smoke_run(tmp_path_factory, smoke_log):
    """``smoke_run(settings, with_dem=True)``: ``run_estimator(smoke_log, RunConfig.model_validate(settings),
    with_dem=with_dem)``, the run of the session's `smoke` log with nothing but its settings, made once in
    the session for every test and process that asks for the same settings (several files check the
    same default runs) and handed to each asker as its own copy (a pickle: the same numbers, bit for
    bit). Without the live map's pipeline (``live``: it holds the running estimator), which no asker
    reads. ``with_dem=False`` is the same run without the DEM made after the estimator finished
    (``run_estimator`` makes it last, from the final poses: ``dem`` and ``metrics.dem`` are all it
    adds). A test that edits the log, patches the code or instruments the run makes its own; the first
    asker makes it, so ask before patching anything."""
    import dataclasses
    import hashlib

    from dem_graph.pipeline import RunConfig, run_estimator

    made: dict[str, bytes] = {}

    def get(settings: dict, with_dem: bool = True):
        key = RunConfig.model_validate(settings).model_dump_json()  # (settings that validate alike: one run)
        if key not in made:

            def make(folder: Path) -> None:
                folder.mkdir(exist_ok=True)  # (left by an asker that failed part way)
                run = run_estimator(smoke_log, RunConfig.model_validate(settings))
                run = dataclasses.replace(run, live=None)
                (folder / "run.pickle").write_bytes(pickle.dumps(run, protocol=pickle.HIGHEST_PROTOCOL))

            name = "smoke_run_" + hashlib.sha1(key.encode()).hexdigest()[:16]
            made[key] = (_made_once_per_session(tmp_path_factory, name, make) / "run.pickle").read_bytes()
        run = pickle.loads(made[key])
        if not with_dem:
            run.dem, run.metrics.dem = None, None
        return run

    return get


@pytest.fixture(scope="session", autouse=True)
def _tracker_kernels_compiled_once(request, tmp_path_factory):
    """The tracker's numba kernels (frontend/match_kernel.py, ``cache=True``) compiled by one test process
    in a clean clone (no numba cache yet), the other xdist workers waiting for them and then loading them
    from numba's cache: before, each worker compiled them at its first run (4.1 CPU-seconds a process
    here). Three frames of PTPM (``PatchTracker.track``) and of GM (``track_many``) on the session's
    `smoke` log compile every kernel a run uses. A single process compiles them once anyway."""
    if os.environ.get("PYTEST_XDIST_WORKER"):
        smoke_log = request.getfixturevalue("smoke_log")  # (made first: the other workers wait for the kernels only)

        def compile_kernels(folder: Path) -> None:
            from dem_graph.pipeline import RunConfig, run_estimator

            folder.mkdir(exist_ok=True)
            for estimator in ("ptpm", "gm"):
                run_estimator(smoke_log, RunConfig(estimator=estimator, max_frames=3), with_dem=False)

        _made_once_per_session(tmp_path_factory, "tracker_kernels", compile_kernels)
    yield


SHARED_KITTI = Path(__file__).resolve().parent.parent.parent / "shared" / "data" / "kitti_odometry"


@pytest.fixture(scope="session")
def kitti_sample() -> Path:
    """The shared KITTI odometry sample (51 frames of sequence 04) at ``../shared/data/kitti_odometry``
    from the repository's root; the test is skipped when it is absent."""
    if not (SHARED_KITTI / "sequences").is_dir():
        pytest.skip(f"shared KITTI sample not found at {SHARED_KITTI}")
    return SHARED_KITTI


SHARED_KITTI_RAW = SHARED_KITTI.parent / "kitti_raw_0013" / "2011_09_26" / "2011_09_26_drive_0013_sync"


@pytest.fixture(scope="session")
def kitti_raw_drive() -> Path:
    """The shared KITTI raw drive 0013 (48 frames, colour camera 2 only); skipped when absent."""
    if not (SHARED_KITTI_RAW / "oxts").is_dir():
        pytest.skip(f"shared KITTI raw drive not found at {SHARED_KITTI_RAW}")
    return SHARED_KITTI_RAW


@pytest.fixture(scope="session")
def kitti_sequence(kitti_sample):
    """The shared sample opened once, its reference ground built once."""
    from dem_graph.datasets.kitti import open_kitti

    sequence = open_kitti(kitti_sample)
    sequence.ground_truth  # noqa: B018 - builds the reference surface once for every test
    return sequence
