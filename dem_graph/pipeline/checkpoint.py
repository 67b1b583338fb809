"""A run folder written as the run goes, so that Ctrl-C, a kill or a late fault keeps what was done.

An hour's run must not be lost to a keypress. :class:`RunCheckpoint` listens to the live pipeline
and, every ``checkpoint_every_s`` of wall time, writes the trajectory so far (``trajectory.tum``,
the pose each frame had when it was made) and the map points that have left the estimator
(``points.ply``). Each file is written whole under a temporary name and renamed over the old one
(an atomic rename on POSIX), so a SIGKILL at any moment leaves every file readable. The run's end
(normal, a Ctrl-C or an error) writes the whole folder over them. The saved live maps are kept in
the folder too, appended as each is saved (``live_maps.part``, :mod:`dem_graph.io.live_maps`).

:func:`stop_at_event_boundaries` makes Ctrl-C and SIGTERM (a service manager's stop) end the run
between two events, where the estimator's state is whole, so the end of the run can be written.
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import threading
import time
from pathlib import Path

import numpy as np

from dem_graph.geometry.trajectory import Trajectory
from dem_graph.io.ply import write_points_ply
from dem_graph.io.tum import write_tum
from dem_graph.pipeline.live import LivePipeline, LiveUpdate

log = logging.getLogger(__name__)


def replace_atomically(path: Path, write) -> Path:
    """``write(tmp)`` a temporary file beside ``path``, then rename it over ``path``."""
    tmp = path.with_name(f".{path.name}.part")
    write(tmp)
    os.replace(tmp, path)
    return path


class RunCheckpoint:
    """A pipeline listener that keeps ``out_dir``'s trajectory and map points current."""

    def __init__(
        self,
        pipeline: LivePipeline,
        out_dir: str | Path,
        every_s: float,
        trajectory_name: str = "trajectory.tum",
        points_name: str = "points.ply",
    ):
        self.pipeline, self.every_s = pipeline, float(every_s)
        self.trajectory_path, self.points_path = Path(out_dir) / trajectory_name, Path(out_dir) / points_name
        self._t: list[float] = []
        self._T: list[np.ndarray] = []
        self._xyz: list[np.ndarray] = []
        self._var_z: list[np.ndarray] = []
        self._created: list[np.ndarray] = []
        self._points_seen = 0
        self._last_write = time.monotonic()
        self.writes = 0

    def __call__(self, update: LiveUpdate) -> None:
        self._t.append(update.t_s)
        self._T.append(update.T_world_body)
        if time.monotonic() - self._last_write >= self.every_s:
            self.write()

    def write(self) -> None:
        """Write the trajectory and the map points so far (a failure to write stops the listener:
        the pipeline logs it and the run goes on)."""
        self._last_write = time.monotonic()
        if len(self._t) < 1:
            return
        xyz, cov, created, self._points_seen = self.pipeline.estimator.archived_points_since(self._points_seen)
        self._xyz.append(xyz)
        self._var_z.append(cov[:, 2, 2].astype(np.float32))
        self._created.append(created)
        trajectory = Trajectory.from_poses(np.asarray(self._t), np.asarray(self._T))
        replace_atomically(self.trajectory_path, lambda p: write_tum(p, trajectory))
        attributes = {"var_z_m2": np.concatenate(self._var_z), "created_t_s": np.concatenate(self._created)}
        replace_atomically(self.points_path, lambda p: write_points_ply(p, np.concatenate(self._xyz), attributes))
        self.writes += 1
        log.debug("checkpoint: %d frames, %d map points in %s", len(self._t), sum(len(x) for x in self._xyz), self.trajectory_path.parent)


class StopRequest:
    """Ctrl-C (SIGINT) and SIGTERM, asked to stop the run at the next event rather than inside one
    (an estimator stopped half-way through a frame has torn state). A second signal stops at once."""

    def __init__(self):
        self.signal_name: str | None = None

    def _handle(self, signum, frame):
        if self.signal_name is not None:
            raise KeyboardInterrupt(f"second {signal.Signals(signum).name}")
        self.signal_name = signal.Signals(signum).name
        log.warning("%s: stopping after this frame and keeping what was done (again to stop at once)", self.signal_name)

    def check(self) -> None:
        """Raise KeyboardInterrupt if a stop was asked for."""
        if self.signal_name is not None:
            raise KeyboardInterrupt(self.signal_name)


@contextlib.contextmanager
def stop_at_event_boundaries():
    """Within the block, SIGINT and SIGTERM set a :class:`StopRequest` (yielded) instead of raising
    wherever the program is (main thread only; elsewhere the signals keep their handlers). The
    previous handlers are restored after."""
    request = StopRequest()
    if threading.current_thread() is not threading.main_thread():
        yield request
        return
    previous = {sig: signal.signal(sig, request._handle) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield request
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


__all__ = ["RunCheckpoint", "StopRequest", "replace_atomically", "stop_at_event_boundaries"]
