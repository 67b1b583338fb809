"""Shared fixtures: small simulated logs recorded once per test session."""

from __future__ import annotations

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
