"""The graph estimator's live points: what its online filter tracks and its graph client keeps in
step with the smoother."""

from __future__ import annotations

import numpy as np


class LivePoints:
    """The points being tracked: ids, world positions and each one's 3x3 information
    (its seed's plus its keyframe observations', poses held fixed); the graph landmark each one
    follows now and the patch segment it belongs to."""

    def __init__(self):
        self.ids = np.zeros(0, dtype=np.int64)
        self.landmark = np.zeros(0, dtype=np.int64)
        self.segment = np.zeros(0, dtype=np.int64)
        self.X = np.zeros((0, 3))
        self.info = np.zeros((0, 3, 3))
        self.n_since_keyframe = np.zeros(0, dtype=np.int64)  # inlier frames since the last keyframe observation

    def __len__(self) -> int:
        return len(self.ids)

    def add(self, ids, landmarks, X_world, Sigma_world) -> None:
        self.ids = np.concatenate([self.ids, np.asarray(ids, dtype=np.int64)])
        self.landmark = np.concatenate([self.landmark, np.asarray(landmarks, dtype=np.int64)])
        self.segment = np.concatenate([self.segment, np.zeros(len(ids), dtype=np.int64)])
        self.X = np.concatenate([self.X, np.asarray(X_world, dtype=float).reshape(-1, 3)])
        self.info = np.concatenate([self.info, np.linalg.inv(np.asarray(Sigma_world, dtype=float).reshape(-1, 3, 3))])
        self.n_since_keyframe = np.concatenate([self.n_since_keyframe, np.zeros(len(ids), dtype=np.int64)])

    def follow(self, i: int, landmark: int, segment: int, info: np.ndarray) -> None:
        """Point ``i`` now follows ``landmark`` (its patch segment ``segment``), with the 3x3
        information ``info``; no frame has tracked it since that landmark's last keyframe observation."""
        self.landmark[i], self.segment[i] = landmark, segment
        self.info[i] = info
        self.n_since_keyframe[i] = 0

    def keep(self, mask: np.ndarray) -> None:
        self.ids, self.X, self.info = self.ids[mask], self.X[mask], self.info[mask]
        self.landmark, self.segment = self.landmark[mask], self.segment[mask]
        self.n_since_keyframe = self.n_since_keyframe[mask]

    def covariances(self) -> np.ndarray:
        return np.linalg.inv(self.info) if len(self) else np.zeros((0, 3, 3))


__all__ = ["LivePoints"]
