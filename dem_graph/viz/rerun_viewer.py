"""A live view of a run in rerun (``pip install dem-graph[viewer]``), after the paper's Fig. 6.

Entities, on the ``time`` timeline (seconds, the frames' times):

- ``camera/image``: the frame, with ``camera/image/laser_points`` (orange) and
  ``camera/image/camera_points`` (cyan): the points the front end matched, and
  ``camera/image/search_regions``: the regions it searched, as boxes around the predicted pixels;
- ``local_map/height``: the live local DEM as a colour image (ahead is up, left is left; heights
  from ``height_range_m``, black where no cell is known);
- ``world/vehicle``: the body pose; ``world/trajectory``: the estimated path so far;
  ``world/map_points``: the points tracked now; ``world/truth``: the true path, where the dataset
  has it (static).

:class:`RerunViewer` streams to a viewer it starts (``spawn``), or saves a recording (``record_path``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dem_graph.errors import DemGraphError

LASER_COLOR = (255, 140, 0)
CAMERA_COLOR = (0, 200, 255)
TRUTH_COLOR = (60, 200, 60)
ESTIMATE_COLOR = (230, 60, 60)


def _rerun():
    try:
        import rerun as rr
    except ImportError:
        raise DemGraphError("the viewer needs rerun: pip install 'dem-graph[viewer]'") from None
    return rr


def height_image(elevation: np.ndarray, height_range_m: tuple[float, float]) -> np.ndarray:
    """A local map's elevation (rows left to right across the heading, columns ahead) as an RGB
    image with ahead up and left on the left (viridis; black where unknown)."""
    from matplotlib import colormaps

    z = np.asarray(elevation, dtype=float).T[::-1]  # rows: far to near; columns: left to right
    lo, hi = height_range_m
    known = np.isfinite(z)
    rgb = (colormaps["viridis"](np.clip((np.where(known, z, lo) - lo) / (hi - lo), 0.0, 1.0))[..., :3] * 255).astype(np.uint8)
    rgb[~known] = 0
    return rgb


def blueprint():
    """The viewer's layout: the camera over the local map on the left, the world in 3D on the right,
    following the latest frame."""
    import rerun.blueprint as rrb

    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(rrb.Spatial2DView(name="camera", origin="/camera"), rrb.Spatial2DView(name="local map", origin="/local_map"), row_shares=[3, 2]),
            rrb.Spatial3DView(name="world", origin="/world"),
            column_shares=[2, 3],
        ),
        rrb.TimePanel(timeline="time", play_state="following"),
    )


class RerunViewer:
    """Logs frames to rerun (see the module)."""

    def __init__(self, name: str = "dem_graph", spawn: bool = False, record_path: str | Path | None = None, height_range_m: tuple[float, float] = (-0.3, 0.3), trajectory_every: int = 10):
        if not spawn and record_path is None:
            raise DemGraphError("the viewer needs somewhere to go: spawn a viewer, or give a recording file")
        rr = _rerun()
        self.rr = rr
        self.stream = rr.RecordingStream("dem_graph")  # a new recording id for every run
        self.stream.log("run", rr.TextDocument(f"dem_graph run: {name}"), static=True)
        layout = blueprint()
        if record_path is not None:
            path = Path(record_path)
            if not path.parent.is_dir():
                raise DemGraphError(f"{path.parent}: folder not found for the recording")
            self.stream.save(path, default_blueprint=layout)
        if spawn:
            self.stream.spawn(connect=record_path is None, default_blueprint=layout)
        self.height_range_m = height_range_m
        self.trajectory_every = int(trajectory_every)
        self._positions: list[np.ndarray] = []
        self.frames = 0

    def log_truth(self, positions_xyz: np.ndarray) -> None:
        self.stream.log("world/truth", self.rr.LineStrips3D([np.asarray(positions_xyz, dtype=np.float32)], colors=[TRUTH_COLOR]), static=True)

    def log_frame(
        self,
        t_s: float,
        image: np.ndarray | None,
        tracked: dict[str, np.ndarray] | None,
        laser_kinds: tuple[int, ...],
        local_elevation: np.ndarray,
        T_world_body: np.ndarray,
        points_xyz: np.ndarray,
    ) -> None:
        """One frame: the image with its tracked points (``tracked``: a
        :class:`~dem_graph.frontend.frontend.TrackedView`'s arrays; the kinds in ``laser_kinds``
        are laser points), the local map's elevation, the pose and the live points."""
        rr, s = self.rr, self.stream
        s.set_time("time", duration=float(t_s))
        if image is not None:
            s.log("camera/image", rr.Image(np.asarray(image)))
        if tracked is not None and len(tracked["kind"]):
            laser = np.isin(tracked["kind"], laser_kinds)
            found = np.all(np.isfinite(tracked["uv_px"]), axis=1)
            s.log("camera/image/laser_points", rr.Points2D(tracked["uv_px"][laser & found], colors=LASER_COLOR, radii=2.0))
            s.log("camera/image/camera_points", rr.Points2D(tracked["uv_px"][~laser & found], colors=CAMERA_COLOR, radii=2.0))
            colors = np.where(laser[:, None], LASER_COLOR, CAMERA_COLOR).astype(np.uint8)
            s.log("camera/image/search_regions", rr.Boxes2D(centers=tracked["uv_pred_px"], half_sizes=np.maximum(tracked["search_half_size_px"], 0.5), colors=colors))
        s.log("local_map/height", rr.Image(height_image(local_elevation, self.height_range_m)))
        T = np.asarray(T_world_body, dtype=float)
        s.log("world/vehicle", rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3]))
        s.log("world/map_points", rr.Points3D(np.asarray(points_xyz, dtype=np.float32).reshape(-1, 3), colors=CAMERA_COLOR, radii=0.02))
        self._positions.append(T[:3, 3].astype(np.float32))
        self.frames += 1
        if (self.frames - 1) % self.trajectory_every == 0:
            self._log_trajectory()

    def _log_trajectory(self) -> None:
        self.stream.log("world/trajectory", self.rr.LineStrips3D([np.array(self._positions)], colors=[ESTIMATE_COLOR]))

    def close(self) -> None:
        if self._positions:
            self._log_trajectory()
        self.stream.flush()
        self.stream.disconnect()


def recording_rows(path: str | Path) -> dict[str, int]:
    """Rows logged per entity in a recording file, read back with rerun's own reader."""
    _rerun()
    from rerun.chunk import RrdReader

    rows: dict[str, int] = {}
    for chunk in RrdReader(str(path)).store().stream():
        rows[chunk.entity_path] = rows.get(chunk.entity_path, 0) + chunk.num_rows
    return rows


__all__ = ["RerunViewer", "height_image", "recording_rows"]
