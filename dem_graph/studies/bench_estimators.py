"""Estimator benchmark: time per frame against the number of live points (the paper's Fig. 12).

The log is simulated once and held in memory, so only the estimator (tracking included) and the
live map are timed: ``frame ms`` is the estimator's own time on a frame, ``map ms`` the live map's
update, ``whole frame ms`` both with the estimator's time on the scans and odometry in between.
With 1550 frames or more, each row also gives the median time per frame around frame 1500 over
the median around frame 150 (100 frames each), and the resident memory at frame 1500 over that
at frame 150: a cost that grows with the run shows there.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dem_graph.datasets.events import CameraFrame
from dem_graph.datasets.memory import InMemorySequence
from dem_graph.evaluation.timing import TimingStats, format_table, machine_description
from dem_graph.frontend.focus import FocusArea
from dem_graph.pipeline.config import RunConfig, split_graph_process
from dem_graph.pipeline.run import run_estimator
from dem_graph.progress import progress
from dem_graph.sim.scenarios import scenario
from dem_graph.sim.simulator import SimulatedSequence


@dataclass(frozen=True)
class BenchRow:
    estimator: str
    max_points: int
    frame: TimingStats
    tracking: TimingStats
    update: TimingStats
    graph: TimingStats
    live_points_median: float
    tracked_points_median: float
    drift_percent: float
    late_over_early: float = float("nan")  # median ms around frame 1500 / around frame 150
    graph_lag_keyframes: float = float("nan")  # isam2: median keyframes between a keyframe and its graph result
    live_map: TimingStats | None = None  # the live map's update per frame
    whole_frame: TimingStats | None = None  # the estimator's events and the live map, per frame
    memory_late_over_early: float = float("nan")  # resident memory at frame 1500 / at frame 150
    graph_update: TimingStats | None = None  # isam2: each graph update (in the second process with isam2-process)
    graph_lag_max: float = float("nan")  # isam2: most keyframes between a keyframe and its graph result
    keyframes_merged: int = 0  # isam2-process: frames not made keyframes while the graph was behind
    ate_m: float = float("nan")

    @property
    def frames_per_s(self) -> float:
        return 1000.0 / self.frame.median_ms

    @property
    def points_per_s(self) -> float:
        return self.tracked_points_median * self.frames_per_s


@dataclass(frozen=True)
class EstimatorBenchResult:
    rows: list[BenchRow]
    scenario: str
    frames: int
    image_size: str
    machine: str
    realtime: bool = True

    def table(self) -> str:
        rows = [
            [
                r.estimator, r.max_points, f"{r.live_points_median:.0f}", f"{r.tracked_points_median:.0f}", f"{r.frame.median_ms:.1f}", f"{r.frame.p95_ms:.1f}",
                f"{r.tracking.median_ms:.1f}", f"{r.update.median_ms:.1f}", f"{r.graph.mean_ms:.1f}", f"{r.frames_per_s:.1f}", f"{r.points_per_s:.0f}", f"{r.drift_percent:.2f}",
                "-" if np.isnan(r.late_over_early) else f"{r.late_over_early:.2f}",
                "-" if np.isnan(r.graph_lag_keyframes) else f"{r.graph_lag_keyframes:.0f}",
                f"{r.live_map.median_ms:.2f}", f"{r.live_map.p95_ms:.2f}", f"{r.whole_frame.median_ms:.1f}", f"{r.whole_frame.p95_ms:.1f}",
                "-" if np.isnan(r.memory_late_over_early) else f"{r.memory_late_over_early:.3f}",
                "-" if r.graph_update is None else f"{r.graph_update.median_ms:.1f}",
                "-" if r.graph_update is None else f"{r.graph_update.p95_ms:.1f}",
                "-" if np.isnan(r.graph_lag_max) else f"{r.graph_lag_max:.0f}",
                r.keyframes_merged,
                f"{1000 * r.ate_m:.1f}",
            ]
            for r in self.rows
        ]
        headers = [
            "estimator", "cap n", "live", "tracked", "frame ms (median)", "frame ms (p95)", "tracking ms", "update ms", "graph ms (mean)", "frames/s", "points/s", "drift %",
            "frame 1500 / frame 150", "graph lag (keyframes)", "map ms (median)", "map ms (p95)", "whole frame ms (median)", "whole frame ms (p95)",
            "memory 1500 / 150", "graph update ms (median)", "graph update ms (p95)", "graph lag max", "keyframes merged", "ATE mm",
        ]
        return format_table(headers, rows, title=f"estimator benchmark: '{self.scenario}' {self.image_size}, {self.frames} frames {'at the camera rate' if self.realtime else 'as fast as possible'}, on {self.machine}")


BENCH_ESTIMATORS = ("gm", "ptpm", "isam2", "isam2-batch", "isam2-process")
NO_IMU = "-noimu"  # a bench's or study's suffix: the estimator run with the log's IMU ignored (--no-imu)


def without_no_imu(name: str) -> str:
    """The estimator of a bench or study name, its :data:`NO_IMU` suffix taken off."""
    return name[: -len(NO_IMU)] if name.endswith(NO_IMU) else name


def config_for_points(estimator: str, max_points: int, rig, speed_mps: float | None = None) -> RunConfig:
    """The run configuration for ``estimator`` with a budget of ``max_points`` live points: 70 % of
    them at most from the laser, and about as many focus cells as points in the focus area at
    ``speed_mps`` (default: the focus settings' nominal speed, which it also becomes), so that the
    cap is what limits. ``isam2-process``: isam2 with its graph in a second process."""
    name, graph_process = split_graph_process(estimator)
    config = RunConfig(estimator=name)
    config.isam2.graph_process = graph_process
    fe = config.frontend
    fe.max_points = max_points
    fe.max_laser_points = int(round(0.7 * max_points))
    if speed_mps is not None:
        fe.focus.nominal_speed_mps = float(speed_mps)
    # about as many focus cells as points wanted, so that the cap is what limits
    focus = FocusArea.for_speed(fe.focus, rig, None)
    area = (focus.x_far_m - focus.x_near_m) * 2 * focus.half_width_m
    fe.focus.cell_size_m = float(np.sqrt(area / (0.8 * max_points)))
    fe.min_separation_px = min(fe.min_separation_px, 6.0)
    return config


def _update_stats(seconds: list[float]) -> TimingStats | None:
    return TimingStats.from_seconds(seconds) if seconds else None


def bench_estimators(
    estimators=("gm", "ptpm"), point_counts=(50, 100, 130, 150, 200, 300), scenario_name: str = "demo", frames: int = 150, seed: int = 0, realtime: bool = True
) -> EstimatorBenchResult:
    """Each estimator at each cap on live points over the first ``frames`` camera frames of the
    scenario, held in memory. ``realtime``: the frames come at the camera's rate, as on the vehicle
    (an estimator slower than that gets them at once); false: as fast as each estimator takes them."""
    sim = SimulatedSequence.from_config(scenario(scenario_name, seed=seed))
    events = []
    for e in sim.events():
        events.append(e)
        if isinstance(e, CameraFrame) and e.index + 1 >= frames:
            break
    log = InMemorySequence(sim.rig, events, sim.T_world_body_initial, sim.t_start_s, sim.ground_truth, sim.name)
    rows = []
    for name in estimators:
        for n in progress(point_counts, total=len(point_counts), desc=f"bench {name}"):
            config = config_for_points(without_no_imu(name), n, sim.rig)
            config.motion.use_imu = not name.endswith(NO_IMU)
            config.realtime = realtime
            run = run_estimator(log, config)
            fr = run.estimator.frames[5:]  # skip the start, while the map fills
            live = run.live.pipeline
            memory = run.metrics.live_map.resident_memory_mb or {}
            total = np.array([f.timing_s["total"] for f in run.estimator.frames])
            ratio = float(np.median(total[1450:1550]) / np.median(total[100:200])) if len(total) >= 1550 else float("nan")
            rows.append(
                BenchRow(
                    name,
                    n,
                    TimingStats.from_seconds([f.timing_s["total"] for f in fr]),
                    TimingStats.from_seconds([f.timing_s["tracking"] for f in fr]),
                    TimingStats.from_seconds([f.timing_s["update"] for f in fr]),
                    TimingStats.from_seconds([f.timing_s.get("graph", 0.0) for f in fr]),
                    float(np.median([f.n_live for f in fr])),
                    float(np.median([f.n_tracked for f in fr])),
                    float(run.metrics.trajectory.drift_percent),
                    ratio,
                    float(run.estimator.counters.get("graph_lag_keyframes_median", np.nan)),
                    TimingStats.from_seconds(live.map_timing_s[5:]),
                    TimingStats.from_seconds(live.frame_timing_s[5:]),
                    memory.get("frame_1500", np.nan) / memory.get("frame_150", np.nan),
                    _update_stats(run.estimator.graph_update_s.get("total", [])),
                    float(run.estimator.counters.get("graph_lag_keyframes_max", np.nan)),
                    int(run.estimator.counters.get("keyframes_merged", 0)),
                    float(run.metrics.trajectory.ate_rmse_m),
                )
            )
    cam = sim.rig.camera
    return EstimatorBenchResult(rows, scenario_name, frames, f"{cam.width_px}x{cam.height_px}", machine_description(), realtime)
