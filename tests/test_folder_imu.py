"""The dataset folder format's optional IMU stream (imu.npz): exact round trip, merge order, validation on open."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from dem_graph import progress as progress_module
from dem_graph.datasets.events import CameraFrame, ImuSample, LaserScan, Odometry
from dem_graph.datasets.folder import FolderSequence, write_folder_dataset
from dem_graph.datasets.memory import InMemorySequence
from dem_graph.errors import DatasetError
from dem_graph.geometry.rig import default_rig

T0_S = 100.0
N_IMU = 21  # 100 Hz over 0.2 s
IMU_EVERY = 5  # a camera frame at every 5th IMU time, the same float
_STREAM = {Odometry: 0, LaserScan: 1, CameraFrame: 2, ImuSample: 3}


def tiny_rig():
    """The default rig (it has an IMU) with a 32x24 camera."""
    rig = default_rig()
    camera = rig.camera.model_copy(update=dict(width_px=32, height_px=24, fx_px=22.4, fy_px=22.4, cx_px=15.5, cy_px=11.5))
    return rig.model_copy(update={"camera": camera})


def imu_truth() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Times, rates and specific forces of the IMU samples: random float64, at rest near +9.81 up."""
    rng = np.random.default_rng(7)
    t = T0_S + 0.01 * np.arange(N_IMU)
    gyro = rng.normal(scale=0.05, size=(N_IMU, 3))
    accel = rng.normal(scale=0.3, size=(N_IMU, 3)) + [0.0, 0.0, 9.80665]
    return t, gyro, accel


def tiny_sequence(with_imu: bool = True) -> InMemorySequence:
    """5 random 32x24 frames, 3 laser scans and (``with_imu``) 21 IMU samples, in replay order."""
    rng = np.random.default_rng(3)
    rig = tiny_rig()
    t_imu, gyro, accel = imu_truth()
    frames = [CameraFrame(float(t), rng.integers(0, 256, size=(24, 32, 3), dtype=np.uint8), k) for k, t in enumerate(t_imu[::IMU_EVERY])]
    beams = rig.laser.beams.count
    scans = [LaserScan(T0_S + 0.003 + 0.07 * k, rng.uniform(1.0, 10.0, beams).astype(np.float32), k) for k in range(3)]
    imu = [ImuSample(float(t_imu[k]), gyro[k].copy(), accel[k].copy(), k) for k in range(N_IMU)] if with_imu else []
    events = sorted([*frames, *scans, *imu], key=lambda e: (e.t_s, _STREAM[type(e)], e.index))
    return InMemorySequence(rig, events, np.eye(4), T0_S, name="tiny-imu")


@pytest.fixture(autouse=True)
def no_progress_bars():
    progress_module.set_progress_enabled(False)
    yield
    progress_module.set_progress_enabled(True)


@pytest.fixture
def written(tmp_path) -> Path:
    return write_folder_dataset(tiny_sequence(), tmp_path / "ds")


def imu_arrays(root: Path) -> dict[str, np.ndarray]:
    with np.load(root / "imu.npz") as npz:
        return {k: npz[k] for k in npz.files}


def edit_npz(path: Path, **changes) -> None:
    with np.load(path) as npz:
        arrays = {k: npz[k] for k in npz.files}
    arrays.update(changes)
    np.savez(path, **arrays)


def edit_counts(root: Path, **changes) -> None:
    path = root / "dataset.yaml"
    data = yaml.safe_load(path.read_text())
    data["counts"].update(changes)
    path.write_text(yaml.safe_dump(data, sort_keys=False))


# ---------------------------------------------------------------------------------------------- round trip


def test_imu_round_trip_is_bit_identical_and_merged_after_camera(written, tmp_path):
    t_imu, gyro, accel = imu_truth()
    assert yaml.safe_load((written / "dataset.yaml").read_text())["counts"] == {"frames": 5, "scans": 3, "odometry": 0, "imu": N_IMU}
    stored = imu_arrays(written)
    assert sorted(stored) == ["accel_mps2", "gyro_rad_s", "t_s"]
    assert all(a.dtype == np.float64 for a in stored.values())
    assert stored["gyro_rad_s"].shape == stored["accel_mps2"].shape == (N_IMU, 3)

    loaded = FolderSequence(written)
    assert loaded.has_imu is True and loaded.n_imu == N_IMU
    assert "imu=21" in repr(loaded)
    events = list(loaded.events())
    assert loaded.event_count() == len(events) == 5 + 3 + N_IMU
    samples = [e for e in events if isinstance(e, ImuSample)]
    assert [s.index for s in samples] == list(range(N_IMU))
    np.testing.assert_array_equal([s.t_s for s in samples], t_imu)
    np.testing.assert_array_equal(np.array([s.gyro_rad_s for s in samples]), gyro)  # bit-identical: float64 throughout
    np.testing.assert_array_equal(np.array([s.accel_mps2 for s in samples]), accel)
    assert all(s.gyro_rad_s.shape == (3,) and s.gyro_rad_s.dtype == np.float64 for s in samples)

    # merged in time order; at a camera frame's time the IMU sample comes right after the frame
    keys = [(e.t_s, _STREAM[type(e)]) for e in events]
    assert keys == sorted(keys)
    for k in range(5):
        shared = [(type(e), e.index) for e in events if e.t_s == t_imu[IMU_EVERY * k]]
        assert shared == [(CameraFrame, k), (ImuSample, IMU_EVERY * k)]

    # written again from the folder: the same imu.npz and dataset.yaml
    again = write_folder_dataset(loaded, tmp_path / "ds2")
    assert (again / "dataset.yaml").read_bytes() == (written / "dataset.yaml").read_bytes()
    for key, value in imu_arrays(again).items():
        np.testing.assert_array_equal(value, stored[key])


def test_without_imu_no_file_no_count(tmp_path):
    out = write_folder_dataset(tiny_sequence(with_imu=False), tmp_path / "ds")
    assert not (out / "imu.npz").exists()
    counts = yaml.safe_load((out / "dataset.yaml").read_text())["counts"]
    assert counts == {"frames": 5, "scans": 3, "odometry": 0}
    loaded = FolderSequence(out)
    assert loaded.has_imu is False and loaded.n_imu == 0
    assert not any(isinstance(e, ImuSample) for e in loaded.events())
    assert loaded.event_count() == 8


# ---------------------------------------------------------------------------------------------- refused on open


def test_nan_gyro_names_the_sample(written):
    gyro = imu_arrays(written)["gyro_rad_s"]
    gyro[7, 1] = np.nan
    edit_npz(written / "imu.npz", gyro_rad_s=gyro)
    with pytest.raises(DatasetError, match=r"imu\.npz: sample 7: gyro_rad_s \[.*nan.*\] contains NaN or infinite values"):
        FolderSequence(written)


def test_infinite_accel_names_the_sample(written):
    accel = imu_arrays(written)["accel_mps2"]
    accel[12, 2] = np.inf
    edit_npz(written / "imu.npz", accel_mps2=accel)
    with pytest.raises(DatasetError, match=r"imu\.npz: sample 12: accel_mps2 .* contains NaN or infinite values"):
        FolderSequence(written)


def test_imu_times_not_increasing(written):
    t = imu_arrays(written)["t_s"]
    t[4] = t[3]
    edit_npz(written / "imu.npz", t_s=t)
    with pytest.raises(DatasetError, match=r"imu\.npz: t_s is not strictly increasing at index 4"):
        FolderSequence(written)


def test_imu_time_before_start(written):
    t = imu_arrays(written)["t_s"]
    t[0] = T0_S - 1.0
    edit_npz(written / "imu.npz", t_s=t)
    with pytest.raises(DatasetError, match=r"imu\.npz: t_s\[0\] = 99\.0 is before t_start_s"):
        FolderSequence(written)


def test_imu_wrong_shape(written):
    edit_npz(written / "imu.npz", gyro_rad_s=imu_arrays(written)["gyro_rad_s"][:, :2])
    with pytest.raises(DatasetError, match=r"imu\.npz: gyro_rad_s has shape \(21, 2\), expected \(21, 3\)"):
        FolderSequence(written)


def test_imu_integer_dtype(written):
    edit_npz(written / "imu.npz", accel_mps2=np.ones((N_IMU, 3), dtype=np.int32))
    with pytest.raises(DatasetError, match=r"imu\.npz: accel_mps2 must be floating point, got dtype int32"):
        FolderSequence(written)


def test_imu_count_mismatch(written):
    edit_counts(written, imu=N_IMU + 1)
    with pytest.raises(DatasetError, match=r"imu\.npz: holds 21 imu samples but dataset\.yaml counts 22"):
        FolderSequence(written)


def test_imu_file_without_count_key(written):
    """A dataset.yaml of before the IMU stream (no counts.imu) counts no sample: an added imu.npz is refused."""
    data = yaml.safe_load((written / "dataset.yaml").read_text())
    del data["counts"]["imu"]
    (written / "dataset.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    with pytest.raises(DatasetError, match=r"imu\.npz: holds 21 imu samples but dataset\.yaml counts 0"):
        FolderSequence(written)


def test_imu_counted_but_missing(written):
    (written / "imu.npz").unlink()
    with pytest.raises(DatasetError, match=r"imu\.npz: not found, but dataset\.yaml counts 21 imu samples"):
        FolderSequence(written)


def test_imu_file_but_rig_has_no_imu_section(written):
    rig = yaml.safe_load((written / "rig.yaml").read_text())
    del rig["imu"]
    (written / "rig.yaml").write_text(yaml.safe_dump(rig, sort_keys=False))
    with pytest.raises(DatasetError, match=r"imu\.npz: the rig has no imu section; add one .*T_body_imu and the noise densities"):
        FolderSequence(written)


def test_imu_clock_jump(written):
    t = imu_arrays(written)["t_s"]
    t[10:] += 1000.0
    edit_npz(written / "imu.npz", t_s=t)
    with pytest.raises(DatasetError, match=r"imu\.npz: t_s\[10\] = .* a clock fault"):
        FolderSequence(written)


# ---------------------------------------------------------------------------------------------- refused when written


def test_writer_refuses_imu_samples_without_rig_imu(tmp_path):
    sequence = tiny_sequence()
    no_imu = InMemorySequence(sequence.rig.model_copy(update={"imu": None}), list(sequence.events()), np.eye(4), T0_S)
    with pytest.raises(DatasetError, match=r"imu\.npz: the rig has no imu section"):
        write_folder_dataset(no_imu, tmp_path / "ds")


def test_writer_refuses_wrong_sample_shape(tmp_path):
    sequence = tiny_sequence()
    events = [
        ImuSample(e.t_s, e.gyro_rad_s[:2], e.accel_mps2, e.index) if isinstance(e, ImuSample) and e.index == 3 else e
        for e in sequence.events()
    ]
    with pytest.raises(DatasetError, match=r"imu\.npz: gyro_rad_s\[3\] has shape \(2,\), expected \(3,\)"):
        write_folder_dataset(sequence.replace_events(events), tmp_path / "ds")
