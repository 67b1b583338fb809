"""Sensor faults put into a log on purpose, to measure how an estimator survives them.

:class:`FaultySequence` wraps any :class:`~dem_graph.datasets.base.Sequence` and replays it with:

- ``camera_gaps``: time intervals ``[t0, t1)`` with no camera frame (a blackout: the driver delivered
  nothing);
- ``laser_gaps``: intervals with no laser scan;
- ``odometry_gaps``: intervals with no odometry message;
- ``black_frames``: intervals whose frames arrive but are black (a lens cap, a dead exposure).

Everything else (rig, start pose, ground truth, odometry) is the wrapped log's. Faults that leave
no camera frame are refused (no run can start without one); an interval that takes nothing out (it
lies outside the log's stream) is written with a warning. Written with
:func:`~dem_graph.datasets.folder.write_folder_dataset` (``dem-graph degrade``), the result is an
ordinary dataset folder whose frames and scans are renumbered; the ground truth still covers the whole
log, so the estimate is judged over the gap too.
"""

from __future__ import annotations

import logging
import math
import shutil
from collections.abc import Iterator
from collections.abc import Sequence as Seq
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from dem_graph.datasets.base import GroundTruth, Sequence
from dem_graph.datasets.events import CameraFrame, Event, ImuSample, LaserScan, Odometry
from dem_graph.datasets.folder import write_folder_dataset
from dem_graph.errors import DatasetError, DemGraphError

log = logging.getLogger(__name__)

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
        self.spans_s: dict[type, list[float]] = {}  # each stream's first and last time in the wrapped log (set by events)
        self.hits: dict[tuple[str, Interval], int] = {}  # events each interval took out or spoiled (set by events)

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

    @property
    def has_imu(self) -> bool:
        return self.base.has_imu

    def run_settings(self) -> dict:
        return self.base.run_settings()

    def skipped_messages(self) -> dict[str, int]:
        return self.base.skipped_messages()

    def event_count(self) -> int | None:
        return self.base.event_count()

    def events(self) -> Iterator[Event]:
        """The wrapped log's events with the faults put in, renumbered per stream. Raises
        :class:`FaultSequenceError` at the end when the faults left no camera frame of the log's."""
        f = self.faults
        counts = {CameraFrame: 0, LaserScan: 0, Odometry: 0, ImuSample: 0}
        self.spans_s, self.hits = {}, {}
        for event in self.base.events():
            t = event.t_s
            kind = type(event)
            span = self.spans_s.setdefault(kind, [t, t])
            span[1] = t
            if isinstance(event, CameraFrame):
                if self._hit("camera_gaps", t):
                    continue
                if self._hit("black_frames", t):
                    event = replace(event, image=np.zeros_like(event.image))
            elif isinstance(event, LaserScan) and self._hit("laser_gaps", t):
                continue
            elif isinstance(event, Odometry) and self._hit("odometry_gaps", t):
                continue
            yield replace(event, index=counts[kind])
            counts[kind] += 1
        if counts[CameraFrame] == 0 and CameraFrame in self.spans_s:
            raise FaultSequenceError(_no_frame_left(f.camera_gaps, self.spans_s[CameraFrame]))

    def _hit(self, name: str, t_s: float) -> bool:
        """Whether ``t_s`` lies in one of the faults' ``name`` intervals (counted for :meth:`warn_unused`)."""
        for interval in getattr(self.faults, name):
            if interval[0] <= t_s < interval[1]:
                self.hits[name, interval] = self.hits.get((name, interval), 0) + 1
                return True
        return False

    def warn_unused(self) -> None:
        """After :meth:`events` went through the log: one warning for each interval that took nothing out."""
        streams = {"camera_gaps": CameraFrame, "black_frames": CameraFrame, "laser_gaps": LaserScan, "odometry_gaps": Odometry}
        for name, kind in streams.items():
            for t0, t1 in getattr(self.faults, name):
                if self.hits.get((name, (t0, t1))):
                    continue
                span = self.spans_s.get(kind)
                one, many = _STREAM[kind]
                where = f"the log's {many} span {span[0]:.3f} to {span[1]:.3f} s" if span else f"the log has no {one}"
                log.warning("%s %g:%g s holds no %s (%s): the fault changes nothing", _FAULT[name], t0, t1, one, where)


_STREAM = {CameraFrame: ("camera frame", "camera frames"), LaserScan: ("laser scan", "laser scans"), Odometry: ("odometry message", "odometry messages")}
_FAULT = {"camera_gaps": "camera gap", "black_frames": "black frames", "laser_gaps": "laser gap", "odometry_gaps": "odometry gap"}


def _no_frame_left(camera_gaps: tuple[Interval, ...], span_s) -> str:
    gaps = ", ".join(f"{t0:g}:{t1:g}" for t0, t1 in camera_gaps)
    return f"the camera gaps ({gaps} s) take out every camera frame of the log ({span_s[0]:.3f} to {span_s[1]:.3f} s): a run needs at least one"


def write_faulty_dataset(base: Sequence, faults: Faults, out_dir, overwrite: bool = False):
    """Write ``base`` with ``faults`` as a dataset folder at ``out_dir`` and return its path.

    A non-empty ``out_dir`` is refused unless ``overwrite``, which replaces it (never the log being read).
    Faults that leave no camera frame are refused (:class:`FaultSequenceError`; before anything is
    written when ``base`` tells its frames' times, as a dataset folder does); an interval that takes
    nothing out is warned of.
    """
    out = Path(out_dir)
    source = getattr(base, "path", None)
    if source is not None and out.resolve() == Path(source).resolve():
        raise DatasetError(out, "the output folder is the dataset being read")
    camera_times = getattr(base, "camera_times", None)
    if camera_times is not None:
        t_s = np.asarray(camera_times())
        if len(t_s) and all(_inside(t, faults.camera_gaps) for t in t_s):
            raise FaultSequenceError(_no_frame_left(faults.camera_gaps, (t_s[0], t_s[-1])))
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        if not overwrite:
            raise DatasetError(out, "output folder exists and is not empty (use --overwrite)")
        shutil.rmtree(out)
    faulty = FaultySequence(base, faults)
    try:
        path = write_folder_dataset(faulty, out, progress_desc=f"writing {base.name} with faults")
    except FaultSequenceError:
        shutil.rmtree(out, ignore_errors=True)  # empty or new before: nothing of the user's is lost
        raise
    faulty.warn_unused()
    return path
