"""The live points' patches in arrays, one slot per point, for a frame's compiled template passes.

Each frame warps every live point's stored region into its template. Gathered from the points one by
one, the regions, centres and source camera poses cost a list and a stack a frame (1.9 MB of regions
copied at 500 points); held here, the compiled passes read them by slot.
"""

from __future__ import annotations

import numpy as np

from dem_graph.frontend.tracker import Patch


class PatchStore:
    """Regions (float32, side x side), centres (pixels, source image) and source camera poses
    (``T_world_cam``) of the patches put in, by point id; a removed point's slot is used again."""

    def __init__(self, region_side_px: int, capacity: int = 64):
        self.regions = np.zeros((capacity, region_side_px, region_side_px), dtype=np.float32)
        self.centers_px = np.zeros((capacity, 2))
        self.T_world_cam_source = np.tile(np.eye(4), (capacity, 1, 1))
        self._slot: dict[int, int] = {}
        self._free: list[int] = list(range(capacity - 1, -1, -1))

    def __len__(self) -> int:
        return len(self._slot)

    def put(self, point_id: int, patch: Patch, T_world_cam_source: np.ndarray) -> None:
        """The point's patch (a new one, or one that replaces its last) and the camera pose it was taken from."""
        slot = self._slot.get(point_id)
        if slot is None:
            if not self._free:
                self._grow()
            slot = self._slot[point_id] = self._free.pop()
        self.regions[slot] = patch.region_f32
        self.centers_px[slot] = patch.center_px
        self.T_world_cam_source[slot] = T_world_cam_source

    def remove(self, point_id: int) -> None:
        """The point's slot freed (nothing if it has none)."""
        slot = self._slot.pop(point_id, None)
        if slot is not None:
            self._free.append(slot)

    def slots(self, point_ids) -> np.ndarray:
        """(n,) int64 slots of the points (each must have been put and not removed)."""
        slot = self._slot
        return np.fromiter((slot[p] for p in np.asarray(point_ids).tolist()), dtype=np.int64, count=len(point_ids))

    def _grow(self) -> None:
        n = len(self.regions)
        self.regions = np.concatenate([self.regions, np.zeros_like(self.regions)])
        self.centers_px = np.concatenate([self.centers_px, np.zeros_like(self.centers_px)])
        self.T_world_cam_source = np.concatenate([self.T_world_cam_source, np.tile(np.eye(4), (n, 1, 1))])
        self._free.extend(range(2 * n - 1, n - 1, -1))


__all__ = ["PatchStore"]
