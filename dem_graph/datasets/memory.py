"""A :class:`Sequence` held in memory: events in a list (for tests, notebooks and replays)."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from dem_graph.datasets.base import GroundTruth, Sequence
from dem_graph.datasets.events import Event, ImuSample, Odometry
from dem_graph.geometry.rig import SensorRig


class InMemorySequence(Sequence):
    def __init__(self, rig: SensorRig, events: list[Event], T_world_body_initial: np.ndarray, t_start_s: float, ground_truth: GroundTruth | None = None, name: str = "in-memory"):
        self._rig = rig
        self._events = list(events)
        self._T0 = np.array(T_world_body_initial, dtype=float)
        self._t0 = float(t_start_s)
        self._gt = ground_truth
        self.name = name

    @classmethod
    def record(cls, sequence: Sequence) -> InMemorySequence:
        """Read every event of ``sequence`` once and keep them."""
        return cls(sequence.rig, list(sequence.events()), sequence.T_world_body_initial, sequence.t_start_s, sequence.ground_truth, sequence.name)

    def replace_events(self, events: list[Event]) -> InMemorySequence:
        return InMemorySequence(self._rig, events, self._T0, self._t0, self._gt, self.name)

    @property
    def rig(self) -> SensorRig:
        return self._rig

    @property
    def t_start_s(self) -> float:
        return self._t0

    @property
    def T_world_body_initial(self) -> np.ndarray:
        return self._T0.copy()

    @property
    def ground_truth(self) -> GroundTruth | None:
        return self._gt

    @property
    def has_odometry(self) -> bool:
        return any(isinstance(e, Odometry) for e in self._events)

    @property
    def has_imu(self) -> bool:
        return any(isinstance(e, ImuSample) for e in self._events)

    def event_count(self) -> int:
        return len(self._events)

    def events(self) -> Iterator[Event]:
        return iter(self._events)
