"""A run's live map, measured: what a :class:`~dem_graph.pipeline.live.LivePipeline` run adds to the
run's metrics and folder.

- :class:`LiveErrorMeter`: the Fig. 8 measure on the map as the guidance had it. Every
  ``local_error.every_n_frames`` frames, the live map as it stands then is read over the Fig. 8
  window from the pose known then, and compared with the truth (both comparisons of
  :class:`~dem_graph.evaluation.dem_metrics.LocalErrorSeries`). The hindsight figure
  (``dem.local_window``) fuses, at the same times, the same measurements placed with the run's final poses.
- :class:`LiveMapRecorder`: every ``live_map.save_every_n_frames`` frames, the local map over a
  fixed window, for ``live_maps.nc`` (:mod:`dem_graph.io.live_maps`), in the run folder as it goes
  (``live_maps.part``) when the run has one.
- :class:`LiveMapMetrics`: ``metrics.json``'s ``live_map``.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

from dem_graph.datasets.base import GroundTruth
from dem_graph.dem.layers import Dem
from dem_graph.evaluation.dem_metrics import (
    HeightErrors,
    LocalErrorConfig,
    LocalErrorSeries,
    LocalErrorSummary,
    height_errors,
    local_dem_errors,
    local_error_series_from_rows,
    truth_at_cells,
)
from dem_graph.evaluation.results import MetricsModel, Number
from dem_graph.evaluation.timing import TimingStats, resident_memory_mb
from dem_graph.geometry.grid import GridGeometry
from dem_graph.io.live_maps import LIVE_MAPS_NC, SAVED_LAYERS, LiveMapWriter
from dem_graph.pipeline.config import LiveMapConfig
from dem_graph.pipeline.live import LivePipeline, LiveUpdate


class LiveMapMetrics(MetricsModel):
    """The live map over a run (``metrics.json``'s ``live_map``)."""

    update_median_ms: Number  # the live map's time per frame: scans placed, revisions, the local map
    update_p95_ms: Number
    whole_frame_median_ms: Number  # the estimator on the frame's events (front end included) and the live map
    whole_frame_p95_ms: Number
    # done between frames, off their path (a run at the camera's rate, with the graph in a second
    # process): the graph's results taken and the map's scans moved with them, each time there was any
    idle_updates: int = 0
    idle_median_ms: Number = float("nan")
    idle_p95_ms: Number = float("nan")
    resident_memory_mb: dict[str, float] | None = None  # the process's, at frames 150, 1500 and the last
    scans: int
    returns: int  # laser returns placed
    returns_moved: int  # re-placements because their poses were revised (a return moved in n revisions counts n times)
    scans_moved: int
    map_points: int
    tiles: int
    memory_mb: float  # the map's cells
    covered_cells: int
    height_error: HeightErrors | None = None  # the live global map (as built) against the truth
    local_window: LocalErrorSummary | None = None  # Fig. 8 on the map as the guidance had it
    bad_input: dict[str, int] | None = None  # events skipped or warned about, by kind
    saved_maps: int = 0


class MemoryProbe:
    """A listener: the process's resident memory at frames 150 and 1500, and at the last frame."""

    FRAMES = (150, 1500)

    def __init__(self):
        self.mb: dict[str, float] = {}
        self._last: tuple[int, float] | None = None

    def __call__(self, update: LiveUpdate) -> None:
        mb = resident_memory_mb()  # a read of /proc/self/statm: microseconds
        if update.frame in self.FRAMES:
            self.mb[f"frame_{update.frame}"] = mb
        self._last = (update.frame, mb)

    def summary(self) -> dict[str, float]:
        return {**self.mb, f"frame_{self._last[0]}": self._last[1]} if self._last else dict(self.mb)


class LiveErrorMeter:
    """A listener: the Fig. 8 measure on the live map every ``window.every_n_frames`` frames."""

    def __init__(self, pipeline: LivePipeline, truth: GroundTruth, window: LocalErrorConfig):
        self.pipeline, self.truth, self.window = pipeline, truth, window
        self.times: list[float] = []
        self.rows: list[tuple[float, float, float, float, float]] = []

    def __call__(self, update: LiveUpdate) -> None:
        if (update.frame - 1) % self.window.every_n_frames:
            return
        w = self.window
        dem = self.pipeline.map.local(update.T_world_body, w.x_range_m, w.width_m / 2.0, update.t_s, traversability_window=None)
        self.times.append(update.t_s)
        self.rows.append(local_dem_errors(dem, self.truth.elevation, self.truth.trajectory))

    def series(self) -> LocalErrorSeries:
        return local_error_series_from_rows(self.times, self.rows)


class LiveMapRecorder:
    """A listener: every ``save_every_n_frames`` frames' local map over the fixed save window, kept
    on disk until :meth:`write` (``live_maps.nc``). ``run_dir``: the run folder, where the maps are
    appended as they are saved (``live_maps.part``, readable after a kill); None: a temporary file."""

    def __init__(self, pipeline: LivePipeline, config: LiveMapConfig, run_dir: str | Path | None = None):
        self.pipeline, self.config = pipeline, config
        x0, x1 = config.save_x_range_m
        self.geometry = GridGeometry.covering(x0, -config.save_width_m / 2.0, x1, config.save_width_m / 2.0, pipeline.map.fusion.resolution_m)
        self.writer = LiveMapWriter(self.geometry, SAVED_LAYERS, None if run_dir is None else Path(run_dir) / LIVE_MAPS_NC)

    def __call__(self, update: LiveUpdate) -> None:
        if (update.frame - 1) % self.config.save_every_n_frames:
            return
        c = self.config
        dem = self.pipeline.map.local(update.T_world_body, c.save_x_range_m, c.save_width_m / 2.0, update.t_s, self.pipeline.config.dem.traversability_window)
        self.writer.append(dem)

    def write(self, path):
        return self.writer.close(path)


@dataclass
class LiveRun:
    """The live parts of a run: the pipeline, its memory probe, and its meter and recorder when it
    has them. Once the run is over, :attr:`final_map` is the map as built (made once)."""

    pipeline: LivePipeline
    truth: GroundTruth | None
    window: LocalErrorConfig
    memory: MemoryProbe
    meter: LiveErrorMeter | None = None
    recorder: LiveMapRecorder | None = None

    @classmethod
    def attach(cls, pipeline: LivePipeline, truth: GroundTruth | None, window: LocalErrorConfig, run_dir: str | Path | None = None) -> LiveRun:
        """The live parts for ``pipeline``, added to its listeners; ``run_dir``: the run folder, which
        the saved local maps are written into as they are saved (:class:`LiveMapRecorder`)."""
        meter = LiveErrorMeter(pipeline, truth, window) if truth is not None and truth.elevation is not None else None
        recorder = LiveMapRecorder(pipeline, pipeline.config.live_map, run_dir) if pipeline.config.live_map.save_every_n_frames else None
        memory = MemoryProbe()
        pipeline.listeners.extend(x for x in (meter, recorder, memory) if x is not None)
        return cls(pipeline, truth, window, memory, meter, recorder)

    @cached_property
    def final_map(self) -> Dem | None:
        """The whole live map with its traversability, as it stands at the end (None if empty)."""
        p = self.pipeline
        return p.map.global_dem(p.config.dem.traversability_window) if p.map.grid.n_kept else None

    def metrics(self) -> LiveMapMetrics:
        p = self.pipeline
        m = p.map
        timing = TimingStats.from_seconds(p.map_timing_s)
        whole = TimingStats.from_seconds(p.frame_timing_s)
        idle = TimingStats.from_seconds(p.idle_timing_s)
        dem, truth = self.final_map, self.truth
        covered = int(dem.covered.sum()) if dem is not None else 0
        height = None
        if dem is not None and truth is not None and truth.elevation is not None:
            height = height_errors(dem.elevation, truth_at_cells(dem, truth.elevation))
        c = m.counters
        bad = {k: v for k, v in p.counters.items() if v}
        return LiveMapMetrics(
            update_median_ms=timing.median_ms,
            update_p95_ms=timing.p95_ms,
            whole_frame_median_ms=whole.median_ms,
            whole_frame_p95_ms=whole.p95_ms,
            idle_updates=len(p.idle_timing_s),
            idle_median_ms=idle.median_ms,
            idle_p95_ms=idle.p95_ms,
            resident_memory_mb=self.memory.summary(),
            scans=c["scans"],
            returns=c["returns"],
            returns_moved=c["returns_moved"],
            scans_moved=c["scans_moved"],
            map_points=c["map_points"],
            tiles=m.grid.n_tiles,
            memory_mb=m.grid.nbytes / 2**20,
            covered_cells=covered,
            height_error=height,
            local_window=self.meter.series().summary(self.window) if self.meter is not None and self.meter.times else None,
            bad_input=bad or None,
            saved_maps=len(self.recorder.writer) if self.recorder is not None else 0,
        )


__all__ = ["LiveErrorMeter", "LiveMapMetrics", "LiveMapRecorder", "LiveRun", "MemoryProbe"]
