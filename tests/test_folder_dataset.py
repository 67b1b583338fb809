"""The dataset folder format: exact round trips, event order, streaming writes, validation on open."""

from __future__ import annotations

import re
import threading
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import yaml

from dem_graph import progress as progress_module
from dem_graph.datasets import folder as folder_module
from dem_graph.datasets.base import GroundTruth, Sequence, read_ahead
from dem_graph.datasets.events import CameraFrame, Event, LaserScan, Odometry
from dem_graph.datasets.folder import FolderSequence, open_folder_dataset, write_folder_dataset
from dem_graph.errors import ConfigError, DatasetError
from dem_graph.geometry.grid import ElevationGrid, GridGeometry
from dem_graph.geometry.rig import default_rig, rig_to_dict
from dem_graph.geometry.se3 import make_pose, rotation_from_rpy
from dem_graph.geometry.trajectory import Trajectory

T0_S = 1000.0
_KIND_ORDER = {Odometry: 0, LaserScan: 1, CameraFrame: 2}


def tiny_rig():
    """The default rig with a 32x24 camera, the size of :class:`TinySequence`'s images."""
    rig = default_rig()
    camera = rig.camera.model_copy(update=dict(width_px=32, height_px=24, fx_px=22.4, fy_px=22.4, cx_px=15.5, cy_px=11.5))
    return rig.model_copy(update={"camera": camera})


class TinySequence(Sequence):
    """6 frames of 32x24 images, 3 scans with NaNs, 10 odometry increments and ground truth, all in memory."""

    name = "tiny"
    description = "synthetic sequence for the folder-format tests\nsecond line, ünïcode"

    def __init__(self, with_odometry: bool = True, with_ground_truth: bool = True, with_elevation: bool = True):
        rng = np.random.default_rng(42)
        self._rig = tiny_rig()
        beams = self._rig.laser.beams.count

        self.frames = []
        for k in range(6):
            t = T0_S + 0.04 * k  # frame 0 and 2 share their time with a scan and an odometry event
            shape = (24, 32) if k == 1 else (24, 32, 3)  # one grey frame, the rest BGR
            self.frames.append(CameraFrame(t, rng.integers(0, 256, size=shape, dtype=np.uint8), k))

        self.scans = []
        for k in range(3):
            ranges = rng.uniform(0.5, 20.0, beams).astype(np.float32)
            ranges[rng.random(beams) < 0.2] = np.nan
            self.scans.append(LaserScan(T0_S + 0.08 * k, ranges, k))

        self.odometry = []
        if with_odometry:
            for k in range(10):
                t_prev, t = T0_S + 0.02 * k, T0_S + 0.02 * (k + 1)
                R = rotation_from_rpy(*rng.normal(scale=0.01, size=3))
                T = make_pose(R, rng.normal(scale=0.05, size=3))
                A = rng.normal(scale=1e-3, size=(6, 6))
                self.odometry.append(Odometry(t, t_prev, T, A @ A.T + 1e-6 * np.eye(6), k))
        self._has_odometry = with_odometry

        t_gt = T0_S + 0.01 * np.arange(25)
        yaw = 0.1 * np.sin(t_gt - T0_S)
        R = rotation_from_rpy(0.01 * np.cos(t_gt), 0.02 * np.sin(t_gt), yaw)
        p = np.stack([np.cos(t_gt), np.sin(t_gt), 0.1 * t_gt], axis=1)
        self._trajectory = Trajectory.from_poses(t_gt, make_pose(R, p))
        geometry = GridGeometry(x_min_m=-5.0, y_max_m=8.0, resolution_m=0.25, n_rows=12, n_cols=10)
        z = rng.normal(scale=0.3, size=geometry.shape).astype(np.float32)
        z[0, :3] = np.nan
        self._elevation = ElevationGrid(geometry, z) if with_elevation else None
        self._with_ground_truth = with_ground_truth
        self.on_event = None  # test hook, called when the consumer comes back for the next event

    @property
    def rig(self):
        return self._rig

    @property
    def t_start_s(self) -> float:
        return T0_S

    @property
    def T_world_body_initial(self) -> np.ndarray:
        return self._trajectory.at(T0_S)

    @property
    def ground_truth(self):
        return GroundTruth(self._trajectory, self._elevation) if self._with_ground_truth else None

    @property
    def has_odometry(self) -> bool:
        return self._has_odometry

    def events(self) -> Iterator[Event]:
        merged = sorted(
            [*self.odometry, *self.scans, *self.frames], key=lambda e: (e.t_s, _KIND_ORDER[type(e)], e.index)
        )
        for event in merged:
            yield event
            if self.on_event is not None:
                self.on_event(event)


@pytest.fixture(autouse=True)
def no_progress_bars():
    progress_module.set_progress_enabled(False)
    yield
    progress_module.set_progress_enabled(True)


@pytest.fixture
def written(tmp_path) -> Path:
    return write_folder_dataset(TinySequence(), tmp_path / "ds")


def assert_events_equal(a: list[Event], b: list[Event]) -> None:
    assert len(a) == len(b)
    for ea, eb in zip(a, b):
        assert type(ea) is type(eb)
        assert ea.t_s == eb.t_s and ea.index == eb.index
        if isinstance(ea, CameraFrame):
            assert ea.image.dtype == eb.image.dtype and ea.image.shape == eb.image.shape
            np.testing.assert_array_equal(ea.image, eb.image)
        elif isinstance(ea, LaserScan):
            assert eb.ranges_m.dtype == np.float32
            np.testing.assert_array_equal(ea.ranges_m, eb.ranges_m)
        else:
            assert ea.t_prev_s == eb.t_prev_s
            np.testing.assert_array_equal(ea.T_prev_curr, eb.T_prev_curr)
            np.testing.assert_array_equal(ea.covariance, eb.covariance)


def assert_sequences_equal(a: Sequence, b: Sequence) -> None:
    assert a.name == b.name
    assert a.t_start_s == b.t_start_s
    np.testing.assert_array_equal(a.T_world_body_initial, b.T_world_body_initial)
    assert rig_to_dict(a.rig) == rig_to_dict(b.rig)
    np.testing.assert_array_equal(a.rig.T_cam_laser, b.rig.T_cam_laser)
    assert a.has_odometry == b.has_odometry
    assert (a.ground_truth is None) == (b.ground_truth is None)
    if a.ground_truth is not None:
        ta, tb = a.ground_truth.trajectory, b.ground_truth.trajectory
        np.testing.assert_array_equal(ta.t_s, tb.t_s)
        np.testing.assert_array_equal(ta.positions_xyz, tb.positions_xyz)
        np.testing.assert_array_equal(ta.orientations_quat_xyzw, tb.orientations_quat_xyzw)
        assert (a.ground_truth.elevation is None) == (b.ground_truth.elevation is None)
        if a.ground_truth.elevation is not None:
            assert a.ground_truth.elevation.geometry == b.ground_truth.elevation.geometry
            np.testing.assert_array_equal(a.ground_truth.elevation.z_m, b.ground_truth.elevation.z_m)
    assert_events_equal(list(a.events()), list(b.events()))


# ---------------------------------------------------------------------------------------------- round trips


def test_round_trip_is_exact(tmp_path):
    source = TinySequence()
    out = write_folder_dataset(source, tmp_path / "ds", progress_desc="test")
    assert out == tmp_path / "ds"
    loaded = open_folder_dataset(out)
    assert isinstance(loaded, FolderSequence)
    assert loaded.description == source.description
    assert (loaded.n_frames, loaded.n_scans, loaded.n_odometry) == (6, 3, 10)
    assert_sequences_equal(source, loaded)
    assert sorted(p.name for p in (out / "images").iterdir()) == [f"{k:06d}.png" for k in range(6)]

    # written again from the folder: identical text files, arrays and images
    again = write_folder_dataset(loaded, tmp_path / "ds2")
    for name in ["dataset.yaml", "rig.yaml", "camera.csv", "ground_truth/trajectory.tum"]:
        assert (again / name).read_bytes() == (out / name).read_bytes(), name
    for name in ["laser.npz", "odometry.npz"]:
        with np.load(out / name) as first, np.load(again / name) as second:
            assert sorted(first.files) == sorted(second.files)
            for key in first.files:
                assert first[key].dtype == second[key].dtype
                np.testing.assert_array_equal(first[key], second[key])
    for k in range(6):
        assert (again / f"images/{k:06d}.png").read_bytes() == (out / f"images/{k:06d}.png").read_bytes()
    assert_sequences_equal(loaded, FolderSequence(again))


def test_file_layout_and_dtypes(written):
    meta = yaml.safe_load((written / "dataset.yaml").read_text())
    assert meta["format"] == "dem_graph-folder" and meta["version"] == 1
    assert meta["counts"] == {"frames": 6, "scans": 3, "odometry": 10}
    assert meta["has_ground_truth"] is True
    lines = (written / "camera.csv").read_text().splitlines()
    assert lines[0] == "index,t_s,file"
    assert lines[1] == f"0,{T0_S!r},images/000000.png"
    with np.load(written / "laser.npz") as laser:
        assert laser["t_s"].dtype == np.float64 and laser["ranges_m"].dtype == np.float32
        assert laser["ranges_m"].shape == (3, default_rig().laser.beams.count)
        assert np.isnan(laser["ranges_m"]).any()
    with np.load(written / "odometry.npz") as odo:
        assert odo["T_prev_curr"].shape == (10, 4, 4) and odo["covariance"].shape == (10, 6, 6)
    assert (written / "ground_truth" / "trajectory.tum").is_file()
    assert (written / "ground_truth" / "elevation.tif").is_file()


def test_events_merge_order_at_equal_times(written):
    events = list(FolderSequence(written).events())
    keys = [(e.t_s, _KIND_ORDER[type(e)]) for e in events]
    assert keys == sorted(keys)
    at_t0 = [type(e) for e in events if e.t_s == T0_S]
    assert at_t0 == [LaserScan, CameraFrame]  # no odometry ends at t0
    t = T0_S + 0.08  # odometry 3, scan 1 and frame 2 all at this time
    shared = [type(e) for e in events if e.t_s == t]
    assert shared == [Odometry, LaserScan, CameraFrame]
    # events() starts over on every call
    assert len(list(FolderSequence(written).events())) == len(events) == 19


def test_writer_streams_images(tmp_path, monkeypatch):
    source = TinySequence()
    out = tmp_path / "ds"
    seen = []

    lag = 2  # frames the background writer may hold

    def check_written(event):
        if isinstance(event, CameraFrame):
            # bounded memory: a frame is on disk at most `lag` + 1 frames after it was produced
            if event.index > lag:
                assert (out / "images" / f"{event.index - lag - 1:06d}.png").is_file()
            seen.append(event.index)

    source.on_event = check_written
    monkeypatch.setattr(folder_module._BackgroundPngWriter, "__init__", _writer_with_lag(lag))
    write_folder_dataset(source, out)
    assert seen == list(range(6))
    assert all((out / "images" / f"{k:06d}.png").is_file() for k in range(6))


def _writer_with_lag(lag):
    original = folder_module._BackgroundPngWriter.__init__

    def init(self, max_pending=lag, compression=1):
        original(self, max_pending=lag, compression=compression)

    return init


def test_without_odometry_and_ground_truth(tmp_path):
    source = TinySequence(with_odometry=False, with_ground_truth=False)
    out = write_folder_dataset(source, tmp_path / "ds")
    assert not (out / "odometry.npz").exists()
    assert not (out / "ground_truth").exists()
    loaded = FolderSequence(out)
    assert loaded.has_odometry is False and loaded.ground_truth is None
    assert_sequences_equal(source, loaded)


def test_ground_truth_without_elevation(tmp_path):
    out = write_folder_dataset(TinySequence(with_elevation=False), tmp_path / "ds")
    assert not (out / "ground_truth" / "elevation.tif").exists()
    gt = FolderSequence(out).ground_truth
    assert gt is not None and gt.elevation is None


# ---------------------------------------------------------------------------------------------- writer refusals


def test_write_refuses_non_empty_folder(tmp_path):
    (tmp_path / "ds").mkdir()
    (tmp_path / "ds" / "keep.txt").write_text("x")
    with pytest.raises(DatasetError, match=r"ds: output folder exists and is not empty"):
        write_folder_dataset(TinySequence(), tmp_path / "ds")


def test_write_rejects_wrong_beam_count(tmp_path):
    source = TinySequence()
    source.scans[1] = LaserScan(source.scans[1].t_s, np.ones(5, dtype=np.float32), 1)
    with pytest.raises(DatasetError, match=r"laser\.npz: scan 1: .*has 361 beams"):
        write_folder_dataset(source, tmp_path / "ds")


def test_write_rejects_non_increasing_frame_times(tmp_path):
    source = TinySequence()
    source.frames[3] = CameraFrame(source.frames[2].t_s, source.frames[3].image, 3)
    with pytest.raises(DatasetError, match=r"camera\.csv: frame 3: time .* is not after"):
        write_folder_dataset(source, tmp_path / "ds")


def test_write_rejects_bad_image(tmp_path):
    source = TinySequence()
    source.frames[0] = CameraFrame(T0_S, np.zeros((24, 32), dtype=np.float32), 0)
    with pytest.raises(DatasetError, match=r"000000\.png: expected an 8-bit grey"):
        write_folder_dataset(source, tmp_path / "ds")


# ---------------------------------------------------------------------------------------------- validation on open


def edit_yaml(path: Path, **changes) -> None:
    data = yaml.safe_load(path.read_text())
    data.update(changes)
    path.write_text(yaml.safe_dump(data, sort_keys=False))


def edit_npz(path: Path, drop: str | None = None, **changes) -> None:
    with np.load(path) as npz:
        arrays = {k: npz[k] for k in npz.files if k != drop}
    arrays.update(changes)
    np.savez(path, **arrays)


def laser_arrays(root: Path) -> dict[str, np.ndarray]:
    with np.load(root / "laser.npz") as npz:
        return {k: npz[k] for k in npz.files}


def odometry_arrays(root: Path) -> dict[str, np.ndarray]:
    with np.load(root / "odometry.npz") as npz:
        return {k: npz[k] for k in npz.files}


def test_missing_folder(tmp_path):
    with pytest.raises(DatasetError, match=r"nowhere: dataset folder not found"):
        FolderSequence(tmp_path / "nowhere")


@pytest.mark.parametrize(
    "name, problem",
    [
        ("dataset.yaml", "not found"),
        ("rig.yaml", "not found"),
        ("camera.csv", "not found"),
        ("laser.npz", "not found"),
        ("images/000004.png", "listed in camera.csv .line 6. not found"),
        ("ground_truth/trajectory.tum", "file not found"),
    ],
)
def test_missing_file(written, name, problem):
    (written / name).unlink()
    with pytest.raises(DatasetError, match=rf"{re.escape(name)}: .*{problem}"):
        FolderSequence(written)


def test_missing_odometry_when_counted(written):
    (written / "odometry.npz").unlink()
    with pytest.raises(DatasetError, match=r"odometry\.npz: not found, but dataset\.yaml counts 10"):
        FolderSequence(written)


def test_wrong_format(written):
    edit_yaml(written / "dataset.yaml", format="something-else")
    with pytest.raises(DatasetError, match=r"dataset\.yaml: format is 'something-else', expected 'dem_graph-folder'"):
        FolderSequence(written)


def test_wrong_version(written):
    edit_yaml(written / "dataset.yaml", version=2)
    with pytest.raises(DatasetError, match=r"dataset\.yaml: unsupported format version 2"):
        FolderSequence(written)


def test_dataset_yaml_not_yaml(written):
    (written / "dataset.yaml").write_text("format: [unclosed\n")
    with pytest.raises(DatasetError, match=r"dataset\.yaml: not valid YAML"):
        FolderSequence(written)


def test_dataset_yaml_missing_key(written):
    data = yaml.safe_load((written / "dataset.yaml").read_text())
    del data["t_start_s"]
    (written / "dataset.yaml").write_text(yaml.safe_dump(data))
    with pytest.raises(DatasetError, match=r"dataset\.yaml: missing key 't_start_s'"):
        FolderSequence(written)


def test_count_mismatch(written):
    edit_yaml(written / "dataset.yaml", counts={"frames": 6, "scans": 4, "odometry": 10})
    with pytest.raises(DatasetError, match=r"laser\.npz: holds 3 scans but dataset\.yaml counts 4"):
        FolderSequence(written)


def test_nan_in_initial_pose(written):
    T = np.eye(4).tolist()
    T[0][3] = float("nan")
    edit_yaml(written / "dataset.yaml", T_world_body_initial=T)
    with pytest.raises(DatasetError, match=r"dataset\.yaml: T_world_body_initial contains NaN"):
        FolderSequence(written)


def test_nan_start_time(written):
    edit_yaml(written / "dataset.yaml", t_start_s=float("nan"))
    with pytest.raises(DatasetError, match=r"dataset\.yaml: t_start_s must be a finite number"):
        FolderSequence(written)


@pytest.mark.parametrize("content", [b"not a zip archive at all", b"PK\x03\x04 truncated"])
def test_corrupt_laser_npz(written, content):
    (written / "laser.npz").write_bytes(content)
    with pytest.raises(DatasetError, match=r"laser\.npz: not a readable npz archive"):
        FolderSequence(written)


def test_corrupt_odometry_npz(written):
    (written / "odometry.npz").write_bytes(b"garbage")
    with pytest.raises(DatasetError, match=r"odometry\.npz: not a readable npz archive"):
        FolderSequence(written)


def test_npz_member_corrupt(written):
    data = bytearray((written / "laser.npz").read_bytes())
    start = data.find(b"ranges_m.npy")
    data[start + 200 : start + 400] = b"\x00" * 200  # inside the stored array, zip CRC no longer matches
    (written / "laser.npz").write_bytes(bytes(data))
    with pytest.raises(DatasetError, match=r"laser\.npz: array 'ranges_m' is corrupt"):
        FolderSequence(written)


def test_npz_missing_key(written):
    edit_npz(written / "laser.npz", drop="ranges_m")
    with pytest.raises(DatasetError, match=r"laser\.npz: missing array 'ranges_m'"):
        FolderSequence(written)


def test_single_npy_instead_of_npz(written):
    with open(written / "laser.npz", "wb") as f:
        np.save(f, np.zeros(3))
    with pytest.raises(DatasetError, match=r"laser\.npz: not an npz archive"):
        FolderSequence(written)


def test_ranges_not_2d(written):
    edit_npz(written / "laser.npz", ranges_m=laser_arrays(written)["ranges_m"].ravel())
    with pytest.raises(DatasetError, match=r"laser\.npz: ranges_m has shape \(1083,\), expected \(N, B\)"):
        FolderSequence(written)


def test_ranges_wrong_beam_count(written):
    edit_npz(written / "laser.npz", ranges_m=laser_arrays(written)["ranges_m"][:, :100])
    with pytest.raises(DatasetError, match=r"laser\.npz: ranges_m has 100 beams per scan, the rig's laser has 361"):
        FolderSequence(written)


def test_ranges_scan_count_differs_from_times(written):
    edit_npz(written / "laser.npz", ranges_m=laser_arrays(written)["ranges_m"][:2])
    with pytest.raises(DatasetError, match=r"laser\.npz: ranges_m has 2 scans but t_s has 3 times"):
        FolderSequence(written)


def test_ranges_integer_dtype(written):
    edit_npz(written / "laser.npz", ranges_m=np.ones((3, 361), dtype=np.int32))
    with pytest.raises(DatasetError, match=r"laser\.npz: ranges_m must be floating point, got dtype int32"):
        FolderSequence(written)


def test_infinite_range(written):
    ranges = laser_arrays(written)["ranges_m"]
    ranges[2, 7] = np.inf
    edit_npz(written / "laser.npz", ranges_m=ranges)
    with pytest.raises(DatasetError, match=r"laser\.npz: scan 2 beam 7: range inf is invalid"):
        FolderSequence(written)


def test_laser_times_not_increasing(written):
    t = laser_arrays(written)["t_s"]
    t[2] = t[1]
    edit_npz(written / "laser.npz", t_s=t)
    with pytest.raises(DatasetError, match=r"laser\.npz: t_s is not strictly increasing at index 2"):
        FolderSequence(written)


def test_nan_laser_time(written):
    t = laser_arrays(written)["t_s"]
    t[1] = np.nan
    edit_npz(written / "laser.npz", t_s=t)
    with pytest.raises(DatasetError, match=r"laser\.npz: t_s\[1\] is NaN"):
        FolderSequence(written)


def test_event_before_start(written):
    t = laser_arrays(written)["t_s"]
    t[0] = T0_S - 1.0
    edit_npz(written / "laser.npz", t_s=t)
    with pytest.raises(DatasetError, match=r"laser\.npz: t_s\[0\] = 999\.0 is before t_start_s"):
        FolderSequence(written)


def test_odometry_times_not_increasing(written):
    t = odometry_arrays(written)["t_s"]
    t[5] = t[3]
    edit_npz(written / "odometry.npz", t_s=t)
    with pytest.raises(DatasetError, match=r"odometry\.npz: t_s is not strictly increasing at index 5"):
        FolderSequence(written)


def test_odometry_pose_wrong_shape(written):
    edit_npz(written / "odometry.npz", T_prev_curr=odometry_arrays(written)["T_prev_curr"][:, :3, :])
    with pytest.raises(DatasetError, match=r"odometry\.npz: T_prev_curr has shape \(10, 3, 4\), expected \(10, 4, 4\)"):
        FolderSequence(written)


def test_odometry_covariance_wrong_shape(written):
    edit_npz(written / "odometry.npz", covariance=np.zeros((10, 3, 3)))
    with pytest.raises(DatasetError, match=r"odometry\.npz: covariance has shape \(10, 3, 3\), expected \(10, 6, 6\)"):
        FolderSequence(written)


def test_odometry_nan_pose(written):
    T = odometry_arrays(written)["T_prev_curr"]
    T[4, 1, 3] = np.nan
    edit_npz(written / "odometry.npz", T_prev_curr=T)
    with pytest.raises(DatasetError, match=r"odometry\.npz: T_prev_curr\[4\] contains NaN"):
        FolderSequence(written)


def test_odometry_pose_not_rigid(written):
    T = odometry_arrays(written)["T_prev_curr"]
    T[6, :3, :3] *= 2.0
    edit_npz(written / "odometry.npz", T_prev_curr=T)
    with pytest.raises(DatasetError, match=r"odometry\.npz: T_prev_curr\[6\] is not a rigid transform"):
        FolderSequence(written)


def test_odometry_nan_covariance(written):
    C = odometry_arrays(written)["covariance"]
    C[2, 0, 0] = np.nan
    edit_npz(written / "odometry.npz", covariance=C)
    with pytest.raises(DatasetError, match=r"odometry\.npz: covariance\[2\] contains NaN"):
        FolderSequence(written)


def test_odometry_prev_time_after_time(written):
    arrays = odometry_arrays(written)
    t_prev = arrays["t_prev_s"]
    t_prev[3] = arrays["t_s"][3] + 0.5
    edit_npz(written / "odometry.npz", t_prev_s=t_prev)
    with pytest.raises(DatasetError, match=r"odometry\.npz: odometry 3: t_prev_s = .* is after t_s"):
        FolderSequence(written)


def _rewrite_camera_csv(root: Path, line_no: int, new_line: str) -> None:
    lines = (root / "camera.csv").read_text().splitlines()
    lines[line_no - 1] = new_line
    (root / "camera.csv").write_text("\n".join(lines) + "\n")


def test_camera_times_not_increasing(written):
    _rewrite_camera_csv(written, 4, f"2,{T0_S + 0.04!r},images/000002.png")
    with pytest.raises(DatasetError, match=r"camera\.csv: line 4: frame 2 time .* is not after"):
        FolderSequence(written)


def test_camera_nan_time(written):
    _rewrite_camera_csv(written, 3, "1,nan,images/000001.png")
    with pytest.raises(DatasetError, match=r"camera\.csv: line 3: t_s is NaN"):
        FolderSequence(written)


def test_camera_bad_header(written):
    _rewrite_camera_csv(written, 1, "i,time,path")
    with pytest.raises(DatasetError, match=r"camera\.csv: line 1: header must be index,t_s,file"):
        FolderSequence(written)


def test_camera_wrong_columns(written):
    _rewrite_camera_csv(written, 2, f"0,{T0_S!r}")
    with pytest.raises(DatasetError, match=r"camera\.csv: line 2: expected 3 columns"):
        FolderSequence(written)


def test_camera_index_out_of_order(written):
    _rewrite_camera_csv(written, 2, f"7,{T0_S!r},images/000000.png")
    with pytest.raises(DatasetError, match=r"camera\.csv: line 2: index 7 out of order"):
        FolderSequence(written)


def test_corrupt_png_is_reported_when_read(written):
    (written / "images" / "000003.png").write_bytes(b"\x89PNG\r\n\x1a\n" + b"\x00" * 40)
    sequence = FolderSequence(written)  # images are only checked for existence on open
    seen = []
    with pytest.raises(DatasetError, match=r"images/000003\.png: unreadable or corrupt PNG"):
        for event in sequence.events():
            seen.append(event)
    # images are decoded ahead of time in a thread, but the error comes when frame 3 is reached:
    # frames 0-2 and every scan and odometry before frame 3 were delivered first
    assert [e.index for e in seen if isinstance(e, CameraFrame)] == [0, 1, 2]
    (written / "images" / "000003.png").write_bytes((written / "images" / "000002.png").read_bytes())
    intact = list(FolderSequence(written).events())
    first_3 = next(k for k, e in enumerate(intact) if isinstance(e, CameraFrame) and e.index == 3)
    assert [(type(e), e.index) for e in seen] == [(type(e), e.index) for e in intact[:first_3]]


def test_read_ahead_keeps_order_raises_in_place_and_stops_early():
    def produce():
        for k in range(10):
            if k == 6:
                raise DatasetError("x.png", "unreadable")
            yield k

    got = []
    with pytest.raises(DatasetError, match="x.png: unreadable"):
        for item in read_ahead(produce(), depth=2):
            got.append(item)
    assert got == [0, 1, 2, 3, 4, 5]
    # a consumer that stops early stops the producing thread too
    produced = []

    def slow_source():
        for k in range(1000):
            produced.append(k)
            yield k

    stream = read_ahead(slow_source(), depth=3)
    assert [next(stream) for _ in range(5)] == [0, 1, 2, 3, 4]
    stream.close()
    assert not any(t.name == "read-ahead" and t.is_alive() for t in threading.enumerate())
    assert len(produced) <= 5 + 3 + 2  # what was consumed, the queue's depth, one in hand and one blocked


def test_truncated_png_is_reported_when_read(written):
    path = written / "images" / "000005.png"
    path.write_bytes(path.read_bytes()[:100])
    with pytest.raises(DatasetError, match=r"images/000005\.png: unreadable or corrupt PNG"):
        list(FolderSequence(written).events())


def test_invalid_rig(written):
    rig = yaml.safe_load((written / "rig.yaml").read_text())
    rig["laser"]["range_max_m"] = -1.0
    (written / "rig.yaml").write_text(yaml.safe_dump(rig))
    with pytest.raises(ConfigError, match=r"rig\.yaml: laser\.range_max_m is -1\.0; it must be a finite number above 0"):
        FolderSequence(written)


def test_binary_rig_file(written):
    (written / "rig.yaml").write_bytes(b"\xff\xfe\x00\x81 not text")
    with pytest.raises(ConfigError, match=r"rig\.yaml: cannot read the rig file"):
        FolderSequence(written)


def test_nan_in_ground_truth_trajectory(written):
    path = written / "ground_truth" / "trajectory.tum"
    lines = path.read_text().splitlines()
    fields = lines[3].split()
    fields[2] = "nan"
    lines[3] = " ".join(fields)
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(DatasetError, match=r"trajectory\.tum: line 4: NaN or infinite"):
        FolderSequence(written)


def test_corrupt_ground_truth_elevation(written):
    (written / "ground_truth" / "elevation.tif").write_bytes(b"nope")
    with pytest.raises(DatasetError, match=r"elevation\.tif: not a readable GeoTIFF"):
        FolderSequence(written)
