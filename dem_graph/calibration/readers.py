"""Readers and writers for calibration recordings, and the pairing of images with scans by time.

A recording (:class:`CalibrationRecording`) lists its images by name and time and reads each on demand, so
the calibration does not care where the images live. Two layouts are read: ROS 1 and ROS 2 bags
(:func:`~dem_graph.calibration.rosbag_reader.read_rosbag_recording`) and, here, RADLOCC's text layout as
in ``../shared/data/hokuyo_checkerboard``::

    RECORDING/data/RGB1.png, RGB2.png, ...   camera images, numbered from 1
    RECORDING/data/camera.txt                 one time stamp (seconds) per image, in image order
    RECORDING/data/laser.txt                  one scan per line (see :func:`read_radlocc_scans`)
    RECORDING/xml/out_camera_data.xml         OpenCV's camera calibration output (intrinsics, board)

Every reader raises :class:`DatasetError` naming the file (and the line) on a malformed input.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from dem_graph.calibration.board import BoardSpec
from dem_graph.errors import DatasetError

log = logging.getLogger(__name__)

_HEADER = "time angle_min angle_increment angle_max field n_beams ranges..."


@dataclass(frozen=True)
class ScanSet:
    """Planar scans sharing one beam layout. Beam ``k`` points at ``angle_min_rad + k * angle_increment_rad``
    from the laser's +x towards +y (the project's :class:`~dem_graph.geometry.rig.PlanarBeams`)."""

    times_s: np.ndarray  # (S,)
    angle_min_rad: float
    angle_increment_rad: float
    ranges_m: np.ndarray  # (S, B); NaN where there is no return
    field: int = 3  # RADLOCC's range-unit field, kept for writing back

    @property
    def n_beams(self) -> int:
        return int(self.ranges_m.shape[1])

    @property
    def angles_rad(self) -> np.ndarray:
        return self.angle_min_rad + self.angle_increment_rad * np.arange(self.n_beams)


@dataclass(frozen=True)
class Intrinsics:
    """A camera's intrinsics as OpenCV writes them: ``K``, five distortion coefficients, image size."""

    K: np.ndarray  # 3x3
    distortion: np.ndarray  # (5,) k1, k2, p1, p2, k3
    width_px: int
    height_px: int


ImageReader = Callable[[Any, bool], np.ndarray]  # (image key, colour) -> 8-bit image, grey (H,W) or BGR (H,W,3)


@dataclass(frozen=True)
class CalibrationRecording:
    """What a calibration needs from a recording: images with their times, scans, intrinsics, the board.

    Images are read when asked for (:meth:`load_image`): ``read_image`` takes image ``k``'s entry of
    ``image_keys`` (a file path, a message's place in a bag) and raises :class:`DatasetError` naming the
    file or topic when the image cannot be read."""

    image_names: list[str]  # how reports and logs name each image
    image_times_s: np.ndarray
    scans: ScanSet
    intrinsics: Intrinsics
    board: BoardSpec | None  # None when the recording does not say
    image_keys: list  # per image, what read_image takes
    read_image: ImageReader

    def load_image(self, k: int, color: bool = False) -> np.ndarray:
        """Image ``k`` as 8-bit grey (H,W) or, with ``color``, BGR (H,W,3)."""
        import cv2

        image = self.read_image(self.image_keys[k], color)
        if color and image.ndim == 2:
            return cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
        if not color and image.ndim == 3:
            return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        return image

    def select(self, indices) -> CalibrationRecording:
        """The recording with only the images ``indices`` (in that order); scans and intrinsics kept."""
        idx = [int(i) for i in np.arange(len(self.image_names))[np.asarray(indices, dtype=int)]]
        return replace(
            self, image_names=[self.image_names[i] for i in idx], image_times_s=self.image_times_s[idx], image_keys=[self.image_keys[i] for i in idx]
        )


# ------------------------------------------------------------------ RADLOCC scans


def _parse_float(token: str) -> float:
    value = float(token)
    return value if math.isfinite(value) else math.nan


def read_radlocc_scans(path: str | Path) -> ScanSet:
    """Read RADLOCC text scans: per line ``time angle_min angle_increment angle_max field n_beams``, then
    ``n_beams`` ranges in metres separated by commas and/or spaces; ``inf`` or ``nan`` is no return.

    Every scan must share the first one's beam layout and times must increase. A block of lines without a
    header after the last scan (the hokuyo_checkerboard recording has one) is skipped with a warning.
    """
    path = Path(path)
    try:
        lines = path.read_text().splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise DatasetError(path, f"cannot read the scans ({exc})") from None
    times, ranges, layout, trailing = [], [], None, []
    for number, line in enumerate(lines, start=1):
        if not line.strip():
            continue
        if "," in line.split()[0]:  # ranges without a header
            trailing.append(number)
            continue
        if trailing:
            raise DatasetError(path, f"line {trailing[0]}: no scan header ({_HEADER})")
        tokens = line.replace(",", " ").split()
        try:
            t_s, a_min, a_inc, a_max = (float(x) for x in tokens[:4])
            field, n = int(tokens[4]), int(tokens[5])
            values = [_parse_float(x) for x in tokens[6:]]
        except (ValueError, IndexError):
            raise DatasetError(path, f"line {number}: not a scan ({_HEADER})") from None
        if len(values) != n:
            raise DatasetError(path, f"line {number}: the header says {n} beams, the line has {len(values)} ranges")
        if not (math.isfinite(t_s) and math.isfinite(a_min) and math.isfinite(a_inc)) or a_inc <= 0 or n < 2:
            raise DatasetError(path, f"line {number}: invalid header (time {t_s}, angle_min {a_min}, angle_increment {a_inc}, {n} beams)")
        if layout is None:
            layout = (a_min, a_inc, n, field)
        elif (a_min, a_inc, n) != layout[:3]:
            raise DatasetError(path, f"line {number}: beam layout differs from the first scan's")
        if times and t_s <= times[-1]:
            raise DatasetError(path, f"line {number}: time {t_s} does not increase (previous {times[-1]})")
        times.append(t_s)
        ranges.append(values)
    if layout is None:
        raise DatasetError(path, "no scans")
    if trailing:
        log.warning("%s: skipped %d lines without a scan header after the last scan (lines %d-%d)", path, len(trailing), trailing[0], trailing[-1])
    return ScanSet(np.asarray(times), layout[0], layout[1], np.asarray(ranges, dtype=float), layout[3])


def write_radlocc_scans(scans: ScanSet, path: str | Path) -> None:
    """Write ``scans`` in the layout :func:`read_radlocc_scans` reads (numbers written exactly, no return as ``inf``)."""
    a_max = scans.angle_min_rad + scans.angle_increment_rad * (scans.n_beams - 1)
    head = f"{{!r}} {scans.angle_min_rad!r} {scans.angle_increment_rad!r} {a_max!r} {scans.field} {scans.n_beams} "
    out = []
    for t_s, row in zip(scans.times_s, scans.ranges_m):
        values = ", ".join("inf" if not math.isfinite(r) else repr(float(r)) for r in row)
        out.append(head.format(float(t_s)) + values)
    _write(path, "\n".join(out) + "\n")


# ------------------------------------------------------------------ image times


def read_times(path: str | Path) -> np.ndarray:
    """One time stamp (seconds) per line, increasing."""
    path = Path(path)
    try:
        lines = path.read_text().splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise DatasetError(path, f"cannot read the time stamps ({exc})") from None
    times = []
    for number, line in enumerate(lines, start=1):
        if not line.strip():
            continue
        try:
            t_s = float(line.split()[0])
        except ValueError:
            raise DatasetError(path, f"line {number}: not a time stamp: {line.strip()[:40]!r}") from None
        if not math.isfinite(t_s) or (times and t_s <= times[-1]):
            raise DatasetError(path, f"line {number}: time {t_s} does not increase")
        times.append(t_s)
    if not times:
        raise DatasetError(path, "no time stamps")
    return np.asarray(times)


def write_times(times_s: np.ndarray, path: str | Path) -> None:
    _write(path, "".join(f"{float(t)!r}\n" for t in times_s))


# ------------------------------------------------------------------ OpenCV intrinsics


def read_opencv_intrinsics(path: str | Path) -> tuple[Intrinsics, BoardSpec | None]:
    """Intrinsics (``Camera_Matrix``, ``Distortion_Coefficients``, ``image_Width``, ``image_Height``) and, when
    present, the board (``board_Width`` x ``board_Height`` inner corners, ``square_Size`` metres) from the file
    OpenCV's calibration sample writes (XML or YAML)."""
    import cv2

    path = Path(path)
    if not path.is_file():
        raise DatasetError(path, "intrinsics file not found")
    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except cv2.error as exc:
        raise DatasetError(path, f"not an OpenCV storage file ({' '.join(str(exc).split())[:120]})") from None
    try:
        K = fs.getNode("Camera_Matrix").mat()
        dist = fs.getNode("Distortion_Coefficients").mat()
        width, height = fs.getNode("image_Width").real(), fs.getNode("image_Height").real()
        cols, rows, square = fs.getNode("board_Width").real(), fs.getNode("board_Height").real(), fs.getNode("square_Size").real()
    finally:
        fs.release()
    if K is None or K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise DatasetError(path, "Camera_Matrix missing or not a valid 3x3 camera matrix")
    if width <= 0 or height <= 0:
        raise DatasetError(path, "image_Width and image_Height missing")
    coeffs = np.zeros(5) if dist is None else np.asarray(dist, dtype=float).ravel()
    if len(coeffs) > 5 and np.any(coeffs[5:] != 0):
        raise DatasetError(path, f"{len(coeffs)} distortion coefficients: only k1, k2, p1, p2, k3 are supported")
    coeffs = np.pad(coeffs[:5], (0, 5 - len(coeffs[:5])))
    board = BoardSpec(int(cols), int(rows), float(square)) if cols >= 2 and rows >= 2 and square > 0 else None
    return Intrinsics(np.asarray(K, dtype=float), coeffs, int(width), int(height)), board


def write_opencv_intrinsics(intrinsics: Intrinsics, board: BoardSpec | None, path: str | Path) -> None:
    """Write what :func:`read_opencv_intrinsics` reads, with OpenCV's node names."""
    import cv2

    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    if not fs.isOpened():
        raise DatasetError(path, "cannot write")
    fs.write("image_Width", int(intrinsics.width_px))
    fs.write("image_Height", int(intrinsics.height_px))
    if board is not None:
        fs.write("board_Width", int(board.cols))
        fs.write("board_Height", int(board.rows))
        fs.write("square_Size", float(board.square_m))
    fs.write("Camera_Matrix", np.asarray(intrinsics.K, dtype=float))
    fs.write("Distortion_Coefficients", np.asarray(intrinsics.distortion, dtype=float).reshape(5, 1))
    fs.release()


# ------------------------------------------------------------------ the RADLOCC recording folder


def read_radlocc_recording(folder: str | Path) -> CalibrationRecording:
    """Read a recording in the RADLOCC layout (see the module's docstring). Images are only listed here."""
    folder = Path(folder)
    if not folder.is_dir():
        raise DatasetError(folder, "recording folder not found")
    data = folder / "data"
    times = read_times(data / "camera.txt")
    scans = read_radlocc_scans(data / "laser.txt")
    intrinsics, board = read_opencv_intrinsics(folder / "xml" / "out_camera_data.xml")
    paths = [data / f"RGB{k}.png" for k in range(1, len(times) + 1)]
    missing = [p.name for p in paths if not p.is_file()]
    if missing:
        raise DatasetError(data, f"{len(missing)} of {len(paths)} images listed in camera.txt are missing (first: {missing[0]})")
    return CalibrationRecording([p.name for p in paths], times, scans, intrinsics, board, paths, read_image_file)


def read_image_file(path: str | Path, color: bool = False) -> np.ndarray:
    """An image file as 8-bit grey or, with ``color``, BGR; :class:`DatasetError` when OpenCV cannot read it."""
    import cv2

    image = cv2.imread(str(path), cv2.IMREAD_COLOR if color else cv2.IMREAD_GRAYSCALE)
    if image is None:
        raise DatasetError(path, "not a readable image")
    return image


# ------------------------------------------------------------------ pairing by time


def pair_nearest(image_times_s: np.ndarray, scan_times_s: np.ndarray, max_dt_s: float) -> np.ndarray:
    """For each image, the index of the scan nearest in time, or -1 when none lies within ``max_dt_s``.
    ``scan_times_s`` must increase."""
    image_times_s, scan_times_s = np.asarray(image_times_s, dtype=float), np.asarray(scan_times_s, dtype=float)
    right = np.clip(np.searchsorted(scan_times_s, image_times_s), 1, len(scan_times_s) - 1) if len(scan_times_s) > 1 else np.zeros(len(image_times_s), int)
    left = np.maximum(right - 1, 0)
    pick = np.where(np.abs(scan_times_s[left] - image_times_s) <= np.abs(scan_times_s[right] - image_times_s), left, right)
    return np.where(np.abs(scan_times_s[pick] - image_times_s) <= max_dt_s, pick, -1)


def _write(path: str | Path, text: str) -> None:
    try:
        Path(path).write_text(text)
    except OSError as exc:
        raise DatasetError(path, f"cannot write ({exc.strerror or exc})") from None
