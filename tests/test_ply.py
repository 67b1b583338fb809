"""Binary PLY point clouds: exact round trip, open3d compatibility, bad input."""

from __future__ import annotations

import numpy as np
import pytest

from dem_graph.errors import DatasetError, DemGraphError
from dem_graph.io.ply import read_points_ply, write_points_ply


def make_points(n: int = 50, seed: int = 0):
    rng = np.random.default_rng(seed)
    points = rng.normal(scale=50.0, size=(n, 3)) + [1e5, -2e6, 300.0]  # large offsets need all float64 digits
    attributes = {
        "variance_z_m2": rng.uniform(1e-6, 1e-2, n).astype(np.float32),
        "sigma_m": rng.uniform(0.001, 0.2, n),  # float64
        "source": rng.integers(0, 2, n).astype(np.uint8),
        "point_id": (np.arange(n) * 7919 - 100).astype(np.int32),
    }
    return points, attributes


def test_round_trip_is_exact(tmp_path):
    points, attributes = make_points()
    path = tmp_path / "points.ply"
    write_points_ply(path, points, attributes)
    points_back, attributes_back = read_points_ply(path)
    assert points_back.dtype == np.float64
    np.testing.assert_array_equal(points_back, points)
    assert list(attributes_back) == list(attributes)
    for name, values in attributes.items():
        assert attributes_back[name].dtype == values.dtype, name
        np.testing.assert_array_equal(attributes_back[name], values)
    assert path.read_bytes().startswith(b"ply\nformat binary_little_endian 1.0\n")


def test_nan_positions_and_no_attributes_round_trip(tmp_path):
    points = np.array([[0.1, np.nan, 3.0], [np.inf, -0.0, 5e-324]])
    path = tmp_path / "p.ply"
    write_points_ply(path, points)
    back, attributes = read_points_ply(path)
    np.testing.assert_array_equal(back, points)
    assert np.signbit(back[1, 1])
    assert attributes == {}


def test_empty_point_set_is_valid(tmp_path):
    path = tmp_path / "empty.ply"
    write_points_ply(path, np.empty((0, 3)), {"source": np.empty(0, np.uint8)})
    points, attributes = read_points_ply(path)
    assert points.shape == (0, 3)
    assert attributes["source"].shape == (0,) and attributes["source"].dtype == np.uint8


def test_open3d_reads_positions_and_attributes(tmp_path):
    o3d = pytest.importorskip("open3d")
    points, attributes = make_points()
    path = tmp_path / "points.ply"
    write_points_ply(path, points, attributes)
    cloud = o3d.t.io.read_point_cloud(str(path))
    positions = cloud.point.positions.numpy()
    assert positions.dtype == np.float64
    np.testing.assert_array_equal(positions, points)
    for name, values in attributes.items():
        read = cloud.point[name].numpy().reshape(-1)
        assert read.dtype == values.dtype, name
        np.testing.assert_array_equal(read, values)


def test_big_endian_float_xyz_and_extra_elements_are_read(tmp_path):
    points = np.array([[1.5, 2.5, 3.5], [-1.0, 0.0, 2.0]], dtype=np.float32)
    dtype = np.dtype([("x", ">f4"), ("y", ">f4"), ("z", ">f4"), ("intensity", ">u2")])
    body = np.array([(*p, i) for p, i in zip(points.tolist(), [7, 65000])], dtype=dtype)
    header = (
        "ply\nformat binary_big_endian 1.0\ncomment made by hand\nelement vertex 2\n"
        "property float x\nproperty float y\nproperty float z\nproperty ushort intensity\n"
        "element face 1\nproperty list uchar int vertex_indices\nend_header\n"
    )
    face = bytes([3]) + np.array([0, 1, 0], ">i4").tobytes()
    path = tmp_path / "be.ply"
    path.write_bytes(header.encode() + body.tobytes() + face)
    back, attributes = read_points_ply(path)
    np.testing.assert_array_equal(back, points.astype(np.float64))
    np.testing.assert_array_equal(attributes["intensity"], [7, 65000])
    assert attributes["intensity"].dtype == np.uint16


# ----------------------------------------------------------------------------------- bad input


def _assert_names_file(exc_info, path):
    assert str(path) in str(exc_info.value)


def test_missing_file(tmp_path):
    path = tmp_path / "nope.ply"
    with pytest.raises(DatasetError, match="not found") as exc_info:
        read_points_ply(path)
    _assert_names_file(exc_info, path)


def test_not_a_ply(tmp_path):
    path = tmp_path / "x.ply"
    path.write_text("hello\nworld\n")
    with pytest.raises(DatasetError, match="not a PLY") as exc_info:
        read_points_ply(path)
    _assert_names_file(exc_info, path)


def test_header_without_end(tmp_path):
    path = tmp_path / "x.ply"
    path.write_text("ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty double x\n")
    with pytest.raises(DatasetError, match="end_header") as exc_info:
        read_points_ply(path)
    _assert_names_file(exc_info, path)


def test_truncated_body(tmp_path):
    points, attributes = make_points(10)
    path = tmp_path / "t.ply"
    write_points_ply(path, points, attributes)
    path.write_bytes(path.read_bytes()[:-5])
    with pytest.raises(DatasetError, match="truncated") as exc_info:
        read_points_ply(path)
    _assert_names_file(exc_info, path)


def test_missing_xyz(tmp_path):
    path = tmp_path / "noz.ply"
    header = "ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty double x\nproperty double y\nend_header\n"
    path.write_bytes(header.encode() + np.zeros(2).tobytes())
    with pytest.raises(DatasetError, match="no z") as exc_info:
        read_points_ply(path)
    _assert_names_file(exc_info, path)


def test_ascii_and_unknown_types_are_refused(tmp_path):
    path = tmp_path / "a.ply"
    path.write_text("ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\nend_header\n1 2 3\n")
    with pytest.raises(DatasetError, match="ASCII"):
        read_points_ply(path)
    path.write_text("ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty quad x\nend_header\n")
    with pytest.raises(DatasetError, match="property"):
        read_points_ply(path)


def test_bad_arguments_to_write(tmp_path):
    path = tmp_path / "w.ply"
    with pytest.raises(DemGraphError, match="N, 3"):
        write_points_ply(path, np.zeros((4, 2)))
    with pytest.raises(DemGraphError, match="int64"):
        write_points_ply(path, np.zeros((4, 3)), {"point_id": np.arange(4, dtype=np.int64)})
    with pytest.raises(DemGraphError, match="shape"):
        write_points_ply(path, np.zeros((4, 3)), {"sigma_m": np.zeros(3)})
    with pytest.raises(DemGraphError, match="name"):
        write_points_ply(path, np.zeros((4, 3)), {"bad name": np.zeros(4)})
    with pytest.raises(DemGraphError, match="clashes"):
        write_points_ply(path, np.zeros((4, 3)), {"z": np.zeros(4)})
    with pytest.raises(DatasetError, match="cannot write"):
        write_points_ply(tmp_path / "no" / "such" / "dir.ply", np.zeros((1, 3)))
