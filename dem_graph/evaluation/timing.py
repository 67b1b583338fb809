"""Timing statistics (a run's time per frame by phase), the machine they came from, and the table
layout every benchmark prints."""

from __future__ import annotations

import platform
from dataclasses import dataclass

import numpy as np

from dem_graph.evaluation.results import MetricsModel, Number


@dataclass(frozen=True)
class TimingStats:
    n: int
    median_ms: float
    p95_ms: float
    mean_ms: float

    @classmethod
    def from_seconds(cls, samples_s) -> TimingStats:
        a = 1000.0 * np.asarray(samples_s, dtype=float)
        if a.size == 0:
            return cls(0, float("nan"), float("nan"), float("nan"))
        return cls(int(a.size), float(np.median(a)), float(np.percentile(a, 95)), float(a.mean()))


class PhaseTiming(MetricsModel):
    """One phase's time per frame over a run, milliseconds."""

    median_ms: Number
    p95_ms: Number
    mean_ms: Number


def frame_timing_summary(per_frame: dict[str, list[float]]) -> dict[str, PhaseTiming]:
    """Per-phase timing of a run: ``{phase: PhaseTiming}``.

    ``per_frame`` maps a phase ("total", "prediction", "tracking", "update", ...) to its duration in
    seconds at each frame. A phase with no sample gets NaN (null in ``metrics.json``).
    """
    summary = {}
    for phase, samples in per_frame.items():
        stats = TimingStats.from_seconds(samples)
        summary[phase] = PhaseTiming(median_ms=stats.median_ms, p95_ms=stats.p95_ms, mean_ms=stats.mean_ms)
    return summary


class GraphUpdateTiming(MetricsModel):
    """The graph's updates over a run: how many, the time of each (``total``, milliseconds) and of
    each phase over the updates it ran in (``factors``, ``solve``, ``estimate``, ``marginal``, and the
    window's ``cut`` and ``rebuild`` made before it; ``counts``: in how many)."""

    updates: int
    total: PhaseTiming
    phases: dict[str, PhaseTiming]
    counts: dict[str, int]


def graph_update_timing(per_update: dict[str, list[float]]) -> GraphUpdateTiming | None:
    """:class:`GraphUpdateTiming` from each update's seconds by phase (``total`` in every update, a phase
    only in those it ran in); None without an update."""
    total = per_update.get("total", [])
    if not total:
        return None
    summary = frame_timing_summary(per_update)
    phases = {k: v for k, v in summary.items() if k != "total"}
    return GraphUpdateTiming(updates=len(total), total=summary["total"], phases=phases, counts={k: len(per_update[k]) for k in phases})


def resident_memory_mb() -> float:
    """This process's resident memory now, MiB (Linux ``/proc/self/statm``; NaN elsewhere)."""
    import os

    try:
        with open("/proc/self/statm") as f:
            pages = int(f.read().split()[1])
    except (OSError, ValueError, IndexError):
        return float("nan")
    return pages * os.sysconf("SC_PAGE_SIZE") / 2**20


def machine_description() -> str:
    import os

    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    return f"{cpu}, {os.cpu_count()} cores, Python {platform.python_version()}"


def format_table(headers: list[str], rows: list[list], title: str = "") -> str:
    """A plain-text table with right-aligned columns."""
    cells = [[str(h) for h in headers]] + [[c if isinstance(c, str) else f"{c:.4g}" if isinstance(c, float) else str(c) for c in row] for row in rows]
    widths = [max(len(r[i]) for r in cells) for i in range(len(headers))]
    lines = []
    if title:
        lines.append(title)
    lines.append("  ".join(h.rjust(w) for h, w in zip(cells[0], widths)))
    lines.append("  ".join("-" * w for w in widths))
    for r in cells[1:]:
        lines.append("  ".join(c.rjust(w) for c, w in zip(r, widths)))
    return "\n".join(lines)
