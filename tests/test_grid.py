"""Truth-checked tests of dem_graph.geometry.grid: GridGeometry and ElevationGrid."""

from __future__ import annotations

import numpy as np
import pytest

from dem_graph.errors import DemGraphError
from dem_graph.geometry.grid import ElevationGrid, GridGeometry

GEOM = GridGeometry(x_min_m=-12.5, y_max_m=40.0, resolution_m=0.5, n_rows=17, n_cols=23)


# ---------------------------------------------------------------------- GridGeometry


def test_grid_extent_properties():
    g = GEOM
    assert g.shape == (17, 23)
    assert g.x_max_m == pytest.approx(-12.5 + 23 * 0.5, abs=1e-12)
    assert g.y_min_m == pytest.approx(40.0 - 17 * 0.5, abs=1e-12)
    np.testing.assert_allclose(g.cell_center_x_m()[[0, -1]], [-12.25, -12.5 + 22.5 * 0.5], atol=1e-12)
    np.testing.assert_allclose(g.cell_center_y_m()[[0, -1]], [39.75, 40.0 - 16.5 * 0.5], atol=1e-12)
    X, Y = g.cell_centers_xy()
    assert X.shape == Y.shape == (17, 23)
    # row 0 is north (largest y), column 0 is west (smallest x)
    assert np.all(np.diff(Y[:, 0]) < 0) and np.all(np.diff(X[0]) > 0)
    assert X[3, 5] == pytest.approx(-12.5 + 5.5 * 0.5) and Y[3, 5] == pytest.approx(40.0 - 3.5 * 0.5)


@pytest.mark.parametrize("kwargs", [dict(resolution_m=0.0), dict(resolution_m=-1.0), dict(n_rows=0), dict(n_cols=-2)])
def test_grid_rejects_invalid(kwargs):
    args = dict(x_min_m=0.0, y_max_m=0.0, resolution_m=1.0, n_rows=3, n_cols=3) | kwargs
    with pytest.raises(DemGraphError):
        GridGeometry(**args)


def test_cell_centres_fractional_index_round_trip():
    g = GEOM
    X, Y = g.cell_centers_xy()
    row_f, col_f = g.fractional_index(X, Y)
    R, C = np.meshgrid(np.arange(g.n_rows), np.arange(g.n_cols), indexing="ij")
    np.testing.assert_allclose(row_f, R, atol=1e-12)
    np.testing.assert_allclose(col_f, C, atol=1e-12)
    # the grid's outer corners sit half a cell outside the centre lattice
    r, c = g.fractional_index(g.x_min_m, g.y_max_m)
    assert (float(r), float(c)) == pytest.approx((-0.5, -0.5), abs=1e-12)
    r, c = g.fractional_index(g.x_max_m, g.y_min_m)
    assert (float(r), float(c)) == pytest.approx((g.n_rows - 0.5, g.n_cols - 0.5), abs=1e-12)
    # linear in between: a quarter cell east and south of a centre
    r, c = g.fractional_index(X[4, 7] + 0.125, Y[4, 7] - 0.125)
    assert (float(r), float(c)) == pytest.approx((4.25, 7.25), abs=1e-12)


def test_cell_index_of_points_inside_each_cell():
    g = GEOM
    rng = np.random.default_rng(31)
    X, Y = g.cell_centers_xy()
    for _ in range(5):
        off = rng.uniform(-0.49, 0.49, size=(2,) + g.shape) * g.resolution_m
        row, col, inside = g.cell_index(X + off[0], Y + off[1])
        R, C = np.meshgrid(np.arange(g.n_rows), np.arange(g.n_cols), indexing="ij")
        np.testing.assert_array_equal(row, R)
        np.testing.assert_array_equal(col, C)
        assert inside.all()
        assert row.dtype == np.int64 and col.dtype == np.int64


def test_cell_index_outside():
    g = GEOM
    d = 0.01
    x = np.array([g.x_min_m - d, g.x_max_m + d, 0.0, 0.0, g.x_min_m + d, g.x_max_m - d])
    y = np.array([35.0, 35.0, g.y_max_m + d, g.y_min_m - d, g.y_max_m - d, g.y_min_m + d])
    row, col, inside = g.cell_index(x, y)
    np.testing.assert_array_equal(inside, [False, False, False, False, True, True])
    assert (row[4], col[4]) == (0, 0)
    assert (row[5], col[5]) == (g.n_rows - 1, g.n_cols - 1)
    assert col[0] == -1 and col[1] == g.n_cols and row[2] == -1 and row[3] == g.n_rows


@pytest.mark.parametrize(
    "box, res",
    [
        ((0.0, 0.0, 10.0, 5.0), 1.0),  # exact multiple
        ((-3.3, 7.1, 4.05, 9.99), 0.25),
        ((0.0, 0.0, 0.3, 0.7), 0.1),  # 0.3 / 0.1 is 2.9999999999999996 in floating point
        ((100.0, -50.0, 100.0, -50.0), 0.2),  # empty box still gives one cell
        ((1.0, 2.0, 1.05, 2.01), 0.5),
    ],
)
def test_covering_covers_the_box(box, res):
    x0, y0, x1, y1 = box
    g = GridGeometry.covering(x0, y0, x1, y1, res)
    assert g.resolution_m == res
    assert g.x_min_m == x0
    assert g.y_min_m == pytest.approx(y0, abs=1e-9)
    assert g.x_max_m >= x1 - 1e-9
    assert g.y_max_m >= y1 - 1e-9
    # the smallest such grid: one column or row fewer would not cover
    assert g.n_cols == 1 or g.x_min_m + (g.n_cols - 1) * res < x1 - 1e-9
    assert g.n_rows == 1 or g.y_min_m + (g.n_rows - 1) * res < y1 - 1e-9
    # points of the box fall in cells of the grid (the south and east grid edges are excluded by
    # cell_index's half-open convention, so the corners are nudged inwards by 1e-9 m)
    if x1 <= x0 or y1 <= y0:
        return  # a degenerate box has no interior
    rng = np.random.default_rng(32)
    x = np.concatenate([[x0 + 1e-9, x1 - 1e-9, x0 + 1e-9, x1 - 1e-9], rng.uniform(x0, x1, 50)])
    y = np.concatenate([[y0 + 1e-9, y1 - 1e-9, y1 - 1e-9, y0 + 1e-9], rng.uniform(y0, y1, 50)])
    inside = (x > x0) & (x < x1) & (y > y0) & (y < y1) | (np.arange(len(x)) < 4)
    assert g.cell_index(x[inside], y[inside])[2].all()


def test_cell_index_edges_are_half_open():
    # a cell holds its north and west edges, not its south and east ones (GeoTIFF pixel convention)
    g = GridGeometry(0.0, 2.0, 1.0, 2, 2)
    row, col, inside = g.cell_index(np.array([0.0, 1.0, 2.0, 0.5, 0.5]), np.array([1.5, 1.5, 1.5, 2.0, 0.0]))
    np.testing.assert_array_equal(col[:3], [0, 1, 2])
    np.testing.assert_array_equal(row[3:], [0, 2])
    np.testing.assert_array_equal(inside, [True, True, False, True, False])


def test_covering_known_counts():
    g = GridGeometry.covering(0.0, 0.0, 10.0, 5.0, 1.0)
    assert g.shape == (5, 10) and g.y_max_m == 5.0
    g = GridGeometry.covering(0.0, 0.0, 10.2, 5.0, 1.0)
    assert g.shape == (5, 11)


def test_affine_maps_pixel_centres_to_cell_centres():
    g = GEOM
    A = g.affine()
    X, Y = g.cell_centers_xy()
    for row, col in [(0, 0), (0, g.n_cols - 1), (g.n_rows - 1, 0), (g.n_rows - 1, g.n_cols - 1), (8, 11)]:
        x, y = A @ (col + 0.5, row + 0.5)
        assert x == pytest.approx(X[row, col], abs=1e-12)
        assert y == pytest.approx(Y[row, col], abs=1e-12)
    # the pixel corner (0, 0) is the grid's north-west corner
    assert A @ (0, 0) == pytest.approx((g.x_min_m, g.y_max_m), abs=1e-12)
    assert A @ (g.n_cols, g.n_rows) == pytest.approx((g.x_max_m, g.y_min_m), abs=1e-12)
    # and the inverse transform agrees with fractional_index (pixel centres at +0.5)
    col_px, row_px = ~A @ (1.234, 35.678)
    r, c = g.fractional_index(1.234, 35.678)
    assert (row_px - 0.5, col_px - 0.5) == pytest.approx((float(r), float(c)), abs=1e-12)


# --------------------------------------------------------------------- ElevationGrid


def plane_grid(a=0.13, b=-0.27, c=4.5, geom=GEOM) -> ElevationGrid:
    X, Y = geom.cell_centers_xy()
    return ElevationGrid(geom, a * X + b * Y + c)


def bumpy_grid(seed=41) -> ElevationGrid:
    rng = np.random.default_rng(seed)
    geom = GridGeometry(x_min_m=3.0, y_max_m=8.0, resolution_m=0.4, n_rows=25, n_cols=30)
    X, Y = geom.cell_centers_xy()
    z = 0.3 * np.sin(1.3 * X) * np.cos(0.9 * Y) + rng.normal(scale=0.25, size=geom.shape) + 0.05 * X
    return ElevationGrid(geom, z)


def test_elevation_grid_rejects_shape_mismatch():
    with pytest.raises(DemGraphError, match="shape"):
        ElevationGrid(GEOM, np.zeros((GEOM.n_cols, GEOM.n_rows)))


def test_height_at_reproduces_a_plane_exactly():
    a, b, c = 0.13, -0.27, 4.5
    grid = plane_grid(a, b, c)
    g = grid.geometry
    X, Y = g.cell_centers_xy()
    rng = np.random.default_rng(42)
    x = rng.uniform(X.min(), X.max(), 2000)
    y = rng.uniform(Y.min(), Y.max(), 2000)
    # include the lattice corners and edges exactly
    x = np.concatenate([x, [X.min(), X.max(), X.min(), X.max(), X.min(), -5.0]])
    y = np.concatenate([y, [Y.max(), Y.min(), Y.min(), Y.max(), 36.1, Y.min()]])
    h = grid.height_at(x, y)
    assert np.all(np.isfinite(h))
    np.testing.assert_allclose(h, a * x + b * y + c, rtol=0, atol=1e-9)


def test_height_at_cell_centres_equals_samples():
    grid = bumpy_grid()
    X, Y = grid.geometry.cell_centers_xy()
    np.testing.assert_allclose(grid.height_at(X, Y), grid.z_m, rtol=0, atol=1e-12)


def test_height_at_is_nan_outside_the_centre_lattice():
    grid = plane_grid()
    g = grid.geometry
    X, Y = g.cell_centers_xy()
    e = 1e-6
    x = np.array([X.min() - e, X.max() + e, 0.0, 0.0, g.x_min_m, -100.0, 0.0])
    y = np.array([35.0, 35.0, Y.max() + e, Y.min() - e, 35.0, 35.0, g.y_max_m])
    h = grid.height_at(x, y)
    assert np.all(np.isnan(h))
    # a scalar query works and gives a 0-d result
    assert np.isnan(grid.height_at(-100.0, 0.0))
    assert float(grid.height_at(X[2, 3], Y[2, 3])) == pytest.approx(grid.z_m[2, 3], abs=1e-12)


def test_height_at_is_piecewise_linear_on_the_mesh_split():
    # a single cell: z00=0, z01=0, z10=0, z11=1. The split diagonal joins (r0,c1)-(r1,c0),
    # so the cell's centre lies on it and must be the mean of z01 and z10 (0), not 0.25 (bilinear)
    # and not 0.5 (the other diagonal).
    geom = GridGeometry(0.0, 2.0, 1.0, 2, 2)
    grid = ElevationGrid(geom, np.array([[0.0, 0.0], [0.0, 1.0]]))
    # cell centres: (0.5, 1.5) (1.5, 1.5) / (0.5, 0.5) (1.5, 0.5)
    assert float(grid.height_at(1.0, 1.0)) == pytest.approx(0.0, abs=1e-12)
    assert float(grid.height_at(1.25, 0.75)) == pytest.approx(0.5, abs=1e-12)  # in triangle B, halfway to z11
    assert float(grid.height_at(0.75, 1.25)) == pytest.approx(0.0, abs=1e-12)  # in triangle A


def _raycast_down(vertices, triangles, x, y, z_top):
    o3d = pytest.importorskip("open3d")
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(vertices), o3d.core.Tensor(triangles))
    rays = np.zeros((len(x), 6), dtype=np.float32)
    rays[:, 0], rays[:, 1], rays[:, 2] = x, y, z_top
    rays[:, 5] = -1.0
    ans = scene.cast_rays(o3d.core.Tensor(rays))
    t_hit = ans["t_hit"].numpy().astype(float)
    normals = ans["primitive_normals"].numpy().astype(float)
    return z_top - t_hit, normals


def test_height_at_matches_open3d_raycast_on_the_mesh():
    grid = bumpy_grid()
    vertices, triangles = grid.triangle_mesh_arrays()
    g = grid.geometry
    assert vertices.dtype == np.float32 and vertices.shape == (g.n_rows * g.n_cols, 3)
    assert triangles.dtype == np.uint32 and triangles.shape == (2 * (g.n_rows - 1) * (g.n_cols - 1), 3)
    X, Y = g.cell_centers_xy()
    np.testing.assert_array_equal(vertices[:, 0], X.ravel().astype(np.float32))
    np.testing.assert_array_equal(vertices[:, 2], grid.z_m.ravel().astype(np.float32))

    rng = np.random.default_rng(43)
    inset = 1e-3
    x = rng.uniform(X.min() + inset, X.max() - inset, 200)
    y = rng.uniform(Y.min() + inset, Y.max() - inset, 200)
    # round to float32 first so both sides see exactly the same query point
    x, y = x.astype(np.float32).astype(float), y.astype(np.float32).astype(float)
    z_top = float(np.nanmax(grid.z_m)) + 5.0
    z_mesh, normals = _raycast_down(vertices, triangles, x, y, z_top)
    assert np.all(np.isfinite(z_mesh)), "every ray must hit the mesh"
    z_grid = grid.height_at(x, y)
    np.testing.assert_allclose(z_grid, z_mesh, rtol=0, atol=1e-4)
    assert np.all(normals[:, 2] > 0), "hit triangles must face up"

    # the comparison is discriminating: splitting cells along the other diagonal gives heights that
    # differ from the mesh by far more than the tolerance at many of the points
    row_f, col_f = g.fractional_index(x, y)
    r0, c0 = np.floor(row_f).astype(int), np.floor(col_f).astype(int)
    fr, fc = row_f - r0, col_f - c0
    z = grid.z_m
    z00, z01, z10, z11 = z[r0, c0], z[r0, c0 + 1], z[r0 + 1, c0], z[r0 + 1, c0 + 1]
    upper_right = fc >= fr  # triangle (r0,c0),(r0,c1),(r1,c1)
    h_other = np.where(
        upper_right,
        z00 + fc * (z01 - z00) + fr * (z11 - z01),
        z00 + fr * (z10 - z00) + fc * (z11 - z10),
    )
    assert np.mean(np.abs(h_other - z_mesh) > 1e-2) > 0.5


def test_mesh_normals_of_a_plane_point_up():
    a, b = 0.13, -0.27
    grid = plane_grid(a, b, 4.5)
    vertices, triangles = grid.triangle_mesh_arrays()
    v = vertices.astype(float)
    n = np.cross(v[triangles[:, 1]] - v[triangles[:, 0]], v[triangles[:, 2]] - v[triangles[:, 0]])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    expected = np.array([-a, -b, 1.0]) / np.linalg.norm([-a, -b, 1.0])
    assert np.all(n[:, 2] > 0)
    np.testing.assert_allclose(n, np.broadcast_to(expected, n.shape), atol=1e-5)
    # every triangle is non-degenerate and the two halves of a cell tile it: total xy area = lattice area
    g = grid.geometry
    e1 = v[triangles[:, 1], :2] - v[triangles[:, 0], :2]
    e2 = v[triangles[:, 2], :2] - v[triangles[:, 0], :2]
    area_xy = 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])
    np.testing.assert_allclose(area_xy, 0.5 * g.resolution_m**2, rtol=1e-5)
    assert area_xy.sum() == pytest.approx((g.n_rows - 1) * (g.n_cols - 1) * g.resolution_m**2, rel=1e-5)
