"""Events of several live streams put back in time order, within a bounded wait.

Each stream's messages come in their own order, but the streams arrive interleaved as the network
and the drivers deliver them: a camera frame stamped ``t`` may come before the scan stamped just
before ``t``. The estimators take events in time order (at equal times odometry, then laser,
camera and IMU, as a bag is read), so :class:`ReorderBuffer` holds each event until no stream can
still deliver one before it, and at most ``window_s`` of wall time. A stream can no longer deliver
one before ``t`` once it has delivered a stamp at or after ``t``, or, when its period is known
(the rig's rates), once its newest stamp is less than half a period before ``t`` (its next message
is due after ``t``): a frame does not wait for the next scan when the last one is recent enough
that none can come between. A stream silent for ``silent_s`` is not waited for, and the laser is not
ordered against the odometry and the IMU (:data:`INDEPENDENT`): a scan goes to the next frame and
into the map with the pose window of the last one, whatever odometry or IMU sample came between,
so an odometry message the estimator holds a frame for does not wait for the next scan.

An event that comes after a later one was released (its stream was waited for ``window_s`` and did
not deliver in time) is released at once, out of order, and counted as late (:attr:`late`): the
live pipeline takes a scan or an odometry message behind the frames; a camera frame older than the
last frame released is the pipeline's to skip.
"""

from __future__ import annotations

import heapq
import itertools
from collections import Counter
from dataclasses import dataclass, field

STREAM_RANK = {"odometry": 0, "laser": 1, "camera": 2, "imu": 3}
"""The order of events at equal times (a bag's: :func:`~dem_graph.datasets.base.merged_order`)."""


INDEPENDENT = frozenset({frozenset({"laser", "odometry"}), frozenset({"laser", "imu"})})
"""Pairs of streams whose order against each other changes nothing (see the module)."""


@dataclass(order=True)
class _Held:
    t_s: float
    rank: int
    seq: int
    arrived_s: float = field(compare=False)
    stream: str = field(compare=False)
    event: object = field(compare=False)


class ReorderBuffer:
    """Holds events of the streams of :data:`STREAM_RANK` until they can go in time order (see the module).

    :meth:`push` an event with its stream and arrival time; :meth:`pop_ready` gives those that may
    go now, in order."""

    def __init__(self, window_s: float = 0.1, silent_s: float = 1.0, periods_s: dict[str, float] | None = None):
        self.window_s, self.silent_s = float(window_s), float(silent_s)
        self.periods_s = {k: float(v) for k, v in (periods_s or {}).items() if v and v > 0}  # each stream's period, seconds
        self._heap: list[_Held] = []
        self._seq = itertools.count()
        self._high: dict[str, float] = {}  # each stream's newest stamp
        self._heard: dict[str, float] = {}  # each stream's newest arrival, wall seconds
        self._released = (-float("inf"), -1)  # (t_s, rank) of the newest event released in order
        self.late = Counter()  # by stream: events that came after a later one had gone
        self.waited_out = Counter()  # by stream: events released because the wait ran out, not because every stream had caught up
        self.released = Counter()

    def __len__(self) -> int:
        return len(self._heap)

    def push(self, stream: str, t_s: float, event, arrived_s: float) -> list:
        """Take ``event`` of ``stream`` stamped ``t_s``; returns it at once (a list of one) when it
        comes after a later event was released (late), else nothing (it waits for :meth:`pop_ready`)."""
        rank = STREAM_RANK[stream]
        self._heard[stream] = arrived_s
        self._high[stream] = max(self._high.get(stream, -float("inf")), t_s)
        if (t_s, rank) < self._released:
            self.late[stream] += 1
            self.released[stream] += 1
            return [event]
        heapq.heappush(self._heap, _Held(t_s, rank, next(self._seq), arrived_s, stream, event))
        return []

    def pop_ready(self, now_s: float, flush: bool = False) -> list:
        """The events that may go at wall time ``now_s``, in time order (all of them with ``flush``)."""
        out = []
        while self._heap:
            head = self._heap[0]
            waited_out = now_s - head.arrived_s >= self.window_s
            if not (flush or waited_out or self._caught_up(head, now_s)):
                break
            heapq.heappop(self._heap)
            if waited_out and not flush and not self._caught_up(head, now_s):
                self.waited_out[head.stream] += 1
            self._released = (head.t_s, head.rank)
            self.released[head.stream] += 1
            out.append(head.event)
        return out

    def holds(self, stream: str) -> bool:
        """Whether an event of ``stream`` waits here."""
        return any(h.stream == stream for h in self._heap)

    def newest(self, stream: str) -> float | None:
        """The newest stamp pushed for ``stream``, held or given (None before its first event)."""
        return self._high.get(stream)

    def next_deadline_s(self) -> float | None:
        """The wall time at which the oldest event held goes whatever comes (None when none is held)."""
        return min(h.arrived_s for h in self._heap) + self.window_s if self._heap else None

    def _caught_up(self, head: _Held, now_s: float) -> bool:
        """Whether no stream heard from in the last ``silent_s`` can still deliver an event before ``head``."""
        for stream, high in self._high.items():
            if stream == head.stream or now_s - self._heard[stream] > self.silent_s or frozenset({stream, head.stream}) in INDEPENDENT:
                continue
            if high < head.t_s and not high + 0.5 * self.periods_s.get(stream, 0.0) > head.t_s:
                return False
        return True


__all__ = ["INDEPENDENT", "STREAM_RANK", "ReorderBuffer"]
