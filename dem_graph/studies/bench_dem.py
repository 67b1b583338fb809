"""``dem-graph research bench-dem``: how fast the DEM is fused and rebuilt.

- fusion throughput: measurements fused per second (cell lookup, median gate, Kalman gate,
  layers), on a dataset's laser returns repeated with jitter up to ``n_points``;
- whole-run rebuild: every laser return of the log placed with the poses, fused, and the
  traversability layers computed, as ``dem-graph dem RUN`` does it.

Without a dataset, the returns are synthetic: a scan line sweeping a 100 x 100 m area.
Each figure is the median (and 95th percentile) of ``repeats`` runs.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from dem_graph.dem.fusion import FusionConfig, covering_geometry, fuse
from dem_graph.dem.returns import GroundReturns, PoseTrack, laser_returns_world
from dem_graph.dem.views import global_dem
from dem_graph.errors import DemGraphError


@dataclass
class DemBenchResult:
    rows: list[dict] = field(default_factory=list)

    def table(self) -> str:
        head = f"{'stage':<34} {'points':>10} {'median s':>9} {'p95 s':>8} {'M points/s':>11}"
        lines = [head, "-" * len(head)]
        for r in self.rows:
            lines.append(f"{r['stage']:<34} {r['points']:>10d} {r['median_s']:>9.3f} {r['p95_s']:>8.3f} {r['points'] / r['median_s'] / 1e6:>11.2f}")
        return "\n".join(lines)


def _timed(fn, repeats: int) -> tuple[float, float]:
    fn()  # warm-up: first-touch page faults and imports are not the steady state
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return float(np.median(times)), float(np.percentile(times, 95))


def _synthetic_returns(n: int, rng: np.random.Generator) -> GroundReturns:
    """A scan line of 300 returns 3 m ahead, advancing along a 100 m lawnmower path, time-ordered."""
    per_scan = 300
    scans = -(-n // per_scan)
    s = np.arange(scans) * 100.0 * 50 / scans  # 50 lanes of 100 m
    lane = (s // 100.0).astype(int)
    along = np.where(lane % 2 == 0, s % 100.0, 100.0 - s % 100.0)
    across = np.linspace(-5.0, 5.0, per_scan)
    x = np.repeat(along, per_scan)
    y = (np.repeat(lane * 2.0, per_scan) + np.tile(across, scans))[: scans * per_scan]
    xyz = np.column_stack([x, y, 0.1 * np.sin(x / 7.0) + rng.normal(0, 0.02, x.size)])[:n]
    return GroundReturns(xyz, np.full(n, 4e-4), np.repeat(np.arange(scans) * 0.08, per_scan)[:n], np.zeros(n, np.uint8))


def _repeat_to(returns: GroundReturns, n: int, rng: np.random.Generator) -> GroundReturns:
    k = -(-n // len(returns))
    xyz = np.tile(returns.xyz_m, (k, 1))[:n] + rng.normal(0, 0.01, (n, 3))
    return GroundReturns(xyz, np.tile(returns.var_z_m2, k)[:n], np.tile(returns.t_s, k)[:n], np.tile(returns.source, k)[:n])


def bench_dem(sequence=None, poses: PoseTrack | None = None, n_points: int = 5_000_000, repeats: int = 5, config: FusionConfig | None = None) -> DemBenchResult:
    """Fusion throughput on ``n_points`` measurements, and (with a sequence) the whole-run rebuild time."""
    config = config or FusionConfig()
    rng = np.random.default_rng(0)
    out = DemBenchResult()
    if sequence is not None:
        if poses is None:
            gt = sequence.ground_truth
            if gt is None:
                raise DemGraphError("this dataset has no ground truth: give a run's poses (--run)")
            t = np.arange(gt.trajectory.t_s[0], gt.trajectory.t_s[-1], 0.04)
            poses = PoseTrack(t, gt.trajectory.at(t), np.zeros((len(t), 6, 6)))
        scan_t_s, ranges_m = sequence.laser_scans()  # read once: the timing is of the DEM, not of the disk

        def rebuild():
            return global_dem(laser_returns_world(scan_t_s, ranges_m, sequence.rig, poses), config)

        returns = laser_returns_world(scan_t_s, ranges_m, sequence.rig, poses)
        med, p95 = _timed(rebuild, repeats)
        out.rows.append({"stage": "rebuild: place + fuse + layers", "points": len(returns), "median_s": med, "p95_s": p95})
        geometry = covering_geometry(returns, config)
        med, p95 = _timed(lambda: fuse(returns, geometry, config), repeats)
        out.rows.append({"stage": "fuse the run's returns", "points": len(returns), "median_s": med, "p95_s": p95})
        big = _repeat_to(returns, n_points, rng)
    else:
        big = _synthetic_returns(n_points, rng)
    geometry = covering_geometry(big, config)
    med, p95 = _timed(lambda: fuse(big, geometry, config), repeats)
    out.rows.append({"stage": f"fuse {n_points / 1e6:g} M points", "points": len(big), "median_s": med, "p95_s": p95})
    return out


__all__ = ["DemBenchResult", "bench_dem"]
