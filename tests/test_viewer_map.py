"""The viewer's 3D view of the live map: a recording of a `smoke` run holds, frame by frame, the
local map's surface over the focus area, the returns of the scans that came since the previous
frame, and every few frames the whole live map, read back with rerun's own reader.

Truths: the live pipeline's own update at each frame (its local map, the heading frame's pose),
the scans of the log (their valid beams, counted from the ranges with the rig's limits), the live
map's global DEM at the end, the simulator's terrain, and hand-made grids for the colouring.
"""

from __future__ import annotations

import numpy as np
import pytest
from matplotlib import colormaps

from dem_graph.datasets.events import LaserScan
from dem_graph.dem.layers import Dem
from dem_graph.errors import DemGraphError
from dem_graph.geometry.grid import GridGeometry
from dem_graph.viz.map_view import focus_outline, surface_mesh

rerun = pytest.importorskip("rerun", reason="the viewer needs rerun (pip install 'dem-graph[viewer]')")

MAP_EVERY = 10  # the viewer's default: the whole map every 10th frame


def _grid(elevation_m: np.ndarray, variance_m2: np.ndarray) -> Dem:
    rows, cols = elevation_m.shape
    return Dem(GridGeometry(0.0, rows * 0.1, 0.1, rows, cols), {"elevation": elevation_m.astype(np.float32), "variance": variance_m2.astype(np.float32)})


def test_surface_mesh_vertices_triangles_and_colours_from_a_hand_made_grid():
    z = np.array([[0.0, 0.1, 0.2, np.nan], [-0.3, 0.3, 0.4, 0.5], [0.0, 0.0, np.nan, 0.0]])
    var = np.full(z.shape, 0.02**2)
    var[0, 0] = 0.0
    var[1, 1] = 0.05**2
    dem = _grid(z, var)
    vertices, triangles, colours = surface_mesh(dem, "height", height_range_m=(-0.3, 0.3))
    known = np.isfinite(z)
    # a flat square per known cell: its four corners (x east, y north, metres) around its centre, at its height as it is
    assert vertices.shape == (4 * known.sum(), 3) and known.sum() == 10
    corners = vertices.reshape(-1, 4, 3)
    X, Y = dem.geometry.cell_centers_xy()
    np.testing.assert_allclose(corners.mean(axis=1), np.stack([X[known], Y[known], z[known]], axis=1), atol=1e-6)
    np.testing.assert_allclose(np.ptp(corners[:, :, 0], axis=1), 0.1, atol=1e-6)
    np.testing.assert_allclose(np.ptp(corners[:, :, 1], axis=1), 0.1, atol=1e-6)
    assert np.all(np.ptp(corners[:, :, 2], axis=1) == 0.0)
    # two triangles per cell, each within its cell, counter-clockwise seen from above (normals up)
    assert triangles.shape == (20, 3)
    assert np.all(triangles // 4 == np.repeat(np.arange(10), 2)[:, None])
    p = vertices[triangles.astype(int)]
    normal_z = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])[:, 2]
    np.testing.assert_allclose(normal_z, 0.1 * 0.1, rtol=1e-5)
    colours = colours[::4]  # one colour per cell, on its four corners
    viridis = (colormaps["viridis"]([0.0, 0.5, 1.0])[:, :3] * 255).astype(np.uint8)
    by_cell = dict(zip(map(tuple, np.argwhere(known)), colours, strict=True))
    np.testing.assert_array_equal(by_cell[(1, 0)], viridis[0])  # -0.3 m: the bottom of the range
    np.testing.assert_array_equal(by_cell[(0, 0)], viridis[1])  # 0 m: its middle
    np.testing.assert_array_equal(by_cell[(1, 1)], viridis[2])  # 0.3 m: its top
    np.testing.assert_array_equal(by_cell[(1, 3)], viridis[2])  # 0.5 m: clipped to the top
    # relative to a reference height: 0.3 m with the reference at 0.3 m is the middle
    _, _, shifted = surface_mesh(dem, "height", height_range_m=(-0.3, 0.3), height_reference_m=0.3)
    np.testing.assert_array_equal(dict(zip(map(tuple, np.argwhere(known)), shifted[::4], strict=True))[(1, 1)], viridis[1])
    # by uncertainty: sigma = sqrt(variance) over (0, 0.05) m
    _, _, by_sigma = surface_mesh(dem, "sigma", sigma_range_m=(0.0, 0.05))
    assert np.all(by_sigma.reshape(-1, 4, 3) == by_sigma[::4][:, None])
    by_sigma = by_sigma[::4]
    magma = (colormaps["magma"]([0.0, 0.4, 1.0])[:, :3] * 255).astype(np.uint8)
    by_cell = dict(zip(map(tuple, np.argwhere(known)), by_sigma, strict=True))
    np.testing.assert_array_equal(by_cell[(0, 0)], magma[0])  # sigma 0
    np.testing.assert_array_equal(by_cell[(0, 1)], magma[1])  # sigma 0.02 m = 0.4 of the range
    np.testing.assert_array_equal(by_cell[(1, 1)], magma[2])  # sigma 0.05 m
    with pytest.raises(DemGraphError, match="colour_by"):
        surface_mesh(dem, "slope")
    with pytest.raises(DemGraphError, match="low < high"):
        surface_mesh(dem, "sigma", sigma_range_m=(0.05, 0.05))


def test_focus_outline_is_the_closed_rectangle():
    outline = focus_outline((1.0, 5.0), 1.5, z_m=-0.2)
    np.testing.assert_array_equal(outline, np.array([[1, -1.5, -0.2], [5, -1.5, -0.2], [5, 1.5, -0.2], [1, 1.5, -0.2], [1, -1.5, -0.2]], dtype=np.float32))


def test_the_viewer_refuses_a_colouring_it_does_not_know(tmp_path):
    from dem_graph.viz.rerun_viewer import RerunViewer

    with pytest.raises(DemGraphError, match="colour_by"):
        RerunViewer(record_path=tmp_path / "x.rrd", colour_by="slope")


@pytest.fixture(scope="module")
def recorded_smoke(smoke_log, tmp_path_factory):
    """A ptpm run of the `smoke` log recorded to a file, with what the pipeline gave at each frame."""
    from dem_graph.pipeline.config import RunConfig
    from dem_graph.pipeline.live_view import ViewerOptions
    from dem_graph.pipeline.run import run_estimator

    path = tmp_path_factory.mktemp("viewer") / "smoke.rrd"
    frames: list[dict] = []
    held: dict = {}

    def capture(pipeline):
        held["pipeline"] = pipeline

        def listener(update):  # called before the viewer's listener, with the same update
            frames.append({
                "t_s": update.t_s, "elevation": update.local.elevation.copy(), "T_world_local": update.local.meta["T_world_local"].copy(),
                "geometry": update.local.geometry, "scans_taken": pipeline.map.counters["scans"], "map_empty": pipeline.map.grid.n_kept == 0,
            })

        pipeline.listeners.append(listener)

    run_estimator(smoke_log, RunConfig(estimator="ptpm"), with_dem=False, viewer=ViewerOptions(record_path=path), instrument=capture)
    return path, frames, held["pipeline"]


def test_recording_holds_the_focus_surface_of_every_frame_as_the_live_map_had_it(recorded_smoke):
    from dem_graph.viz.rerun_viewer import recording_column

    path, frames, _ = recorded_smoke
    surfaces = recording_column(path, "world/focus/surface", "Mesh3D:vertex_positions")
    poses = recording_column(path, "world/focus", "Transform3D:translation")
    assert len(frames) > 50
    assert [t for t, _ in surfaces] == pytest.approx([f["t_s"] for f in frames], abs=1e-9)
    assert len(poses) == len(frames)
    checked = 0
    for frame, (_, vertices), (_, translation) in zip(frames, surfaces, poses, strict=True):
        known = np.isfinite(frame["elevation"])
        X, Y = frame["geometry"].cell_centers_xy()
        assert vertices.shape == (4 * known.sum(), 3)
        corners = vertices.reshape(-1, 4, 3)  # a square per known cell
        # the surface's heights are the local map's elevation layer at that frame (heading frame, relative to the body origin)
        for k in range(4):
            np.testing.assert_allclose(corners[:, k, 2], frame["elevation"][known], atol=1e-6)
        np.testing.assert_allclose(corners[:, :, :2].mean(axis=1), np.stack([X[known], Y[known]], axis=1), atol=1e-6)
        # and the surface stands in the heading frame of that frame (float32 in the recording: 1e-5 m)
        np.testing.assert_allclose(translation.ravel(), frame["T_world_local"][:3, 3], atol=1e-5)
        checked += int(known.sum())
    assert checked > 1000


def test_recording_holds_each_frames_new_scan_returns_where_the_map_put_them(recorded_smoke, smoke_log):
    from dem_graph.viz.rerun_viewer import recording_column

    path, frames, pipeline = recorded_smoke
    scans = [e for e in smoke_log.events() if isinstance(e, LaserScan)]
    assert frames[-1]["scans_taken"] <= len(scans) == pipeline.map.counters["scans"]
    valid = np.array([pipeline.rig.laser.valid_ranges(s.ranges_m).sum() for s in scans])
    # the returns logged at a frame: every valid beam of the scans taken since the previous frame
    expected, before = {}, 0
    for f in frames:
        n = int(valid[before:f["scans_taken"]].sum())
        if n:
            expected[round(f["t_s"], 9)] = n
        before = f["scans_taken"]
    logged = recording_column(path, "world/scan", "Points3D:positions")
    assert {round(t, 9): len(xyz) for t, xyz in logged} == expected
    assert len(expected) > 20
    # they land on the ground: against the simulator's terrain under them (ptpm drifts millimetres on smoke)
    xyz = np.concatenate([p for _, p in logged])
    error_m = xyz[:, 2] - smoke_log.ground_truth.elevation.height_at(xyz[:, 0], xyz[:, 1])
    error_m = error_m[np.isfinite(error_m)]
    assert len(error_m) > 0.9 * len(xyz)
    assert np.median(np.abs(error_m)) < 0.02 and np.percentile(np.abs(error_m), 95) < 0.05


def test_recording_holds_the_whole_live_map_in_tiles_logged_when_they_change(recorded_smoke):
    from dem_graph.viz.rerun_viewer import recording_column, recording_rows

    path, frames, pipeline = recorded_smoke
    tiles = sorted(e.lstrip("/") for e in recording_rows(path) if e.startswith("/world/map/tiles/"))
    rows = {tile: recording_column(path, tile, "Mesh3D:vertex_positions") for tile in tiles}
    times = [f["t_s"] for f in frames]
    shown = [times[i] for i in range(0, len(times), MAP_EVERY) if not frames[i]["map_empty"]]  # nothing to draw before the first return
    if (len(times) - 1) % MAP_EVERY:
        shown.append(times[-1])  # the map as the run ends
    assert frames[0]["map_empty"] and not frames[MAP_EVERY]["map_empty"]
    logged_at = sorted({round(t, 9) for r in rows.values() for t, _ in r})
    assert logged_at == pytest.approx(shown, abs=1e-9)
    # a tile is logged again only when it changed: fewer rows than tiles times logs (the map's first tiles are behind the vehicle by the end)
    n_rows = sum(len(r) for r in rows.values())
    assert len(tiles) >= 2 and n_rows < len(tiles) * len(shown)
    # each tile's cells lie inside it (32 cells of 0.1 m a side, named by its global index)
    for tile, r in rows.items():
        tx, ty = (int(v) for v in tile.rsplit("/", 1)[1].split("_"))
        centres = r[-1][1].reshape(-1, 4, 3).mean(axis=1)
        assert np.all(np.floor(centres[:, 0] / 0.1 / 32) == tx) and np.all(np.floor(centres[:, 1] / 0.1 / 32) == ty)
    # the tiles as last logged are the live map as the run ended, world frame, to 1e-6 m
    cells = np.concatenate([r[-1][1].reshape(-1, 4, 3) for r in rows.values()])
    assert np.all(np.ptp(cells[:, :, 2], axis=1) == 0.0)
    recorded = cells.mean(axis=1)
    final = pipeline.map.global_dem(traversability_window=None)
    known = final.covered
    X, Y = final.geometry.cell_centers_xy()
    expected = np.stack([X[known], Y[known], final.elevation[known]], axis=1)
    assert len(recorded) == len(expected)

    def order(xyz):  # by cell: the centres lie mid-cell
        return np.lexsort((np.floor(xyz[:, 1] / 0.1), np.floor(xyz[:, 0] / 0.1)))

    np.testing.assert_allclose(recorded[order(recorded)], expected[order(expected)], atol=1e-6)


def test_a_still_of_the_3d_view_is_drawn_from_the_recording(recorded_smoke, tmp_path):
    from dem_graph.viz.viewer_still import map_surface_at, recording_still

    path, frames, pipeline = recorded_smoke
    t_end = frames[-1]["t_s"]
    vertices, triangles, colours = map_surface_at(path, t_end)
    # the map as the run ended: a square (4 vertices, 2 triangles) per known cell of the live map
    n_cells = int(pipeline.map.global_dem(traversability_window=None).covered.sum())
    assert vertices.shape == (4 * n_cells, 3) and triangles.shape == (2 * n_cells, 3) and colours.shape == (4 * n_cells, 4)
    assert triangles.max() == len(vertices) - 1 and np.all((colours >= 0) & (colours <= 1))
    png = recording_still(path, t_end, tmp_path / "still.png")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    with pytest.raises(DemGraphError, match="no map surface"):
        recording_still(path, frames[0]["t_s"], tmp_path / "none.png")  # nothing mapped at the first frame
