"""The on-disk dataset folder format (``dem_graph-folder``, version 1).

A dataset is one folder::

    DIR/dataset.yaml                  metadata (below); written last, so a half-written folder does not open
    DIR/rig.yaml                      the sensor rig (dem_graph.geometry.rig.save_rig / load_rig)
    DIR/images/000000.png             camera frames in order, lossless 8-bit PNG, grey (H,W) or BGR (H,W,3)
    DIR/camera.csv                    header ``index,t_s,file`` (UTF-8, a byte-order mark allowed); one line per
                                      frame, at least one; ``file`` relative to DIR and inside it
    DIR/laser.npz                     t_s float64 (N,); ranges_m float32 (N,B), B = the rig's beam count
    DIR/odometry.npz                  t_s, t_prev_s float64 (N,); T_prev_curr float64 (N,4,4);
                                      covariance float64 (N,6,6). Absent when the sequence has no odometry
    DIR/imu.npz                       t_s float64 (N,); gyro_rad_s, accel_mps2 float64 (N,3), in the IMU's frame
                                      (rig.yaml's ``imu.T_body_imu``). Absent when the sequence has no IMU; when
                                      present, rig.yaml must have an ``imu`` section
    DIR/ground_truth/trajectory.tum   ground-truth T_world_body (TUM text), when ground truth exists
    DIR/ground_truth/elevation.tif    ground-truth terrain (GeoTIFF, band "elevation"), when known

``dataset.yaml`` holds ``format: dem_graph-folder``, ``version: 1``, ``name``, ``t_start_s``,
``T_world_body_initial`` (the body pose at ``t_start_s``, a 4x4 nested list, row-major),
``counts`` (``frames``, ``scans``, ``odometry`` and, only when there is an imu.npz, ``imu``; a
dataset without the key has no IMU sample), ``has_ground_truth`` and a free-form ``description``.

Conventions: times in seconds, ranges in metres, NaN range = no return. Poses are ``T_world_body``
(maps body coordinates to world coordinates). Odometry ``T_prev_curr`` is the body pose at ``t_s``
in the body frame at ``t_prev_s``; its covariance is in gtsam's tangent order [rotation,
translation] (rad^2, m^2). IMU samples hold the angular rate (rad/s) and the specific force
(m/s^2, reading +9.81 up at rest), every value finite. Within each stream times strictly increase; no event is before
``t_start_s``. Every float is written exactly (repr in text files, native dtype in npz), so a
dataset read and written again is identical. The ``index`` of each event is its position in its
stream. Events are replayed merged in time order; at equal times odometry comes first, then laser,
then camera, then IMU.

:class:`FolderSequence` reads and validates every small file when it is opened and reads images
lazily while :meth:`FolderSequence.events` iterates. :func:`write_folder_dataset` writes any
:class:`Sequence` in this format, streaming its images to disk.

Beyond the format, the reader holds a log to :class:`~dem_graph.datasets.checks.InputChecks`
(:mod:`dem_graph.datasets.checks`): on open it refuses a clock jump in camera.csv, laser.npz,
odometry.npz or imu.npz, an odometry covariance that is not one, and a first image of another size than the
rig's camera; it repairs all-zero (unknown) covariances, skips odometry increments beyond the
vehicle's motion and says when there is no laser scan or no valid return, each with one warning. While
iterating it refuses any image of the wrong size and marks frames without texture or repeating the one
before (a frozen camera).
"""

from __future__ import annotations

import csv
import io
import math
import os
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import yaml

from dem_graph.datasets.base import (
    CAMERA_STREAM,
    IMU_STREAM,
    LASER_STREAM,
    ODOMETRY_STREAM,
    GroundTruth,
    Sequence,
    first_not_increasing,
    merged_order,
    read_ahead,
)
from dem_graph.datasets.checks import (
    InputChecks,
    TextureWatch,
    check_covariances,
    check_image_size,
    check_time_jumps,
    image_std_dn,
    plausible_increments,
    repair_unknown_covariances,
    warn_if_no_laser,
)
from dem_graph.datasets.events import CameraFrame, Event, ImuSample, LaserScan, Odometry
from dem_graph.errors import ConfigError, DatasetError
from dem_graph.geometry.rig import CameraSpec, SensorRig, load_rig, save_rig
from dem_graph.geometry.se3 import check_pose
from dem_graph.io.geotiff import read_elevation, write_elevation
from dem_graph.io.npz import read_npz
from dem_graph.io.tum import read_tum, write_tum
from dem_graph.progress import progress

FORMAT_NAME = "dem_graph-folder"
FORMAT_VERSION = 1

DATASET_YAML = "dataset.yaml"
RIG_YAML = "rig.yaml"
CAMERA_CSV = "camera.csv"
LASER_NPZ = "laser.npz"
ODOMETRY_NPZ = "odometry.npz"
IMU_NPZ = "imu.npz"
IMAGES_DIR = "images"
GROUND_TRUTH_DIR = "ground_truth"
GT_TRAJECTORY = "ground_truth/trajectory.tum"
GT_ELEVATION = "ground_truth/elevation.tif"
CAMERA_HEADER = ["index", "t_s", "file"]

_POSE_TOL = 1e-6
_NO_IMU_SECTION = "the rig has no imu section; add one to rig.yaml with T_body_imu and the noise densities"


# ----------------------------------------------------------------------------------------------
# validation shared by the reader and the writer (the writer checks what it writes)


def _check_times(path: Path, name: str, t: np.ndarray, t_start_s: float) -> None:
    if not np.all(np.isfinite(t)):
        i = int(np.argmax(~np.isfinite(t)))
        raise DatasetError(path, f"{name}[{i}] is NaN or infinite")
    i = first_not_increasing(t)
    if i is not None:
        raise DatasetError(path, f"{name} is not strictly increasing at index {i} ({float(t[i])!r} after {float(t[i - 1])!r})")
    if len(t) and t[0] < t_start_s:
        raise DatasetError(path, f"{name}[0] = {float(t[0])!r} is before t_start_s = {t_start_s!r}")


def _check_float_array(path: Path, name: str, a: np.ndarray, shape: tuple) -> None:
    """Check the dtype class and shape of ``a``; a ``str`` in ``shape`` names a free dimension."""
    if not np.issubdtype(a.dtype, np.floating):
        raise DatasetError(path, f"{name} must be floating point, got dtype {a.dtype}")
    ok = a.ndim == len(shape) and all(isinstance(s, str) or s == n for s, n in zip(shape, a.shape))
    if not ok:
        expected = "(" + ", ".join(str(s) for s in shape) + ("," if len(shape) == 1 else "") + ")"
        raise DatasetError(path, f"{name} has shape {a.shape}, expected {expected}")


def _check_laser(path: Path, t_s: np.ndarray, ranges_m: np.ndarray, beam_count: int, t_start_s: float) -> None:
    _check_float_array(path, "t_s", t_s, ("N",))
    _check_float_array(path, "ranges_m", ranges_m, ("N", "B"))
    if ranges_m.shape[0] != len(t_s):
        raise DatasetError(path, f"ranges_m has {ranges_m.shape[0]} scans but t_s has {len(t_s)} times")
    if ranges_m.shape[1] != beam_count:
        raise DatasetError(path, f"ranges_m has {ranges_m.shape[1]} beams per scan, the rig's laser has {beam_count}")
    with np.errstate(invalid="ignore"):
        bad = np.isinf(ranges_m) | (ranges_m < 0)
    if np.any(bad):
        i, j = (int(k) for k in np.argwhere(bad)[0])
        raise DatasetError(path, f"scan {i} beam {j}: range {float(ranges_m[i, j])!r} is invalid (use NaN for no return)")
    _check_times(path, "t_s", t_s, t_start_s)


def _check_odometry(
    path: Path, t_s: np.ndarray, t_prev_s: np.ndarray, T_prev_curr: np.ndarray, covariance: np.ndarray, t_start_s: float
) -> None:
    _check_float_array(path, "t_s", t_s, ("N",))
    n = len(t_s)
    _check_float_array(path, "t_prev_s", t_prev_s, (n,))
    _check_float_array(path, "T_prev_curr", T_prev_curr, (n, 4, 4))
    _check_float_array(path, "covariance", covariance, (n, 6, 6))
    _check_times(path, "t_s", t_s, t_start_s)
    if not np.all(np.isfinite(t_prev_s)):
        raise DatasetError(path, f"t_prev_s[{int(np.argmax(~np.isfinite(t_prev_s)))}] is NaN or infinite")
    if np.any(t_prev_s > t_s):
        i = int(np.argmax(t_prev_s > t_s))
        raise DatasetError(path, f"odometry {i}: t_prev_s = {float(t_prev_s[i])!r} is after t_s = {float(t_s[i])!r}")
    finite = np.all(np.isfinite(T_prev_curr), axis=(1, 2))
    if not np.all(finite):
        raise DatasetError(path, f"T_prev_curr[{int(np.argmin(finite))}] contains NaN or infinite values")
    if n:
        R = T_prev_curr[:, :3, :3]
        last_row_ok = np.all(np.abs(T_prev_curr[:, 3, :] - [0.0, 0.0, 0.0, 1.0]) <= _POSE_TOL, axis=1)
        orthonormal = np.all(np.abs(np.swapaxes(R, 1, 2) @ R - np.eye(3)) <= _POSE_TOL, axis=(1, 2))
        rigid = last_row_ok & orthonormal & (np.linalg.det(R) > 0)
        if not np.all(rigid):
            raise DatasetError(path, f"T_prev_curr[{int(np.argmin(rigid))}] is not a rigid transform")
    check_covariances(path, covariance)  # all-zero ones (unknown) pass: the reader repairs them


def _check_imu(path: Path, t_s: np.ndarray, gyro_rad_s: np.ndarray, accel_mps2: np.ndarray, t_start_s: float) -> None:
    _check_float_array(path, "t_s", t_s, ("N",))
    n = len(t_s)
    _check_float_array(path, "gyro_rad_s", gyro_rad_s, (n, 3))
    _check_float_array(path, "accel_mps2", accel_mps2, (n, 3))
    _check_times(path, "t_s", t_s, t_start_s)
    for name, values in (("gyro_rad_s", gyro_rad_s), ("accel_mps2", accel_mps2)):
        finite = np.all(np.isfinite(values), axis=1)
        if not np.all(finite):
            i = int(np.argmin(finite))
            raise DatasetError(path, f"sample {i}: {name} {[float(x) for x in values[i]]} contains NaN or infinite values")


def _check_image(path: Path, image: np.ndarray) -> None:
    if image.dtype != np.uint8 or not (image.ndim == 2 or (image.ndim == 3 and image.shape[2] == 3)) or image.size == 0:
        raise DatasetError(path, f"expected an 8-bit grey (H,W) or BGR (H,W,3) image, got dtype {image.dtype} shape {image.shape}")


def _initial_pose(path: Path, T) -> np.ndarray:
    try:
        return check_pose(T, "T_world_body_initial")
    except ConfigError as exc:
        raise DatasetError(path, exc.problem) from None


# ----------------------------------------------------------------------------------------------
# reading


def _require_file(path: Path, what: str) -> None:
    if not path.is_file():
        raise DatasetError(path, f"{what} not found" if not path.exists() else f"{what} is not a regular file")


def _read_metadata(path: Path) -> dict:
    _require_file(path, "dataset description")
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8"))
    except yaml.YAMLError as exc:
        raise DatasetError(path, f"not valid YAML ({str(exc).splitlines()[0]})") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise DatasetError(path, f"cannot read ({exc})") from None
    if not isinstance(data, dict):
        raise DatasetError(path, "must hold a mapping (format, version, name, ...)")
    if data.get("format") != FORMAT_NAME:
        raise DatasetError(path, f"format is {data.get('format')!r}, expected {FORMAT_NAME!r}")
    if data.get("version") != FORMAT_VERSION or isinstance(data.get("version"), bool):
        raise DatasetError(path, f"unsupported format version {data.get('version')!r} (this reader supports {FORMAT_VERSION})")
    for key in ("name", "t_start_s", "T_world_body_initial", "counts", "has_ground_truth"):
        if key not in data:
            raise DatasetError(path, f"missing key {key!r}")
    if not isinstance(data["name"], str):
        raise DatasetError(path, "name must be a string")
    t0 = data["t_start_s"]
    if isinstance(t0, bool) or not isinstance(t0, (int, float)) or not math.isfinite(t0):
        raise DatasetError(path, f"t_start_s must be a finite number, got {t0!r}")
    counts = data["counts"]
    if not isinstance(counts, dict):
        raise DatasetError(path, "counts must be a mapping with frames, scans and odometry")
    for key in ("frames", "scans", "odometry"):
        n = counts.get(key)
        if isinstance(n, bool) or not isinstance(n, int) or n < 0:
            raise DatasetError(path, f"counts.{key} must be a non-negative integer, got {n!r}")
    n_imu = counts.get("imu", 0)  # optional: datasets written before the IMU stream have none
    if isinstance(n_imu, bool) or not isinstance(n_imu, int) or n_imu < 0:
        raise DatasetError(path, f"counts.imu must be a non-negative integer, got {n_imu!r}")
    if not isinstance(data["has_ground_truth"], bool):
        raise DatasetError(path, "has_ground_truth must be true or false")
    description = data.get("description", "")
    if description is None:
        description = ""
    if not isinstance(description, str):
        raise DatasetError(path, "description must be a string")
    return {
        "name": data["name"],
        "t_start_s": float(t0),
        "T_world_body_initial": _initial_pose(path, data["T_world_body_initial"]),
        "counts": {**{k: counts[k] for k in ("frames", "scans", "odometry")}, "imu": n_imu},
        "has_ground_truth": data["has_ground_truth"],
        "description": description,
    }


def _read_camera_csv(path: Path, root: Path, t_start_s: float) -> tuple[np.ndarray, list[Path], list[int]]:
    """Frame times, image paths and the line of each frame in ``camera.csv``."""
    _require_file(path, "camera index")
    try:
        text = path.read_text(encoding="utf-8-sig")  # a byte-order mark (Excel's UTF-8) is not part of the header
    except (OSError, UnicodeDecodeError) as exc:
        raise DatasetError(path, f"cannot read ({exc})") from None
    rows = [(n, row) for n, row in enumerate(csv.reader(io.StringIO(text)), start=1) if row]
    if not rows:
        raise DatasetError(path, f"empty: expected the header {','.join(CAMERA_HEADER)}")
    if [c.strip() for c in rows[0][1]] != CAMERA_HEADER:
        raise DatasetError(path, f"line {rows[0][0]}: header must be {','.join(CAMERA_HEADER)}, got {','.join(rows[0][1])}")
    times, files, lines = [], [], []
    for position, (line_no, row) in enumerate(rows[1:]):
        if len(row) != 3:
            raise DatasetError(path, f"line {line_no}: expected 3 columns (index,t_s,file), got {len(row)}")
        index_text, t_text, file_text = (c.strip() for c in row)
        try:
            index = int(index_text)
        except ValueError:
            raise DatasetError(path, f"line {line_no}: index is not an integer: {index_text!r}") from None
        if index != position:
            raise DatasetError(path, f"line {line_no}: index {index} out of order, expected {position}")
        try:
            t = float(t_text)
        except ValueError:
            raise DatasetError(path, f"line {line_no}: t_s is not a number: {t_text!r}") from None
        if not file_text:
            raise DatasetError(path, f"line {line_no}: empty file name")
        if _outside(root, file_text):
            raise DatasetError(
                path, f"line {line_no}: file {file_text!r} lies outside the dataset folder: give a path inside it, relative to it"
            )
        image_path = root / file_text
        if not image_path.is_file():
            raise DatasetError(image_path, f"image listed in {CAMERA_CSV} (line {line_no}) not found")
        if not math.isfinite(t):
            raise DatasetError(path, f"line {line_no}: t_s is NaN or infinite")
        if times and not t > times[-1]:
            raise DatasetError(
                path,
                f"line {line_no}: frame {position} time {t!r} is not after the previous {times[-1]!r} (times must be strictly increasing)",
            )
        times.append(t)
        files.append(image_path)
        lines.append(line_no)
    if not times:
        raise DatasetError(path, "holds no camera frame (only the header): a run needs at least one")
    t_s = np.array(times, dtype=np.float64)
    _check_times(path, "t_s", t_s, t_start_s)
    return t_s, files, lines


def _outside(root: Path, file_text: str) -> bool:
    """Whether an image path of camera.csv (absolute, or relative to ``root``) leads out of ``root``,
    told from the names (a symbolic link inside the folder may lead elsewhere: it is the user's)."""
    top = os.path.abspath(root)
    return os.path.relpath(os.path.normpath(os.path.join(top, file_text)), top).split(os.sep)[0] == os.pardir


def _decode_quietly(data: np.ndarray) -> np.ndarray | None:
    """``cv2.imdecode`` without OpenCV logging its own complaints about a broken file to stderr."""
    level = cv2.utils.logging.getLogLevel()
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)
    try:
        return cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    finally:
        cv2.utils.logging.setLogLevel(level)


def _read_image(path: Path) -> np.ndarray:
    try:
        data = np.fromfile(path, dtype=np.uint8)
    except OSError as exc:
        raise DatasetError(path, f"cannot read image ({exc.strerror or exc})") from None
    image = _decode_quietly(data) if data.size else None
    if image is None:
        raise DatasetError(path, "unreadable or corrupt PNG image")
    _check_image(path, image)
    return image


def _read_frame(path: Path, camera: CameraSpec) -> tuple[np.ndarray, float]:
    """The image at ``path``, checked against the rig's camera, and its grey levels' deviation (DN)."""
    image = _read_image(path)
    check_image_size(path, image, camera)
    return image, image_std_dn(image)


class FolderSequence(Sequence):
    """A dataset folder (see the module docstring), validated on open; images are read lazily.

    ``checks``: the limits the log is held to (:class:`~dem_graph.datasets.checks.InputChecks`; None: the defaults).
    """

    def __init__(self, path: str | Path, checks: InputChecks | None = None):
        self.input_checks = checks if checks is not None else InputChecks()
        root = Path(path)
        if not root.is_dir():
            raise DatasetError(root, "dataset folder not found" if not root.exists() else "not a folder")
        self.path = root
        meta = _read_metadata(root / DATASET_YAML)
        self.name = meta["name"]
        self.description: str = meta["description"]
        self._t_start_s: float = meta["t_start_s"]
        self._T_world_body_initial: np.ndarray = meta["T_world_body_initial"]
        counts = meta["counts"]

        rig_path = root / RIG_YAML
        _require_file(rig_path, "rig file")
        self._rig: SensorRig = load_rig(rig_path)  # its ConfigError names the file
        beam_count = self._rig.laser.beams.count

        camera_path = root / CAMERA_CSV
        self._frame_t_s, self._frame_files, lines = _read_camera_csv(camera_path, root, self._t_start_s)
        check_time_jumps(camera_path, self._frame_t_s, self._t_start_s, self.input_checks, lambda i: f"line {lines[i]}: frame {i} t_s")

        laser_path = root / LASER_NPZ
        _require_file(laser_path, "laser scans")
        laser = read_npz(laser_path, ("t_s", "ranges_m"))
        _check_laser(laser_path, laser["t_s"], laser["ranges_m"], beam_count, self._t_start_s)
        self._scan_t_s = laser["t_s"].astype(np.float64)
        self._scan_ranges_m = laser["ranges_m"].astype(np.float32)
        check_time_jumps(laser_path, self._scan_t_s, self._t_start_s, self.input_checks, lambda i: f"t_s[{i}]")

        odometry_path = root / ODOMETRY_NPZ
        self._has_odometry = odometry_path.exists()
        if self._has_odometry:
            _require_file(odometry_path, "odometry")
            odo = read_npz(odometry_path, ("t_s", "t_prev_s", "T_prev_curr", "covariance"))
            _check_odometry(odometry_path, odo["t_s"], odo["t_prev_s"], odo["T_prev_curr"], odo["covariance"], self._t_start_s)
            self._odo = {k: v.astype(np.float64) for k, v in odo.items()}
            check_time_jumps(odometry_path, self._odo["t_s"], self._t_start_s, self.input_checks, lambda i: f"t_s[{i}]")
            self._odo["covariance"] = repair_unknown_covariances(
                odometry_path, self._odo["covariance"], self._odo["T_prev_curr"], self._rig.odometry
            )
        else:
            if counts["odometry"]:
                raise DatasetError(odometry_path, f"not found, but {DATASET_YAML} counts {counts['odometry']} odometry events")
            self._odo = {
                "t_s": np.zeros(0),
                "t_prev_s": np.zeros(0),
                "T_prev_curr": np.zeros((0, 4, 4)),
                "covariance": np.zeros((0, 6, 6)),
            }

        imu_path = root / IMU_NPZ
        self._has_imu = imu_path.exists()
        if self._has_imu:
            _require_file(imu_path, "IMU samples")
            if self._rig.imu is None:
                raise DatasetError(imu_path, _NO_IMU_SECTION)
            imu = read_npz(imu_path, ("t_s", "gyro_rad_s", "accel_mps2"))
            _check_imu(imu_path, imu["t_s"], imu["gyro_rad_s"], imu["accel_mps2"], self._t_start_s)
            self._imu = {k: v.astype(np.float64) for k, v in imu.items()}
            check_time_jumps(imu_path, self._imu["t_s"], self._t_start_s, self.input_checks, lambda i: f"t_s[{i}]")
        else:
            if counts["imu"]:
                raise DatasetError(imu_path, f"not found, but {DATASET_YAML} counts {counts['imu']} imu samples")
            self._imu = {"t_s": np.zeros(0), "gyro_rad_s": np.zeros((0, 3)), "accel_mps2": np.zeros((0, 3))}

        for key, n, source in (
            ("frames", len(self._frame_t_s), camera_path),
            ("scans", len(self._scan_t_s), laser_path),
            ("odometry", len(self._odo["t_s"]), odometry_path),
        ):
            if counts[key] != n:
                raise DatasetError(source, f"holds {n} {key} but {DATASET_YAML} counts {counts[key]}")
        if counts["imu"] != self.n_imu:
            raise DatasetError(imu_path, f"holds {self.n_imu} imu samples but {DATASET_YAML} counts {counts['imu']}")

        self._ground_truth: GroundTruth | None = None
        if meta["has_ground_truth"]:
            trajectory = read_tum(root / GT_TRAJECTORY)
            elevation_path = root / GT_ELEVATION
            elevation = read_elevation(elevation_path) if elevation_path.exists() else None
            self._ground_truth = GroundTruth(trajectory, elevation)

        if self._frame_files:  # the first image, now: a rig that is not this camera's is refused before the run
            _read_frame(self._frame_files[0], self._rig.camera)
        warn_if_no_laser(laser_path, self._scan_ranges_m, self._rig.laser)
        dt_s = self._odo["t_s"] - self._odo["t_prev_s"]
        self._odometry_kept = np.flatnonzero(plausible_increments(odometry_path, self._odo["T_prev_curr"], dt_s, self.input_checks))
        self._order = [
            (kind, int(self._odometry_kept[i]) if kind == ODOMETRY_STREAM else i)
            for kind, i in merged_order(self._odo["t_s"][self._odometry_kept], self._scan_t_s, self._frame_t_s, self._imu["t_s"])
        ]

    @property
    def rig(self) -> SensorRig:
        return self._rig

    @property
    def t_start_s(self) -> float:
        return self._t_start_s

    @property
    def T_world_body_initial(self) -> np.ndarray:
        return self._T_world_body_initial.copy()

    @property
    def ground_truth(self) -> GroundTruth | None:
        return self._ground_truth

    @property
    def has_odometry(self) -> bool:
        return self._has_odometry

    @property
    def has_imu(self) -> bool:
        return self._has_imu

    @property
    def n_frames(self) -> int:
        return len(self._frame_t_s)

    def camera_times(self) -> np.ndarray:
        """Every frame's time (n,), seconds, from camera.csv."""
        return self._frame_t_s.copy()

    @property
    def n_scans(self) -> int:
        return len(self._scan_t_s)

    @property
    def n_odometry(self) -> int:
        return len(self._odo["t_s"])

    @property
    def n_imu(self) -> int:
        return len(self._imu["t_s"])

    def event_count(self) -> int:
        return len(self._order)

    def laser_scans(self) -> tuple[np.ndarray, np.ndarray]:
        return self._scan_t_s.copy(), self._scan_ranges_m.astype(float)

    def events(self) -> Iterator[Event]:
        """Every event in time order (odometry, then laser, camera and IMU at equal times); images read lazily.

        Odometry increments beyond the vehicle's motion are left out; frames without texture, or
        bit-identical to the frame before (a frozen camera), are marked ``textureless``. Raises :class:`DatasetError` naming the image when a PNG is missing, cannot be
        decoded or is not the rig's size.
        """
        odo, imu = self._odo, self._imu
        camera = self._rig.camera
        images = read_ahead(_read_frame(path, camera) for path in self._frame_files)  # camera frames come in index order
        texture = TextureWatch(self.path / IMAGES_DIR, self.input_checks)
        for kind, i in self._order:
            if kind == ODOMETRY_STREAM:
                yield Odometry(
                    float(odo["t_s"][i]),
                    float(odo["t_prev_s"][i]),
                    odo["T_prev_curr"][i].copy(),
                    odo["covariance"][i].copy(),
                    i,
                )
            elif kind == LASER_STREAM:
                yield LaserScan(float(self._scan_t_s[i]), self._scan_ranges_m[i].copy(), i)
            elif kind == CAMERA_STREAM:
                image, std_dn = next(images)
                yield texture.frame(CameraFrame(float(self._frame_t_s[i]), image, i), std_dn, self._frame_files[i])
            elif kind == IMU_STREAM:
                yield ImuSample(float(imu["t_s"][i]), imu["gyro_rad_s"][i].copy(), imu["accel_mps2"][i].copy(), i)

    def __repr__(self) -> str:
        return (
            f"FolderSequence({str(self.path)!r}, name={self.name!r}, frames={self.n_frames}, "
            f"scans={self.n_scans}, odometry={self.n_odometry}, imu={self.n_imu})"
        )


def open_folder_dataset(path: str | Path) -> FolderSequence:
    """Open and validate a dataset folder; same as ``FolderSequence(path)``."""
    return FolderSequence(path)


# ----------------------------------------------------------------------------------------------
# writing


def with_rig(dataset: str | Path, out: str | Path, rig: SensorRig) -> Path:
    """A dataset folder ``out`` that is ``dataset`` with ``rig`` in its rig.yaml, its other files
    linked (studies of a rig measured wrong: :func:`~dem_graph.geometry.rig.camera_remounted`)."""
    dataset, out = Path(dataset), Path(out)
    out.mkdir(parents=True)
    for p in dataset.iterdir():
        if p.name != "rig.yaml":
            (out / p.name).symlink_to(p.resolve())
    save_rig(rig, out / "rig.yaml")
    return out


def _float_list(T: np.ndarray) -> list:
    return [[float(x) for x in row] for row in np.asarray(T, dtype=float)]


def write_folder_dataset(
    sequence: Sequence,
    out_dir: str | Path,
    progress_desc: str = "writing dataset",
    description: str | None = None,
) -> Path:
    """Write ``sequence`` as a dataset folder at ``out_dir`` and return its path.

    ``sequence.events()`` is consumed once; images are written as they arrive, never held together.
    ``out_dir`` must not exist or be empty. ``description`` defaults to the sequence's
    ``description`` attribute, if it has one. Ranges are stored as float32 and the ground-truth
    elevation as float32, so those round-trip exactly only if they already are float32. IMU samples
    go to ``imu.npz`` when the sequence has an IMU (``has_imu``) or yields IMU samples, which needs a
    rig with an ``imu`` section.
    ``dataset.yaml`` is written last. Raises :class:`DatasetError` naming the file concerned if the
    sequence breaks the format (for example times that do not increase within a stream, or scans
    with the wrong number of beams).
    """
    out = Path(out_dir)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise DatasetError(out, "output folder exists and is not empty")
    if description is None:
        description = getattr(sequence, "description", "") or ""
    if not isinstance(description, str):
        raise DatasetError(out / DATASET_YAML, "description must be a string")

    rig = sequence.rig
    t_start_s = float(sequence.t_start_s)
    if not math.isfinite(t_start_s):
        raise DatasetError(out / DATASET_YAML, f"t_start_s must be finite, got {t_start_s!r}")
    T_world_body_initial = _initial_pose(out / DATASET_YAML, sequence.T_world_body_initial)
    beam_count = rig.laser.beams.count

    images_dir = out / IMAGES_DIR
    try:
        images_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise DatasetError(images_dir, f"cannot create folder ({exc.strerror or exc})") from None
    _write(out / RIG_YAML, lambda p: save_rig(rig, p))

    frame_t, frame_files = [], []
    scan_t, scan_ranges = [], []
    odo_t, odo_t_prev, odo_T, odo_cov = [], [], [], []
    imu_t, imu_gyro, imu_accel = [], [], []
    camera_path, laser_path, odometry_path, imu_path = out / CAMERA_CSV, out / LASER_NPZ, out / ODOMETRY_NPZ, out / IMU_NPZ
    image_writer = _BackgroundPngWriter()
    try:
        for event in progress(sequence.events(), total=sequence.event_count(), desc=progress_desc, unit="event"):
            if isinstance(event, CameraFrame):
                index = len(frame_t)
                t = float(event.t_s)
                if not math.isfinite(t):
                    raise DatasetError(camera_path, f"frame {index}: time is NaN or infinite")
                if frame_t and not t > frame_t[-1]:
                    raise DatasetError(camera_path, f"frame {index}: time {t!r} is not after the previous {frame_t[-1]!r}")
                if t < t_start_s:
                    raise DatasetError(camera_path, f"frame {index}: time {t!r} is before t_start_s = {t_start_s!r}")
                name = f"{IMAGES_DIR}/{index:06d}.png"
                image = np.ascontiguousarray(event.image)
                _check_image(out / name, image)
                check_image_size(out / name, image, rig.camera)
                image_writer.submit(out / name, image)
                frame_t.append(t)
                frame_files.append(name)
            elif isinstance(event, LaserScan):
                ranges = np.asarray(event.ranges_m)
                if ranges.shape != (beam_count,):
                    raise DatasetError(laser_path, f"scan {len(scan_t)}: {ranges.shape} ranges, the rig's laser has {beam_count} beams")
                scan_t.append(float(event.t_s))
                scan_ranges.append(ranges.astype(np.float32))
            elif isinstance(event, Odometry):
                odo_t.append(float(event.t_s))
                odo_t_prev.append(float(event.t_prev_s))
                odo_T.append(np.asarray(event.T_prev_curr, dtype=np.float64))
                odo_cov.append(np.asarray(event.covariance, dtype=np.float64))
            elif isinstance(event, ImuSample):
                if rig.imu is None:
                    raise DatasetError(imu_path, _NO_IMU_SECTION)
                imu_t.append(float(event.t_s))
                imu_gyro.append(np.asarray(event.gyro_rad_s, dtype=np.float64))
                imu_accel.append(np.asarray(event.accel_mps2, dtype=np.float64))
            else:
                raise DatasetError(out, f"unknown event type {type(event).__name__}")
    finally:
        image_writer.close()

    # camera.csv
    lines = [",".join(CAMERA_HEADER)]
    lines.extend(f"{i},{t!r},{name}" for i, (t, name) in enumerate(zip(frame_t, frame_files)))
    _write(camera_path, lambda p: p.write_text("\n".join(lines) + "\n", encoding="utf-8"))

    # laser.npz
    laser_t = np.array(scan_t, dtype=np.float64)
    laser_ranges = np.stack(scan_ranges) if scan_ranges else np.zeros((0, beam_count), dtype=np.float32)
    _check_laser(laser_path, laser_t, laser_ranges, beam_count, t_start_s)
    _write(laser_path, lambda p: np.savez(p, t_s=laser_t, ranges_m=laser_ranges))

    # odometry.npz
    if sequence.has_odometry or odo_t:
        odometry = {
            "t_s": np.array(odo_t, dtype=np.float64),
            "t_prev_s": np.array(odo_t_prev, dtype=np.float64),
            "T_prev_curr": _stack_checked(odometry_path, "T_prev_curr", odo_T, (4, 4)),
            "covariance": _stack_checked(odometry_path, "covariance", odo_cov, (6, 6)),
        }
        _check_odometry(odometry_path, **odometry, t_start_s=t_start_s)
        _write(odometry_path, lambda p: np.savez(p, **odometry))

    # imu.npz
    write_imu = sequence.has_imu or bool(imu_t)
    if write_imu:
        if rig.imu is None:
            raise DatasetError(imu_path, _NO_IMU_SECTION)
        imu = {
            "t_s": np.array(imu_t, dtype=np.float64),
            "gyro_rad_s": _stack_checked(imu_path, "gyro_rad_s", imu_gyro, (3,)),
            "accel_mps2": _stack_checked(imu_path, "accel_mps2", imu_accel, (3,)),
        }
        _check_imu(imu_path, **imu, t_start_s=t_start_s)
        _write(imu_path, lambda p: np.savez(p, **imu))

    # ground truth
    ground_truth = sequence.ground_truth
    if ground_truth is not None:
        _write(out / GROUND_TRUTH_DIR, lambda p: p.mkdir(exist_ok=True))
        write_tum(out / GT_TRAJECTORY, ground_truth.trajectory)
        if ground_truth.elevation is not None:
            write_elevation(out / GT_ELEVATION, ground_truth.elevation)

    metadata = {
        "format": FORMAT_NAME,
        "version": FORMAT_VERSION,
        "name": str(sequence.name),
        "t_start_s": t_start_s,
        "T_world_body_initial": _float_list(T_world_body_initial),
        "counts": {"frames": len(frame_t), "scans": len(scan_t), "odometry": len(odo_t), **({"imu": len(imu_t)} if write_imu else {})},
        "has_ground_truth": ground_truth is not None,
        "description": description,
    }
    text = yaml.safe_dump(metadata, sort_keys=False, default_flow_style=None, allow_unicode=True)
    _write(out / DATASET_YAML, lambda p: p.write_text(text, encoding="utf-8"))
    return out


def _stack_checked(path: Path, name: str, items: list[np.ndarray], shape: tuple[int, ...]) -> np.ndarray:
    for i, a in enumerate(items):
        if a.shape != shape:
            raise DatasetError(path, f"{name}[{i}] has shape {a.shape}, expected {shape}")
    return np.stack(items) if items else np.zeros((0,) + shape)


class _BackgroundPngWriter:
    """Encodes and writes PNG images on a worker thread (OpenCV releases the GIL), a few frames behind."""

    def __init__(self, max_pending: int = 8, compression: int = 1):
        from concurrent.futures import ThreadPoolExecutor

        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="png-writer")
        self._pending: list = []
        self._max_pending = max_pending
        self._params = [cv2.IMWRITE_PNG_COMPRESSION, compression]

    def submit(self, path: Path, image: np.ndarray) -> None:
        self._pending.append((path, self._pool.submit(cv2.imwrite, str(path), image, self._params)))
        while len(self._pending) > self._max_pending:
            self._check(*self._pending.pop(0))

    @staticmethod
    def _check(path: Path, future) -> None:
        try:
            ok = future.result()
        except cv2.error as exc:
            raise DatasetError(path, f"cannot write PNG image ({str(exc).strip().splitlines()[-1]})") from None
        if not ok:
            raise DatasetError(path, "cannot write PNG image")

    def close(self) -> None:
        try:
            while self._pending:
                self._check(*self._pending.pop(0))
        finally:
            self._pool.shutdown(wait=True)


def _write(path: Path, write) -> None:
    """Run ``write(path)``, turning an OS error into a :class:`DatasetError` naming ``path``."""
    try:
        write(path)
    except OSError as exc:
        raise DatasetError(path, f"cannot write ({exc.strerror or exc})") from None
