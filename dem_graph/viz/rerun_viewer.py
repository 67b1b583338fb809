"""A live view of a run in rerun (``pip install dem-graph[viewer]``), after the paper's Fig. 6.

Entities, on the ``time`` timeline (seconds, the frames' times):

- ``camera/image``: the frame, with ``camera/image/laser_points`` (orange) and
  ``camera/image/camera_points`` (cyan): the points the front end matched, and
  ``camera/image/search_regions``: the regions it searched, as boxes around the predicted pixels;
- ``local_map/height``: the live local DEM as a colour image (ahead is up, left is left; heights
  from ``height_range_m``, black where no cell is known);
- ``world/vehicle``: the body pose; ``world/trajectory``: the estimated path so far;
  ``world/map_points``: the points tracked now; ``world/truth``: the true path, where the dataset
  has it (static);
- ``world/map/tiles/TX_TY``: the whole live map so far as a surface, a flat square per known cell at
  its height (world frame, metres), one entity per square tile of ``map_tile_cells`` cells (tile
  TX, TY: global cells ``TX * map_tile_cells`` onwards east, ``TY * map_tile_cells`` onwards
  north); every ``map_every`` frames and at the end, only the tiles whose heights or variances
  changed since they were last logged, so that the recording grows with what changes, not with the map;
- ``world/focus``: the heading frame of the frame (a transform), holding ``world/focus/surface``, the
  local map over the focus area as a surface (heights relative to the body origin, the ``elevation``
  layer as it is), and ``world/focus/outline``, the focus area's rectangle; every frame;
- ``world/scan``: the returns of the laser scans that came since the previous frame, where the live
  map placed them (world frame), logged at the frame's time when there are any.

The surfaces are coloured by height (viridis; the focus area's over ``height_range_m`` relative to
the body origin at that frame, the whole map's over the wider ``map_height_range_m`` relative to
the body origin at the first frame, so that a tile's colours change only with its heights) or,
with ``colour_by="sigma"``, by each cell's height standard deviation (magma over
``sigma_range_m``). :func:`recording_rows` and :func:`recording_column` read a recording back.

:class:`RerunViewer` streams to a viewer it starts (``spawn``), or saves a recording (``record_path``).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

from dem_graph.dem.layers import Dem
from dem_graph.errors import DemGraphError
from dem_graph.geometry.grid import GridGeometry
from dem_graph.viz.map_view import ColourBy, focus_outline, surface_mesh

LASER_COLOR = (255, 140, 0)
CAMERA_COLOR = (0, 200, 255)
TRUTH_COLOR = (60, 200, 60)
ESTIMATE_COLOR = (230, 60, 60)
FOCUS_COLOR = (255, 255, 255)


_ONE_CELL = GridGeometry(0.0, 1.0, 1.0, 1, 1)


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
    """Logs frames to rerun (see the module).

    ``colour_by``: the surfaces coloured by ``"height"`` or by ``"sigma"`` (height standard
    deviation, metres, over ``sigma_range_m``). ``global_map``: called every ``map_every`` frames
    (and at :meth:`close`) for the whole live map (a world-frame :class:`~dem_graph.dem.layers.Dem`,
    None while empty; on a grid whose cell edges lie on multiples of its resolution, as the live
    map's), cut into tiles of ``map_tile_cells``; without it only the focus area's surface is drawn."""

    def __init__(
        self,
        name: str = "dem_graph",
        spawn: bool = False,
        record_path: str | Path | None = None,
        height_range_m: tuple[float, float] = (-0.3, 0.3),
        trajectory_every: int = 10,
        colour_by: ColourBy = "height",
        sigma_range_m: tuple[float, float] = (0.0, 0.05),
        map_every: int = 10,
        global_map: Callable[[], Dem | None] | None = None,
        map_tile_cells: int = 32,
        map_height_range_m: tuple[float, float] = (-1.0, 1.0),
    ):
        if not spawn and record_path is None:
            raise DemGraphError("the viewer needs somewhere to go: spawn a viewer, or give a recording file")
        for heights in (height_range_m, map_height_range_m):  # refuses a bad colouring before the run starts
            surface_mesh(Dem.empty(_ONE_CELL), colour_by, heights, sigma_range_m)
        if map_every < 1 or map_tile_cells < 1:
            raise DemGraphError(f"map_every and map_tile_cells must be at least 1, got {map_every} and {map_tile_cells}")
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
        self.colour_by: ColourBy = colour_by
        self.sigma_range_m = sigma_range_m
        self.map_every = int(map_every)
        self.global_map = global_map
        self._positions: list[np.ndarray] = []
        self.map_tile_cells = int(map_tile_cells)
        self.map_height_range_m = map_height_range_m
        self._map_z_reference_m: float | None = None  # the first frame's body origin height: the whole map's colours are relative to it
        self._tiles_logged: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}  # tile: its elevation and variance as last logged
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
        local_map: Dem | None = None,
        returns_xyz: np.ndarray | None = None,
    ) -> None:
        """One frame: the image with its tracked points (``tracked``: a
        :class:`~dem_graph.frontend.frontend.TrackedView`'s arrays; the kinds in ``laser_kinds``
        are laser points), the local map's elevation, the pose and the live points; in 3D, the
        local map (``local_map``: the live map's local :class:`~dem_graph.dem.layers.Dem` in the
        heading frame, ``meta["T_world_local"]`` its pose) and the returns of the scans since the
        previous frame (``returns_xyz``, world frame, metres)."""
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
        if self._map_z_reference_m is None:
            self._map_z_reference_m = float(T[2, 3])
        if local_map is not None:
            self._log_focus(local_map)
        if returns_xyz is not None and len(returns_xyz):
            s.log("world/scan", rr.Points3D(np.asarray(returns_xyz, dtype=np.float32).reshape(-1, 3), colors=LASER_COLOR, radii=0.015))
        self.frames += 1
        if (self.frames - 1) % self.trajectory_every == 0:
            self._log_trajectory()
        if self.global_map is not None and (self.frames - 1) % self.map_every == 0:
            self._log_global_map()

    def _mesh(self, dem: Dem, height_reference_m: float, height_range_m: tuple[float, float]):
        vertices, triangles, colours = surface_mesh(dem, self.colour_by, height_range_m, self.sigma_range_m, height_reference_m)
        return self.rr.Mesh3D(vertex_positions=vertices, triangle_indices=triangles, vertex_colors=colours)

    def _log_focus(self, local_map: Dem) -> None:
        """The local map in its heading frame: the frame's transform, the surface, the area's outline
        (at the median height of its known cells, 0 when none is known)."""
        rr, s = self.rr, self.stream
        T = np.asarray(local_map.meta["T_world_local"], dtype=float)
        s.log("world/focus", rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3]))
        s.log("world/focus/surface", self._mesh(local_map, 0.0, self.height_range_m))
        g = local_map.geometry
        known = local_map.covered
        z = float(np.median(local_map.elevation[known])) if known.any() else 0.0
        outline = focus_outline((g.x_min_m, g.x_max_m), (g.y_max_m - g.y_min_m) / 2.0, z)
        outline[:, 1] += (g.y_max_m + g.y_min_m) / 2.0
        s.log("world/focus/outline", rr.LineStrips3D([outline], colors=[FOCUS_COLOR], radii=0.01))

    def _log_global_map(self) -> None:
        """The tiles of the whole map whose heights or variances changed since they were last logged."""
        dem = self.global_map()
        if dem is None:
            return
        g, n = dem.geometry, self.map_tile_cells
        col_cell = int(round(g.x_min_m / g.resolution_m)) + np.arange(g.n_cols)  # global cell index east
        row_cell = int(round(g.y_max_m / g.resolution_m)) - 1 - np.arange(g.n_rows)  # north, rows going south
        col_tile, row_tile = np.floor_divide(col_cell, n), np.floor_divide(row_cell, n)
        for tx in np.unique(col_tile):
            cols = np.flatnonzero(col_tile == tx)
            for ty in np.unique(row_tile):
                rows = np.flatnonzero(row_tile == ty)
                block = (slice(rows[0], rows[-1] + 1), slice(cols[0], cols[-1] + 1))
                z, var = dem.elevation[block], dem.variance[block]
                key = (int(tx), int(ty))
                last = self._tiles_logged.get(key)
                if last is None and not np.isfinite(z).any():
                    continue
                if last is not None and last[0].shape == z.shape and np.array_equal(last[0], z, equal_nan=True) and np.array_equal(last[1], var, equal_nan=True):
                    continue
                tile = Dem(
                    GridGeometry(g.x_min_m + cols[0] * g.resolution_m, g.y_max_m - rows[0] * g.resolution_m, g.resolution_m, len(rows), len(cols)),
                    {"elevation": z, "variance": var},
                )
                self.stream.log(f"world/map/tiles/{key[0]}_{key[1]}", self._mesh(tile, self._map_z_reference_m or 0.0, self.map_height_range_m))
                self._tiles_logged[key] = (z.copy(), var.copy())

    def _log_trajectory(self) -> None:
        self.stream.log("world/trajectory", self.rr.LineStrips3D([np.array(self._positions)], colors=[ESTIMATE_COLOR]))

    def close(self) -> None:
        if self._positions:
            self._log_trajectory()
            if self.global_map is not None and (self.frames - 1) % self.map_every != 0:  # the map as it ends
                self._log_global_map()
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


def recording_column(path: str | Path, entity: str, component: str) -> list[tuple[float, np.ndarray]]:
    """Every row of ``component`` (e.g. ``"Mesh3D:vertex_positions"``, ``"Points3D:positions"``,
    ``"Transform3D:translation"``) logged to ``entity`` (e.g. ``"world/scan"``) in a recording file,
    read back with rerun's own reader: (time on the ``time`` timeline in seconds, -inf for a static
    row; the row's values as a float64 array, (N, 3) for positions), in time order."""
    _rerun()
    from rerun.chunk import RrdReader

    wanted = "/" + entity.strip("/")
    out: list[tuple[float, np.ndarray]] = []
    for chunk in RrdReader(str(path)).store().stream():
        if chunk.entity_path != wanted:
            continue
        batch = chunk.to_record_batch()
        if component not in batch.schema.names:
            continue
        column = batch.column(component)
        width = getattr(column.type.value_type, "list_size", None)  # 3 for positions, 9 for a 3x3 matrix
        if "time" in batch.schema.names:
            times_s = batch.column("time").cast("int64").to_numpy(zero_copy_only=False) * 1e-9
        else:  # static: before every time
            times_s = np.full(len(batch), -np.inf)
        for t_s, values in zip(times_s, column.to_pylist(), strict=True):
            if values is not None:
                row = np.array(values, dtype=float)
                out.append((float(t_s), row.reshape(-1, width) if width else row))
    return sorted(out, key=lambda row: row[0])


__all__ = ["RerunViewer", "height_image", "recording_column", "recording_rows"]
