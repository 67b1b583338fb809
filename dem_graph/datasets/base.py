"""The dataset interface that the simulator, the folder format, KITTI and rosbag implement."""

from __future__ import annotations

import abc
import queue
import threading
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from typing import TypeVar

import numpy as np

from dem_graph.datasets.events import Event, LaserScan
from dem_graph.geometry.grid import ElevationGrid
from dem_graph.geometry.rig import SensorRig
from dem_graph.geometry.trajectory import Trajectory


@dataclass(frozen=True)
class GroundTruth:
    """What a dataset knows for certain, when it knows it."""

    trajectory: Trajectory  # T_world_body, queryable at any time inside its span
    elevation: ElevationGrid | None = None  # the terrain, world metres


def first_not_increasing(t) -> int | None:
    """The first index whose time is not after the one before it (times must increase strictly), or None."""
    t = np.asarray(t, dtype=float)
    bad = np.flatnonzero(np.diff(t) <= 0) if len(t) > 1 else ()
    return int(bad[0]) + 1 if len(bad) else None


_Item = TypeVar("_Item")
_END = object()


def read_ahead(items: Iterable[_Item], depth: int = 4) -> Iterator[_Item]:
    """The items of ``items`` in order, produced up to ``depth`` ahead by a background thread.

    For images: OpenCV's decoding releases the GIL, so the next frames are read while the estimator works
    on this one (a seventh of an in-process run's time on ``paper`` was PNG decoding). An exception raised
    while producing an item is raised here, when that item is reached; stopping early stops the thread.
    """
    slots: queue.Queue = queue.Queue(maxsize=depth)
    stop = threading.Event()

    def put(entry) -> bool:
        while not stop.is_set():
            try:
                slots.put(entry, timeout=0.1)
                return True
            except queue.Full:
                continue
        return False

    def produce() -> None:
        try:
            for item in items:
                if not put((item, None)):
                    return
        except BaseException as exc:  # handed to the consumer, raised there
            put((None, exc))
            return
        put((_END, None))

    thread = threading.Thread(target=produce, name="read-ahead", daemon=True)
    thread.start()
    try:
        while True:
            item, exc = slots.get()
            if exc is not None:
                raise exc
            if item is _END:
                return
            yield item
    finally:
        stop.set()
        thread.join()


# the streams every reader merges, in this order (:func:`merged_order`'s stream numbers)
ODOMETRY_STREAM, LASER_STREAM, CAMERA_STREAM, IMU_STREAM = 0, 1, 2, 3  # at equal times, in this order


def merged_order(*stream_times) -> list[tuple[int, int]]:
    """``(stream, index)`` of every item of the given time arrays, in time order; at equal times the
    stream given first comes first, then the lower index (the order every reader replays events in)."""
    times = np.concatenate([np.asarray(t, dtype=float).reshape(-1) for t in stream_times]) if stream_times else np.zeros(0)
    kinds = np.concatenate([np.full(len(t), k) for k, t in enumerate(stream_times)]) if stream_times else np.zeros(0, dtype=int)
    indices = np.concatenate([np.arange(len(t)) for t in stream_times]) if stream_times else np.zeros(0, dtype=int)
    order = np.lexsort((indices, kinds, times))
    return list(zip(kinds[order].tolist(), indices[order].tolist()))


class Sequence(abc.ABC):
    """A time-ordered stream of camera frames, laser scans and (optionally) odometry.

    Implementations must yield events in non-decreasing time order, give ``T_world_body`` at
    ``t_start_s`` (the estimate is anchored there), and say whether ground truth is known.
    """

    name: str = "sequence"

    @property
    @abc.abstractmethod
    def rig(self) -> SensorRig: ...

    @property
    @abc.abstractmethod
    def t_start_s(self) -> float:
        """Time of the initial pose; no event is earlier."""

    @property
    @abc.abstractmethod
    def T_world_body_initial(self) -> np.ndarray:
        """4x4 body pose at :attr:`t_start_s`."""

    @property
    def ground_truth(self) -> GroundTruth | None:
        return None

    @property
    def initial_speed_mps(self) -> float | None:
        """The log's own estimate of its starting speed (m/s), for a run without odometry that asks for
        it (``motion.initial_speed_from_dataset``); None when the dataset has none."""
        return None

    def open_options(self) -> dict:
        """How to open this dataset again beyond its path (``format`` and the fields of
        :class:`~dem_graph.datasets.open.DatasetOptions` it used, plain values), recorded in a run's
        ``metrics.json`` so that ``dem-graph dem`` and ``evaluate`` read the same data. None by default."""
        return {}

    def run_settings(self) -> dict:
        """Run-configuration values this kind of log needs (a nested mapping as in ``config.yaml``),
        applied over the defaults and under the user's own configuration file. None by default."""
        return {}

    @property
    def has_odometry(self) -> bool:
        return False

    def skipped_messages(self) -> dict[str, int]:
        """How many of the log's messages the reader skipped, by stream and kind (``odometry_nonfinite``,
        ``camera_stamp_not_after``, ``laser_wrong_shape``, ...; :class:`~dem_graph.datasets.checks.SkippedMessages`),
        kept in ``metrics.json``. None skipped by default."""
        return {}

    @property
    def has_imu(self) -> bool:
        """Whether :meth:`events` yields :class:`~dem_graph.datasets.events.ImuSample` events (in the rig's ``imu`` frame)."""
        return False

    def event_count(self) -> int | None:
        """How many events :meth:`events` yields, when known cheaply (for progress bars)."""
        return None

    def laser_scans(self) -> tuple[np.ndarray, np.ndarray]:
        """Every scan's time (n,) and ranges (n, beams), metres, NaN for no return.

        This default reads every event (images included); datasets that can, read the scans alone.
        """
        scans = [e for e in self.events() if isinstance(e, LaserScan)]
        beams = self.rig.laser.beams.count
        if not scans:
            return np.zeros(0), np.zeros((0, beams))
        return np.array([s.t_s for s in scans]), np.array([s.ranges_m for s in scans], dtype=float)

    @abc.abstractmethod
    def events(self) -> Iterator[Event]:
        """Every event in time order. Each call starts from the beginning."""

    def __iter__(self) -> Iterator[Event]:
        return self.events()
