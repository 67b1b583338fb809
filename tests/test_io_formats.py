"""TUM trajectory and elevation GeoTIFF files: exact round trips, evo compatibility, bad input."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from dem_graph.errors import DatasetError
from dem_graph.geometry.grid import ElevationGrid, GridGeometry
from dem_graph.geometry.trajectory import Trajectory
from dem_graph.io import (
    read_elevation,
    read_elevation_geotiff,
    read_tum,
    write_elevation,
    write_elevation_geotiff,
    write_tum,
)


def make_trajectory(n: int = 25, seed: int = 0) -> Trajectory:
    rng = np.random.default_rng(seed)
    t_s = 1.7e9 + np.cumsum(rng.uniform(0.01, 0.1, n))  # unix-like times need all 17 digits
    positions = rng.normal(scale=30.0, size=(n, 3))
    quats = Rotation.random(n, random_state=seed).as_quat()
    return Trajectory(t_s, positions, quats)


def make_grid() -> ElevationGrid:
    rng = np.random.default_rng(1)
    geometry = GridGeometry(x_min_m=-3.3, y_max_m=12.1, resolution_m=0.1, n_rows=7, n_cols=9)
    z = rng.normal(size=geometry.shape).astype(np.float32)
    z[2, 3] = np.nan
    return ElevationGrid(geometry, z)


# ---------------------------------------------------------------------------------------------- TUM


def test_tum_round_trip_is_bit_exact(tmp_path):
    traj = make_trajectory()
    path = tmp_path / "traj.tum"
    write_tum(path, traj)
    back = read_tum(path)
    np.testing.assert_array_equal(back.t_s, traj.t_s)
    np.testing.assert_array_equal(back.positions_xyz, traj.positions_xyz)
    np.testing.assert_array_equal(back.orientations_quat_xyzw, traj.orientations_quat_xyzw)


def test_tum_is_readable_by_evo(tmp_path):
    file_interface = pytest.importorskip("evo.tools.file_interface")
    traj = make_trajectory()
    path = tmp_path / "traj.tum"
    write_tum(path, traj)
    evo_traj = file_interface.read_tum_trajectory_file(str(path))
    np.testing.assert_array_equal(evo_traj.timestamps, traj.t_s)
    np.testing.assert_array_equal(evo_traj.positions_xyz, traj.positions_xyz)
    # evo stores quaternions scalar first (w, x, y, z)
    np.testing.assert_array_equal(evo_traj.orientations_quat_wxyz, np.roll(traj.orientations_quat_xyzw, 1, axis=1))


def test_tum_reads_comments_and_blank_lines(tmp_path):
    path = tmp_path / "traj.tum"
    path.write_text("# a comment\n\n0.0 1 2 3 0 0 0 1\n   # indented comment\n0.5 1 2 3 0 0 0 1\n")
    traj = read_tum(path)
    np.testing.assert_array_equal(traj.t_s, [0.0, 0.5])


def _write_lines(tmp_path, text: str):
    path = tmp_path / "bad.tum"
    path.write_text(text)
    return path


def test_tum_missing_file(tmp_path):
    with pytest.raises(DatasetError, match=r"nope\.tum: file not found"):
        read_tum(tmp_path / "nope.tum")


def test_tum_wrong_column_count(tmp_path):
    path = _write_lines(tmp_path, "# header\n0 0 0 0 0 0 0 1\n1 0 0 0 0 0 1\n")
    with pytest.raises(DatasetError, match=r"bad\.tum: line 3: expected 8 columns.*got 7"):
        read_tum(path)


def test_tum_non_numeric(tmp_path):
    path = _write_lines(tmp_path, "0 0 0 0 0 0 0 1\n1 0 zero 0 0 0 0 1\n")
    with pytest.raises(DatasetError, match=r"bad\.tum: line 2: not a number: 'zero'"):
        read_tum(path)


@pytest.mark.parametrize("value", ["nan", "inf", "-inf"])
def test_tum_nan_in_pose(tmp_path, value):
    path = _write_lines(tmp_path, f"0 0 0 0 0 0 0 1\n1 0 {value} 0 0 0 0 1\n")
    with pytest.raises(DatasetError, match=r"bad\.tum: line 2: NaN or infinite"):
        read_tum(path)


@pytest.mark.parametrize("second_time", ["0", "-1"])
def test_tum_times_not_increasing(tmp_path, second_time):
    path = _write_lines(tmp_path, f"0 0 0 0 0 0 0 1\n{second_time} 0 0 0 0 0 0 1\n")
    with pytest.raises(DatasetError, match=r"bad\.tum: line 2: .*strictly increasing"):
        read_tum(path)


def test_tum_quaternion_not_unit(tmp_path):
    path = _write_lines(tmp_path, "0 0 0 0 0 0 0 2\n")
    with pytest.raises(DatasetError, match=r"bad\.tum: line 1: quaternion is not unit length"):
        read_tum(path)


@pytest.mark.parametrize("text", ["", "# only a comment\n\n"])
def test_tum_empty_file(tmp_path, text):
    path = _write_lines(tmp_path, text)
    with pytest.raises(DatasetError, match=r"bad\.tum: empty"):
        read_tum(path)


def test_tum_binary_file(tmp_path):
    path = tmp_path / "bad.tum"
    path.write_bytes(b"\xff\xfe\x00\x81" * 10)
    with pytest.raises(DatasetError, match=r"bad\.tum: not a text file"):
        read_tum(path)


def test_tum_write_to_missing_folder(tmp_path):
    with pytest.raises(DatasetError, match=r"traj\.tum: cannot write"):
        write_tum(tmp_path / "missing" / "traj.tum", make_trajectory(3))


# ---------------------------------------------------------------------------------------------- GeoTIFF


def test_elevation_round_trip_is_exact(tmp_path):
    grid = make_grid()
    path = tmp_path / "dem.tif"
    write_elevation(path, grid)
    back = read_elevation(path)
    assert back.geometry == grid.geometry
    assert back.z_m.dtype == np.float32
    np.testing.assert_array_equal(back.z_m, grid.z_m)  # NaN compares equal here
    assert sorted(p.name for p in tmp_path.iterdir()) == ["dem.tif"]  # no side-car files


def test_geotiff_bands_by_name_and_cell_centres(tmp_path):
    rasterio = pytest.importorskip("rasterio")
    grid = make_grid()
    g = grid.geometry
    sigma = np.full(g.shape, 0.25, dtype=np.float32)
    count = np.arange(g.n_rows * g.n_cols, dtype=np.float32).reshape(g.shape)
    path = tmp_path / "layers.tif"
    write_elevation_geotiff(path, grid, {"sigma": sigma, "count": count})

    geometry, bands = read_elevation_geotiff(path)
    assert geometry == g
    assert list(bands) == ["elevation", "sigma", "count"]
    np.testing.assert_array_equal(bands["sigma"], sigma)
    np.testing.assert_array_equal(bands["count"], count)
    np.testing.assert_array_equal(bands["elevation"], grid.z_m)

    X, Y = g.cell_centers_xy()
    with rasterio.open(path) as src:
        assert src.descriptions == ("elevation", "sigma", "count")
        assert src.crs is None
        assert np.isnan(src.nodata)
        assert src.dtypes == ("float32",) * 3
        for row, col in [(0, 0), (0, g.n_cols - 1), (g.n_rows - 1, 0), (4, 5)]:
            x, y = src.xy(row, col)  # centre of the pixel
            assert x == pytest.approx(X[row, col], abs=1e-12)
            assert y == pytest.approx(Y[row, col], abs=1e-12)
            assert src.index(X[row, col], Y[row, col]) == (row, col)


def test_geotiff_from_geometry_only(tmp_path):
    g = GridGeometry(0.0, 5.0, 0.5, 10, 4)
    path = tmp_path / "layers.tif"
    write_elevation_geotiff(path, g, {"slope": np.zeros(g.shape)})
    geometry, bands = read_elevation_geotiff(path)
    assert geometry == g and list(bands) == ["slope"]
    with pytest.raises(DatasetError, match=r"layers\.tif: no 'elevation' band \(bands: slope\)"):
        read_elevation(path)


def test_geotiff_write_rejects_wrong_band_shape(tmp_path):
    g = GridGeometry(0.0, 5.0, 0.5, 10, 4)
    with pytest.raises(DatasetError, match=r"x\.tif: band 'slope' has shape \(4, 10\)"):
        write_elevation_geotiff(tmp_path / "x.tif", g, {"slope": np.zeros((4, 10))})
    with pytest.raises(DatasetError, match=r"x\.tif: band 'elevation' is given twice"):
        write_elevation_geotiff(tmp_path / "x.tif", make_grid(), {"elevation": np.zeros(make_grid().geometry.shape)})


def test_geotiff_missing_file(tmp_path):
    with pytest.raises(DatasetError, match=r"nope\.tif: file not found"):
        read_elevation(tmp_path / "nope.tif")


@pytest.mark.parametrize("content", [b"", b"this is not a tiff file", b"II*\x00" + b"\x13" * 64])
def test_geotiff_corrupt_file(tmp_path, content):
    path = tmp_path / "bad.tif"
    path.write_bytes(content)
    with pytest.raises(DatasetError, match=r"bad\.tif: not a readable GeoTIFF"):
        read_elevation(path)


def test_geotiff_truncated_file(tmp_path):
    path = tmp_path / "dem.tif"
    rng = np.random.default_rng(2)
    g = GridGeometry(0.0, 64.0, 1.0, 64, 64)
    write_elevation(path, ElevationGrid(g, rng.normal(size=g.shape).astype(np.float32)))
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(DatasetError, match=r"dem\.tif: not a readable GeoTIFF"):
        read_elevation(path)
