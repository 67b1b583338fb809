"""The live pipeline shown in the viewer: a listener that hands each update, with the front end's
searches and the points tracked, to :class:`~dem_graph.viz.rerun_viewer.RerunViewer`."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from dem_graph.datasets.base import GroundTruth
from dem_graph.frontend.frontend import PointKind
from dem_graph.pipeline.live import LivePipeline, LiveUpdate
from dem_graph.viz.map_view import scan_returns_world
from dem_graph.viz.rerun_viewer import RerunViewer

LASER_KINDS = (int(PointKind.LASER),)


@dataclass(frozen=True)
class ViewerOptions:
    """Where a run is shown: a rerun viewer started for it (``spawn``), a recording file, or both."""

    spawn: bool = False
    record_path: Path | None = None
    colour_by: str = "height"  # the map surfaces' colour: "height", or "sigma" (the height's standard deviation)


class ViewerListener:
    """Streams a :class:`LivePipeline` to rerun: ``spawn`` a viewer, and/or save ``record_path`` (.rrd)."""

    def __init__(self, pipeline: LivePipeline, options: ViewerOptions, truth: GroundTruth | None = None):
        self.pipeline = pipeline
        live_map = pipeline.map
        self.viewer = RerunViewer(
            pipeline.name, spawn=options.spawn, record_path=options.record_path, colour_by=options.colour_by,
            global_map=lambda: live_map.global_dem(traversability_window=None) if live_map.grid.n_kept else None,
        )
        self._scans_shown = 0  # the live map's scans whose returns were shown
        frontend = getattr(pipeline.estimator, "frontend", None)
        if frontend is not None:
            frontend.record_view = True  # the searches of each frame, for the image
        if truth is not None:
            self.viewer.log_truth(truth.trajectory.positions_xyz)

    def __call__(self, update: LiveUpdate) -> None:
        est = self.pipeline.estimator
        frontend = getattr(est, "frontend", None)
        view = frontend.last_view if frontend is not None else None
        tracked = view.arrays() if view is not None and view.t_s == update.t_s else None
        _, xyz = est.live_points()
        returns_xyz, self._scans_shown = scan_returns_world(self.pipeline.map, self._scans_shown)
        self.viewer.log_frame(update.t_s, update.image, tracked, LASER_KINDS, update.local.elevation, update.T_world_body, xyz, local_map=update.local, returns_xyz=returns_xyz)

    def close(self) -> None:
        self.viewer.close()


__all__ = ["ViewerListener", "ViewerOptions"]
