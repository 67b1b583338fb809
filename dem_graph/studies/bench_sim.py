"""Simulator benchmark: camera render rate, laser ray rate, and the time to simulate a whole scenario."""

from __future__ import annotations

import tempfile
import time
from dataclasses import dataclass

import numpy as np

from dem_graph.evaluation.timing import TimingStats, format_table, machine_description
from dem_graph.progress import progress
from dem_graph.sim.laser import cast_scan
from dem_graph.sim.pipeline import simulate
from dem_graph.sim.scenarios import scenario
from dem_graph.sim.simulator import SimulatedSequence


@dataclass(frozen=True)
class SimBenchResult:
    scenario: str
    image_size: str
    world_build_s: float
    render: TimingStats
    laser_scan: TimingStats
    rays_per_scan: int
    full_simulation_s: float | None
    full_frames: int | None
    machine: str

    @property
    def render_fps(self) -> float:
        return 1000.0 / self.render.median_ms

    @property
    def laser_rays_per_s(self) -> float:
        return self.rays_per_scan / (self.laser_scan.median_ms / 1000.0)

    def table(self) -> str:
        rows = [
            ["world build (terrain, texture, BVH)", f"{self.world_build_s:.2f} s", "", ""],
            [f"camera render {self.image_size}", f"{self.render.median_ms:.1f} ms", f"{self.render.p95_ms:.1f} ms", f"{self.render_fps:.1f} frames/s"],
            [f"laser scan ({self.rays_per_scan} beams)", f"{self.laser_scan.median_ms:.2f} ms", f"{self.laser_scan.p95_ms:.2f} ms", f"{self.laser_rays_per_s / 1e6:.2f} M rays/s"],
        ]
        if self.full_simulation_s is not None:
            rows.append([f"simulate '{self.scenario}' to disk ({self.full_frames} frames)", f"{self.full_simulation_s:.1f} s", "", f"{self.full_frames / self.full_simulation_s:.1f} frames/s"])
        return format_table(["step", "median", "p95", "throughput"], rows, title=f"simulator benchmark on {self.machine}")


def bench_sim(scenario_name: str = "paper", n_frames: int = 40, n_scans: int = 200, full: bool = True, seed: int = 0) -> SimBenchResult:
    """Time rendering and laser casting along the scenario's path, and (``full``) a whole simulation to a temporary folder."""
    config = scenario(scenario_name, seed=seed)
    t0 = time.perf_counter()
    seq = SimulatedSequence.from_config(config)
    seq.renderer.render(seq.T_world_body_initial @ seq.rig.T_body_cam)  # builds the ray-casting structure
    build_s = time.perf_counter() - t0

    rng = np.random.default_rng(seed)
    cam_times = seq.camera_times()
    samples = []
    for t in progress(cam_times[np.linspace(0, len(cam_times) - 1, n_frames).astype(int)], total=n_frames, desc="render"):
        T = seq.world.motion.T_world_body(t) @ seq.rig.T_body_cam
        start = time.perf_counter()
        seq.renderer.render(T, rng)
        samples.append(time.perf_counter() - start)
    render = TimingStats.from_seconds(samples)

    laser_times = seq.laser_times()
    samples = []
    for t in laser_times[np.linspace(0, len(laser_times) - 1, n_scans).astype(int)]:
        T = seq.world.motion.T_world_body(t) @ seq.rig.T_body_laser
        start = time.perf_counter()
        cast_scan(seq.scene, T, seq.rig.laser, rng)
        samples.append(time.perf_counter() - start)
    laser = TimingStats.from_seconds(samples)

    full_s = frames = None
    if full:
        with tempfile.TemporaryDirectory(prefix="dem_graph_bench_") as tmp:
            start = time.perf_counter()
            result = simulate(config, f"{tmp}/data", preview=False)
            full_s, frames = time.perf_counter() - start, result.n_frames
    cam = config.rig.camera
    return SimBenchResult(scenario_name, f"{cam.width_px}x{cam.height_px}", build_s, render, laser, config.rig.laser.beams.count, full_s, frames, machine_description())
