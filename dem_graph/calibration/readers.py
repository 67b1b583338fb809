"""Readers and writers for calibration recordings, and the pairing of images with scans by time.

A recording (:class:`CalibrationRecording`) lists its images by name and time and reads each on demand, so
the calibration does not care where the images live. Two layouts are read: ROS 1 and ROS 2 bags
(:func:`~dem_graph.calibration.rosbag_reader.read_rosbag_recording`) and, here, RADLOCC's text layout as
in ``../shared/data/hokuyo_checkerboard``::

    RECORDING/data/RGB1.png, RGB2.png, ...   camera images, numbered from 1 (.png, .jpg or .jpeg)
    RECORDING/data/camera.txt                 one time stamp (seconds) per image, in image order
    RECORDING/data/laser.txt                  one scan per line (see :func:`read_radlocc_scans`)
    RECORDING/xml/out_camera_data.xml         OpenCV's camera calibration output (intrinsics, board)

and what other people's recordings of that layout hold instead (see :func:`read_radlocc_recording`):
``camera.txt`` lines ``TIME NAME`` or ``NAME TIME`` naming each image (a path below ``data/``), and
``Calib_Results.mat`` from the Camera Calibration Toolbox for MATLAB in place of the XML file.

Every reader raises :class:`DatasetError` naming the file (and the line) on a malformed input.
"""

from __future__ import annotations

import logging
import math
import re
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from dem_graph.calibration.board import BoardSpec
from dem_graph.errors import DatasetError, one_line

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
    image_numbers: list[int] | None = None  # per image, the number the input gives it (RGB<k>: k); None: 1..n

    def __post_init__(self):
        if self.image_numbers is not None and len(self.image_numbers) != len(self.image_names):
            raise ValueError(f"{len(self.image_numbers)} image numbers for {len(self.image_names)} images")

    @property
    def view_numbers(self) -> list[int]:
        """Each image's number as the input gives it (``image_numbers``), or 1..n when it gives none."""
        return list(self.image_numbers) if self.image_numbers is not None else list(range(1, len(self.image_names) + 1))

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
        """The recording with only the images ``indices`` (in that order), each keeping its number
        (:attr:`view_numbers`); scans and intrinsics kept."""
        idx = [int(i) for i in np.arange(len(self.image_names))[np.asarray(indices, dtype=int)]]
        numbers = self.view_numbers
        numbers = [numbers[i] for i in idx]  # kept as they were: view 31 stays 31
        return replace(
            self,
            image_names=[self.image_names[i] for i in idx],
            image_times_s=self.image_times_s[idx],
            image_keys=[self.image_keys[i] for i in idx],
            image_numbers=numbers,
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


def _read_lines(path: Path) -> list[str]:
    try:
        return path.read_text().splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise DatasetError(path, f"cannot read the time stamps ({exc})") from None


def read_times(path: str | Path) -> np.ndarray:
    """One time stamp (seconds) per line, increasing."""
    path = Path(path)
    return _times_of_lines(path, _read_lines(path))


def _times_of_lines(path: Path, lines: list[str]) -> np.ndarray:
    """:func:`read_times` on lines already read from ``path``."""
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


def _finite_float(token: str) -> float | None:
    try:
        value = float(token)
    except ValueError:
        return None
    return value if math.isfinite(value) else None


def _time_and_name(tokens: list[str]) -> tuple[str, float | None, str | None]:
    """A camera.txt line's kind, its time and its image's name: ``named`` (two fields, exactly one a finite
    number: the time; the other the name), ``time`` (numbers only, no name) or ``bad``."""
    values = [_finite_float(t) for t in tokens]
    if len(tokens) == 2 and (values[0] is None) != (values[1] is None):
        k = 0 if values[0] is not None else 1
        return "named", values[k], tokens[1 - k]
    return ("time" if all(v is not None for v in values) else "bad"), None, None


def read_image_list(path: str | Path) -> tuple[np.ndarray, list[str] | None]:
    """The times (seconds, increasing) of a camera.txt and, when its lines name their images, the names.

    A line is ``TIME`` or, naming the image, ``TIME NAME`` or ``NAME TIME`` (the field that is a finite number
    is the time). Either every line names its image or none does; a file that names none is read by
    :func:`read_times` (same checks, same messages) and its names are ``None``."""
    path = Path(path)
    lines = _read_lines(path)
    entries = [(number, line.split()) for number, line in enumerate(lines, start=1) if line.strip()]
    kinds = [(number, tokens, *_time_and_name(tokens)) for number, tokens in entries]
    first_named = next((number for number, _, kind, _, _ in kinds if kind == "named"), None)
    if first_named is None:
        return _times_of_lines(path, lines), None
    times: list[float] = []
    names: list[str] = []
    seen: dict[str, int] = {}
    for number, tokens, kind, t_s, name in kinds:
        if kind == "time":
            raise DatasetError(path, f"line {number}: a time without an image name, but line {first_named} names its image (name one on every line or on none)")
        if kind == "bad":
            raise DatasetError(path, f"line {number}: not TIME NAME or NAME TIME: {' '.join(tokens)[:40]!r}")
        if times and t_s <= times[-1]:
            raise DatasetError(path, f"line {number}: time {t_s} does not increase")
        if name in seen:
            raise DatasetError(path, f"line {number}: image {name} is listed twice (first on line {seen[name]})")
        seen[name] = number
        times.append(t_s)
        names.append(name)
    return np.asarray(times), names


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


# ------------------------------------------------------------------ MATLAB intrinsics (Calib_Results.mat)

# Pixel convention of cc. The Camera Calibration Toolbox for MATLAB (J.-Y. Bouguet) puts (0,0) at the centre of
# the upper-left pixel, as OpenCV does, although MATLAB itself indexes that pixel (1,1). Checked in the toolbox's
# source (copies on GitHub, e.g. sonsongithub/CoreAR calibration/toolbox_calib/): click_ima_calib.m subtracts 1
# from every extracted corner to move MATLAB's origin to 0, and init_intrinsic_param.m starts cc at
# [nx;ny]/2 - 0.5, which is OpenCV's image centre ((w-1)/2, (h-1)/2). The toolbox's parameter page
# (vision.caltech.edu/bouguetj/calib_doc/htmls/parameters.html, "Important Convention", as cited in
# https://www.mathworks.com/matlabcentral/answers/473128) says pixel centres are the reference and the
# upper-left pixel is the origin. So OpenCV's (cx, cy) is cc unchanged. (MATLAB's own cameraParameters,
# Computer Vision Toolbox, is 1-based: its PrincipalPoint is 1 more. That is another file format.)
BOUGUET_CC_OFFSET_PX = 0.0  # OpenCV (cx, cy) = cc - this
_BOUGUET_FIELDS = ("fc", "cc", "alpha_c", "kc", "nx", "ny")


def read_bouguet_intrinsics(path: str | Path) -> tuple[Intrinsics, None]:
    """Intrinsics from the ``Calib_Results.mat`` the Camera Calibration Toolbox for MATLAB saves: ``fc`` (focal
    lengths, pixels), ``cc`` (principal point), ``alpha_c`` (skew), ``kc`` (k1, k2, p1, p2, k3: OpenCV's order;
    older versions save four, k3 is then 0), ``nx``, ``ny`` (image width, height). The file does not give the
    board: the second value is ``None``."""
    from scipy.io import loadmat

    path = Path(path)
    if not path.is_file():
        raise DatasetError(path, "intrinsics file not found")
    try:
        mat = loadmat(str(path), variable_names=list(_BOUGUET_FIELDS))
    except NotImplementedError:  # scipy reads MAT files up to version 7.2
        raise DatasetError(path, "a MATLAB v7.3 (HDF5) file, which scipy cannot read: save it again with save(..., '-v7')") from None
    except Exception as exc:  # scipy's parser raises various errors on a file that is not a MAT file
        raise DatasetError(path, f"not a MATLAB MAT file ({one_line(exc, 120)})") from None

    def field(name: str, sizes: tuple[int, ...]) -> np.ndarray:
        if name not in mat:
            raise DatasetError(path, f"field {name} missing (a Calib_Results.mat has {', '.join(_BOUGUET_FIELDS)})")
        raw = np.asarray(mat[name])
        if raw.dtype.kind not in "iuf":
            raise DatasetError(path, f"field {name} is not a real number array ({raw.dtype})")
        values = raw.astype(float).ravel()
        if values.size not in sizes:
            raise DatasetError(path, f"field {name} has {values.size} values, expected {' or '.join(map(str, sizes))}")
        if not np.all(np.isfinite(values)):
            raise DatasetError(path, f"field {name} is not finite: {values.tolist()}")
        return values

    fc, cc, alpha, kc = field("fc", (2,)), field("cc", (2,)), field("alpha_c", (1,))[0], field("kc", (5, 4))
    size = [field(name, (1,))[0] for name in ("nx", "ny")]
    if np.any(fc <= 0):
        raise DatasetError(path, f"field fc must be positive: {fc.tolist()}")
    for name, value in zip(("nx", "ny"), size):
        if value < 1 or value != round(value):
            raise DatasetError(path, f"field {name} must be a whole number of pixels, at least 1: {value}")
    cx, cy = cc - BOUGUET_CC_OFFSET_PX
    K = np.array([[fc[0], alpha * fc[0], cx], [0.0, fc[1], cy], [0.0, 0.0, 1.0]])
    return Intrinsics(K, np.pad(kc, (0, 5 - kc.size)), int(size[0]), int(size[1])), None


def read_intrinsics_file(path: str | Path) -> tuple[Intrinsics, BoardSpec | None]:
    """Intrinsics (and the board, when the file gives it) from ``path``: a ``.mat`` file is the MATLAB
    toolbox's (:func:`read_bouguet_intrinsics`), anything else OpenCV's XML or YAML (:func:`read_opencv_intrinsics`)."""
    path = Path(path)
    return read_bouguet_intrinsics(path) if path.suffix.lower() == ".mat" else read_opencv_intrinsics(path)


# ------------------------------------------------------------------ the RADLOCC recording folder


def read_radlocc_recording(folder: str | Path, intrinsics_path: str | Path | None = None) -> CalibrationRecording:
    """Read a recording in the RADLOCC layout (see the module's docstring). Images are only listed here.

    Images: those ``data/camera.txt`` names (:func:`read_image_list`; names are paths below ``data/``), numbered
    by the integer that ends each name's stem when every name has a different one, else by their place in the
    list; or, when it names none, ``data/RGB<k>.png`` (or ``.jpg``, ``.jpeg``, the suffix in any case), number k.
    Intrinsics: ``intrinsics_path`` when given (:func:`read_intrinsics_file`), else the first file found of
    ``xml/out_camera_data.xml`` (OpenCV), ``Calib_Results.mat`` (MATLAB toolbox) and ``data/Calib_Results.mat``."""
    folder = Path(folder)
    if not folder.is_dir():
        raise DatasetError(folder, "recording folder not found")
    data = folder / "data"
    times, listed = read_image_list(data / "camera.txt")
    scans = read_radlocc_scans(data / "laser.txt")
    intrinsics, board = read_intrinsics_file(intrinsics_path) if intrinsics_path is not None else _find_intrinsics(folder)
    if listed is None:
        paths, missing = _numbered_images(data, len(times))
        names, numbers = [p.name for p in paths], list(range(1, len(times) + 1))
    else:
        paths, names, numbers = [data / name for name in listed], listed, _numbers_from_names(listed)
        missing = [name for name, p in zip(listed, paths) if not p.is_file()]
    if missing:
        raise DatasetError(data, f"{len(missing)} of {len(paths)} images listed in camera.txt are missing (first: {missing[0]})")
    return CalibrationRecording(names, times, scans, intrinsics, board, paths, read_image_file, numbers)


_INTRINSICS_PLACES = (("xml", "out_camera_data.xml"), ("Calib_Results.mat",), ("data", "Calib_Results.mat"))


def _find_intrinsics(folder: Path) -> tuple[Intrinsics, BoardSpec | None]:
    for parts in _INTRINSICS_PLACES:
        path = folder.joinpath(*parts)
        if path.is_file():
            return read_intrinsics_file(path)
    raise DatasetError(folder, "no intrinsics file: neither xml/out_camera_data.xml (OpenCV) nor Calib_Results.mat (MATLAB toolbox, here or in data/)")


_NUMBERED_IMAGE = re.compile(r"RGB([0-9]+)\.(?i:png|jpe?g)")


def _numbered_images(data: Path, n: int) -> tuple[list[Path], list[str]]:
    """``data/RGB<k>.<png|jpg|jpeg>`` for k = 1..n, and the names of those missing."""
    found: dict[int, Path] = {}
    try:
        entries = sorted(data.iterdir()) if data.is_dir() else []
    except OSError as exc:
        raise DatasetError(data, f"cannot list the images ({exc.strerror or exc})") from None
    for path in entries:
        match = _NUMBERED_IMAGE.fullmatch(path.name)
        if match is None or not 1 <= int(match.group(1)) <= n:
            continue
        k = int(match.group(1))
        if k in found:
            raise DatasetError(data, f"image {k} is both {found[k].name} and {path.name}: keep one")
        found[k] = path
    paths = [found.get(k, data / f"RGB{k}.png") for k in range(1, n + 1)]
    return paths, [f"RGB{k}.png/.jpg/.jpeg" for k in range(1, n + 1) if k not in found]


def _numbers_from_names(names: list[str]) -> list[int]:
    """The integer ending each name's stem (``frame_0042.jpg``: 42) when every name has a different one,
    else 1..n (the names' places in the list)."""
    matches = [re.search(r"([0-9]+)$", Path(name).stem) for name in names]
    numbers = [int(m.group(1)) for m in matches if m is not None]
    if len(numbers) == len(names) and len(set(numbers)) == len(numbers):
        return numbers
    return list(range(1, len(names) + 1))


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
