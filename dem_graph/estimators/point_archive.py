"""The points the front end has dropped, each kept with its last estimate, and a run's result from
them and the live points.

A point leaves the front end when it is behind the camera, out of the image, lost, or (the graph
estimator) marginalised. :class:`PointArchive` drops it from the front end and keeps its id, kind,
covariance, number of frames tracked and creation time, with its world position then, or without
one when the estimator knows a better one at the end (the graph's latest estimate of its landmark).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from dem_graph.estimators.base import EstimatorResult, FrameRecord
from dem_graph.frontend.frontend import FrontEnd


class PointArchive:
    def __init__(self, frontend: FrontEnd):
        self._frontend = frontend
        # per point, in the order dropped: id, kind, X_world (None: asked for at the end), covariance, n_tracked, created_t_s
        self._points: list[tuple[int, int, np.ndarray | None, np.ndarray, int, float]] = []

    def __len__(self) -> int:
        return len(self._points)

    def archive(self, point_id: int, reason: str, covariance: np.ndarray, xyz: np.ndarray | None = None) -> None:
        """Drop point ``point_id`` from the front end (counted as ``dropped_<reason>``) and keep it
        with its 3x3 world covariance and its world position ``xyz`` (None: given by :meth:`result`)."""
        track = self._frontend.drop(point_id, reason)
        self._points.append((track.point_id, track.kind, None if xyz is None else np.array(xyz, dtype=float), covariance, track.n_tracked, track.created_t_s))

    def since(self, start: int, xyz_of: Callable[[int], np.ndarray | None] | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
        """The points archived from the ``start``-th on: world positions (m,3), covariances (m,3,3)
        and creation times (m,), and the count so far. A point kept without a position takes
        ``xyz_of(point_id)``; without one (None) it is left out."""
        xyz, cov, t = [], [], []
        for pid, _, X, covariance, _, created_t_s in self._points[start:]:
            X = X if X is not None else (xyz_of(pid) if xyz_of is not None else None)
            if X is None:
                continue
            xyz.append(X)
            cov.append(covariance)
            t.append(created_t_s)
        n = len(xyz)
        return np.asarray(xyz, dtype=float).reshape(n, 3), np.asarray(cov, dtype=float).reshape(n, 3, 3), np.asarray(t, dtype=float), len(self._points)

    def drop_points(
        self, point_ids: np.ndarray, X_world: np.ndarray, T_world_body: np.ndarray, estimate: Callable[[int], tuple[np.ndarray, np.ndarray | None]]
    ) -> tuple[np.ndarray, np.ndarray]:
        """Archive the live points (ids, world positions (n,3)) the front end drops from the pose
        ``T_world_body``, in index order, each with ``estimate(i)``: its ``(covariance, xyz)`` as for
        :meth:`archive`. Returns the mask of the points kept and their pixels (m,2)."""
        return self._frontend.drop_points(point_ids, X_world, T_world_body, lambda i, reason: self.archive(int(point_ids[i]), reason, *estimate(i)))

    def result(
        self,
        name: str,
        frames: Sequence[FrameRecord],
        live_ids: np.ndarray,
        live_xyz: Callable[[int], np.ndarray],
        live_covariance: Callable[[int], np.ndarray],
        archived_xyz: Callable[[int], np.ndarray] | None = None,
    ) -> EstimatorResult:
        """The frames so far and every point: the archived ones in the order they were dropped (at
        ``archived_xyz(point_id)`` when kept without a position), then the live ones (``live_ids``)
        at their current estimates ``live_xyz(i)``, ``live_covariance(i)``; and the front end's counters."""
        res = EstimatorResult(name, list(frames))
        for pid, kind, xyz, covariance, n_tracked, created_t_s in self._points:
            res.points.add(pid, kind, archived_xyz(pid) if xyz is None else xyz, covariance, n_tracked, created_t_s)
        tracks = self._frontend.tracks
        for i, pid in enumerate(live_ids):
            track = tracks[int(pid)]
            res.points.add(track.point_id, track.kind, live_xyz(i), live_covariance(i), track.n_tracked, track.created_t_s)
        res.counters = self._frontend.counters.copy()
        return res


__all__ = ["PointArchive"]
