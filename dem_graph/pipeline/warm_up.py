"""The estimators' compiled kernels made ready before a live source's first message.

The tracker, the pose update and the live map run compiled kernels (numba), compiled at their first
call and cached on disk: a new installation's first run compiles them as it goes (17 s for a
`smoke` run here), a later one loads them (about 2 s). A live source cannot wait that long once its
messages come: :func:`warm_up` runs the estimator over 8 frames of a simulated 0.4 m drive first,
so that the compiling, or the loading, is done before.
"""

from __future__ import annotations

import logging
import time

from dem_graph.pipeline.config import RunConfig
from dem_graph.pipeline.live import LivePipeline

log = logging.getLogger(__name__)


def warm_up(estimator: str = "isam2", frames: int = 8) -> float:
    """Run ``estimator`` (in this process, its graph here too) over ``frames`` frames of a simulated
    drive, so that every kernel it uses is compiled or loaded; returns the seconds it took."""
    from dem_graph.pipeline.run import feed
    from dem_graph.sim.scenarios import scenario
    from dem_graph.sim.simulator import SimulatedSequence

    t0 = time.perf_counter()
    sequence = SimulatedSequence.from_config(scenario("smoke", seed=0, length_m=0.4))
    pipeline = LivePipeline.for_sequence(sequence, RunConfig(estimator=estimator))
    for _ in feed(pipeline, sequence, max_frames=frames):
        pass
    seconds = time.perf_counter() - t0
    log.info("the %s estimator's kernels are ready (%.1f s)", estimator, seconds)
    return seconds


__all__ = ["warm_up"]
