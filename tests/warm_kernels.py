"""Compile the package's numba kernels into their on-disk cache before the test suite starts.

`make test` runs this beside its lint and docs build. In a clean clone no kernel is compiled yet,
and every test process that meets one before a cache file exists compiles it again (about 30 s of a
core each); after this, they load it. Every estimator and the live map run a few frames of a short
simulated log, which calls each kernel with the types the package uses. Not a test: it asserts
nothing, and the suite does not depend on it having run."""

from __future__ import annotations

from dem_graph.datasets.memory import InMemorySequence
from dem_graph.pipeline import RunConfig, run_estimator
from dem_graph.sim.scenarios import scenario
from dem_graph.sim.simulator import SimulatedSequence


def main() -> None:
    log = InMemorySequence.record(SimulatedSequence.from_config(scenario("smoke", seed=5, length_m=0.5)))
    for estimator in ("isam2", "ptpm", "gm"):
        run_estimator(log, RunConfig.model_validate({"estimator": estimator, "max_frames": 6}))


if __name__ == "__main__":
    main()
