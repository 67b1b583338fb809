"""Sensor faults put into a log on purpose, to measure how an estimator survives them.

:class:`FaultySequence` wraps any :class:`~dem_graph.datasets.base.Sequence` and replays it with:

- ``camera_gaps``: time intervals ``[t0, t1)`` with no camera frame (a blackout: the driver delivered
  nothing);
- ``laser_gaps``: intervals with no laser scan;
- ``odometry_gaps``: intervals with no odometry message;
- ``black_frames``: intervals whose frames arrive but are black (a lens cap, a dead exposure).

Everything else (rig, start pose, ground truth, odometry) is the wrapped log's. Written with
:func:`~dem_graph.datasets.folder.write_folder_dataset` (``dem-graph degrade``), the result is an
ordinary dataset folder whose frames and scans are renumbered; the ground truth still covers the whole
log, so the estimate is judged over the gap too.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from collections.abc import Sequence as Seq
from dataclasses import dataclass, replace

import numpy as np

from dem_graph.datasets.base import GroundTruth, Sequence
from dem_graph.datasets.events import CameraFrame, Event, LaserScan, Odometry
from dem_graph.errors import DemGraphError

Interval = tuple[float, float]


class FaultSequenceError(DemGraphError, ValueError):
    """A fault interval that cannot be applied (empty, reversed, not finite)."""


def parse_interval(text: str) -> Interval:
    """``"T0:T1"`` (seconds) as ``(t0, t1)``; a one-line :class:`FaultSequenceError` otherwise."""
    parts = text.split(":")
    try:
        if len(parts) != 2:
            raise ValueError
        t0, t1 = float(parts[0]), float(parts[1])
    except ValueError:
        raise FaultSequenceError(f"interval {text!r}: expected T0:T1 in seconds, for example 30:31") from None
    return _checked((t0, t1))


def _checked(interval: Interval) -> Interval:
    t0, t1 = (float(v) for v in interval)
    if not (math.isfinite(t0) and math.isfinite(t1)):
        raise FaultSequenceError(f"interval {t0!r}:{t1!r}: both ends must be finite")
    if not t1 > t0:
        raise FaultSequenceError(f"interval {t0!r}:{t1!r}: the end must be after the start")
    return t0, t1


def _inside(t_s: float, intervals: Seq[Interval]) -> bool:
    return any(t0 <= t_s < t1 for t0, t1 in intervals)


@dataclass(frozen=True)
class Faults:
    """Which parts of a log to take out or spoil (seconds, the log's own clock)."""

    camera_gaps: tuple[Interval, ...] = ()
    laser_gaps: tuple[Interval, ...] = ()
    odometry_gaps: tuple[Interval, ...] = ()
    black_frames: tuple[Interval, ...] = ()

    def __post_init__(self) -> None:
        for name in ("camera_gaps", "laser_gaps", "odometry_gaps", "black_frames"):
            object.__setattr__(self, name, tuple(_checked(i) for i in getattr(self, name)))

    def describe(self) -> str:
        parts = []
        for name, label in (("camera_gaps", "no camera"), ("laser_gaps", "no laser"), ("odometry_gaps", "no odometry"), ("black_frames", "black frames")):
            for t0, t1 in getattr(self, name):
                parts.append(f"{label} {t0:g}-{t1:g} s")
        return ", ".join(parts) or "no faults"


class FaultySequence(Sequence):
    """``base`` replayed with ``faults`` (see the module text); events are renumbered per stream."""

    def __init__(self, base: Sequence, faults: Faults):
        self.base = base
        self.faults = faults
        self.name = base.name
        base_description = getattr(base, "description", "") or ""
        self.description = f"{base_description}; faults: {faults.describe()}".lstrip("; ")

    @property
    def rig(self):
        return self.base.rig

    @property
    def t_start_s(self) -> float:
        return self.base.t_start_s

    @property
    def T_world_body_initial(self) -> np.ndarray:
        return self.base.T_world_body_initial

    @property
    def ground_truth(self) -> GroundTruth | None:
        return self.base.ground_truth

    @property
    def initial_speed_mps(self) -> float | None:
        return self.base.initial_speed_mps

    @property
    def has_odometry(self) -> bool:
        return self.base.has_odometry

    def run_settings(self) -> dict:
        return self.base.run_settings()

    def event_count(self) -> int | None:
        return self.base.event_count()

    def events(self) -> Iterator[Event]:
        f = self.faults
        counts = {CameraFrame: 0, LaserScan: 0, Odometry: 0}
        for event in self.base.events():
            t = event.t_s
            if isinstance(event, CameraFrame):
                if _inside(t, f.camera_gaps):
                    continue
                if _inside(t, f.black_frames):
                    event = replace(event, image=np.zeros_like(event.image))
            elif isinstance(event, LaserScan) and _inside(t, f.laser_gaps):
                continue
            elif isinstance(event, Odometry) and _inside(t, f.odometry_gaps):
                continue
            kind = type(event)
            yield replace(event, index=counts[kind])
            counts[kind] += 1


def write_faulty_dataset(base: Sequence, faults: Faults, out_dir, overwrite: bool = False):
    """Write ``base`` with ``faults`` as a dataset folder at ``out_dir`` and return its path.

    A non-empty ``out_dir`` is refused unless ``overwrite``, which replaces it (never the log being read).
    """
    import shutil
    from pathlib import Path

    from dem_graph.datasets.folder import write_folder_dataset
    from dem_graph.errors import DatasetError

    out = Path(out_dir)
    source = getattr(base, "path", None)
    if source is not None and out.resolve() == Path(source).resolve():
        raise DatasetError(out, "the output folder is the dataset being read")
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        if not overwrite:
            raise DatasetError(out, "output folder exists and is not empty (use --overwrite)")
        shutil.rmtree(out)
    return write_folder_dataset(FaultySequence(base, faults), out, progress_desc=f"writing {base.name} with faults")
