"""Shared fixtures: small simulated logs recorded once per test session."""

from __future__ import annotations

from pathlib import Path

import pytest

from dem_graph.datasets.memory import InMemorySequence
from dem_graph.progress import set_progress_enabled
from dem_graph.sim.scenarios import scenario
from dem_graph.sim.simulator import SimulatedSequence

set_progress_enabled(False)


@pytest.fixture(scope="session")
def smoke_log() -> InMemorySequence:
    """The `smoke` scenario (4 m, 320x240, odometry), every event in memory."""
    return InMemorySequence.record(SimulatedSequence.from_config(scenario("smoke", seed=3)))


@pytest.fixture(scope="session")
def tiny_folder(tmp_path_factory):
    """The `smoke` scenario cut to 0.5 m (8 camera frames), written as a dataset folder with ground truth."""
    from dem_graph.sim.pipeline import simulate

    out = tmp_path_factory.mktemp("tiny") / "smoke"
    simulate(scenario("smoke", seed=5, length_m=0.5), out, preview=False)
    return out


@pytest.fixture(scope="session")
def smoke_folder(tmp_path_factory):
    """The `smoke` scenario (4 m, 2.5 s) as a dataset folder, as `dem-graph simulate` writes it."""
    from dem_graph.sim.pipeline import simulate

    out = tmp_path_factory.mktemp("smoke_folder") / "smoke"
    simulate(scenario("smoke", seed=5), out, preview=False)
    return out


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
