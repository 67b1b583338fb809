"""KITTI logs as :class:`Sequence`s: the odometry benchmark layout and the raw (synced) layout.

Odometry layout (:class:`KittiOdometrySequence`)::

    ROOT/sequences/NN/image_0/000000.png   left grey camera, rectified
    ROOT/sequences/NN/velodyne/000000.bin  Velodyne HDL-64E scans (float32 x, y, z, reflectance)
    ROOT/sequences/NN/calib.txt            P0..P3 (3x4) and Tr (lidar -> camera 0, 3x4), row-major
    ROOT/sequences/NN/times.txt            one time per frame, seconds
    ROOT/poses/NN.txt                      camera-0 poses in the first camera frame (3x4 per line), if known

Raw layout (:class:`KittiRawSequence`)::

    DATE/DATE_drive_XXXX_sync/image_0N/data/*.png, image_0N/timestamps.txt  (N = 0, 1 grey; 2, 3 colour)
    DATE/DATE_drive_XXXX_sync/velodyne_points/data/*.bin, timestamps.txt (facing forward),
                                           timestamps_start.txt, timestamps_end.txt
    DATE/DATE_drive_XXXX_sync/oxts/data/*.txt (30 values per line), oxts/timestamps.txt
    DATE/calib_cam_to_cam.txt, calib_velo_to_cam.txt, calib_imu_to_velo.txt (or in the drive folder)

Time stamps of the raw layout (``2011-09-26 13:02:25.964389445``) become seconds after the drive's
first OXTS time stamp.

Frames (all right-handed, metres):

- body: the lidar frame (x forward, y left, z up) moved down by ``lidar_height_m`` (1.73 m, KITTI's
  mounting height), so that the body's z = 0 plane is the road under the vehicle, as the front end's
  focus area assumes. ``T_body_lidar`` is a pure translation.
- camera: ``T_body_cam = T_body_lidar @ inv(T_cam_lidar)``, ``T_cam_lidar`` being ``Tr`` (odometry) or
  ``R_rect_00 @ [R|T]`` of ``calib_velo_to_cam.txt`` (raw), for camera 0; intrinsics from ``P0`` /
  ``P_rect_00``, no distortion (the images are rectified). The raw layout reads any of its four
  cameras (:data:`RAW_CAMERAS`; default the first present, grey first): camera N's rectified
  projection ``P_rect_0N = K [I | K t]`` is camera 0's rectified frame moved by ``t`` (the stereo
  baseline), so ``T_camN_lidar = Trans(t) @ T_cam0_lidar``. Colour images are read as grey.
- laser: one ring of the 64 (see :mod:`dem_graph.datasets.velodyne`), its beams in the lidar frame,
  so ``T_body_laser = T_body_lidar``.
- world, odometry layout: the body frame at the first frame (z up as far as the car stands level
  there); the ground truth is ``T_world_body = T_body_cam @ T_cam0_cami @ inv(T_body_cam)``.
- world, raw layout: east-north-up, from the OXTS latitude and longitude through the Mercator
  projection with the scale of the first latitude, as the KITTI development kit describes; its
  origin is the first OXTS position. OXTS roll, pitch and yaw give the IMU's orientation
  (``Rz(yaw) Ry(pitch) Rx(roll)``), ``T_body_imu = T_body_lidar @ T_velo_imu``, ``T_velo_imu`` being
  ``[R|T]`` of ``calib_imu_to_velo.txt`` (it maps IMU coordinates to Velodyne coordinates).
- imu, raw layout: the OXTS unit's own frame (x forward, y left, z up), ``T_body_imu`` as above.

Odometry: the odometry layout has none (the estimators then use their constant-velocity model).
The raw layout's OXTS velocities give increments: the forward, leftward and upward velocity and
angular rate (``vf vl vu``, ``wf wl wu``, in the heading frame) are turned into the IMU frame with
the OXTS roll and pitch, averaged over consecutive samples, and integrated as a constant twist
over each interval; their covariance is :class:`~dem_graph.geometry.rig.OdometrySpec`'s for the
distance travelled.

IMU: the raw layout's OXTS records also hold the unit's raw inertial measurements, the
accelerations ``ax ay az`` and angular rates ``wx wy wz`` in its own frame; each record is an
:class:`~dem_graph.datasets.events.ImuSample` at the record's time stamp (10 Hz in the synced
drives), and the rig's ``imu`` is an :class:`~dem_graph.geometry.rig.ImuSpec` with the RT3003's
noise figures (:func:`oxts_imu_spec`). ``ax ay az`` are specific force already (they hold gravity's
reaction: see :data:`OXTS_ACCEL`) and are passed on unchanged. The odometry layout has no IMU.

Ground truth: the trajectory, and :attr:`ground_truth`'s elevation, the reference ground built from
all 64 rings of every scan placed with the ground-truth poses
(:func:`~dem_graph.datasets.velodyne.reference_surface`), made when first asked for.
"""

from __future__ import annotations

import functools
import logging
import math
from collections.abc import Iterator
from datetime import datetime, timezone
from pathlib import Path
from typing import NamedTuple

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
from dem_graph.datasets.checks import STAMP_NOT_AFTER, InputChecks, SkippedMessages, increasing_stamps, time_text
from dem_graph.datasets.events import CameraFrame, Event, ImuSample, LaserScan, Odometry
from dem_graph.datasets.velodyne import (
    RingLaser,
    RingSplitError,
    azimuth_deg,
    choose_ring,
    elevation_deg,
    read_velodyne_bin,
    reference_surface,
    register_scans,
    ring_elevations_deg,
    scan_in_world,
    split_rings,
)
from dem_graph.errors import DatasetError
from dem_graph.geometry.grid import ElevationGrid
from dem_graph.geometry.rig import CameraSpec, ImuSpec, LaserSpec, OdometrySpec, SensorRig, validated
from dem_graph.geometry.se3 import invert, make_pose, nearest_pose, rotation_from_rpy
from dem_graph.geometry.trajectory import Trajectory
from dem_graph.progress import progress

log = logging.getLogger(__name__)

LIDAR_HEIGHT_M = 1.73  # KITTI's Velodyne above the road
EARTH_RADIUS_M = 6378137.0


# ----------------------------------------------------------------------------------------------
# small file readers


def read_calib_file(path: str | Path) -> dict[str, np.ndarray]:
    """``key: numbers`` lines of a KITTI calibration file; lines whose values are not numbers
    (``calib_time``) are skipped. Raises :class:`DatasetError` naming a missing file."""
    path = Path(path)
    if not path.is_file():
        raise DatasetError(path, "calibration file not found")
    out: dict[str, np.ndarray] = {}
    for line in path.read_text(errors="replace").splitlines():
        key, sep, values = line.partition(":")
        if not sep:
            continue
        try:
            out[key.strip()] = np.array([float(v) for v in values.split()])
        except ValueError:
            continue
    return out


def _calib_matrix(calib: dict, key: str, shape: tuple[int, int], path: Path) -> np.ndarray:
    if key not in calib:
        raise DatasetError(path, f"no '{key}' entry")
    if calib[key].size != shape[0] * shape[1]:
        raise DatasetError(path, f"'{key}' has {calib[key].size} values, expected {shape[0] * shape[1]}")
    if not np.all(np.isfinite(calib[key])):
        raise DatasetError(path, f"'{key}' holds NaN or infinite values")
    return calib[key].reshape(shape)


def _pose_from_3x4(M: np.ndarray) -> np.ndarray:
    return nearest_pose(np.vstack([M, [0.0, 0.0, 0.0, 1.0]]))


def read_times(path: Path) -> np.ndarray:
    """The odometry layout's ``times.txt``: one time in seconds per line."""
    if not path.is_file():
        raise DatasetError(path, "times file not found")
    try:
        t = np.loadtxt(path, dtype=float, ndmin=1)
    except ValueError as exc:
        raise DatasetError(path, f"not one number per line ({exc})") from None
    i = first_not_increasing(t)
    if i is not None:  # the odometry benchmark's own file, one time for an image and a scan: not a recorder's blemish
        raise DatasetError(path, f"times do not increase at line {i + 1} ({time_text(t[i])} after {time_text(t[i - 1])} on line {i})")
    return t


def read_kitti_timestamps(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Raw-layout time stamps ``YYYY-MM-DD HH:MM:SS.fffffffff`` as (whole UTC seconds, nanoseconds) int64 arrays."""
    if not path.is_file():
        raise DatasetError(path, "time stamps file not found")
    seconds, nanos = [], []
    for i, line in enumerate(path.read_text().splitlines()):
        text = line.strip()
        if not text:
            continue
        whole, _, frac = text.partition(".")
        try:
            dt = datetime.strptime(whole, "%Y-%m-%d %H:%M:%S").replace(tzinfo=timezone.utc)
            ns = int((frac + "000000000")[:9]) if frac else 0
        except ValueError:
            raise DatasetError(path, f"line {i + 1}: not a time stamp 'YYYY-MM-DD HH:MM:SS.fffffffff': {text!r}") from None
        seconds.append(int(dt.timestamp()))
        nanos.append(ns)
    return np.array(seconds, dtype=np.int64), np.array(nanos, dtype=np.int64)


def read_kitti_poses(path: Path) -> np.ndarray:
    """(N,4,4) poses, one 3x4 row-major per line."""
    try:
        values = np.loadtxt(path, dtype=float, ndmin=2)
    except ValueError as exc:
        raise DatasetError(path, f"not 12 numbers per line ({exc})") from None
    if values.shape[1] != 12:
        raise DatasetError(path, f"{values.shape[1]} numbers per line, expected 12 (a 3x4 pose)")
    return np.stack([_pose_from_3x4(v.reshape(3, 4)) for v in values])


def _files(folder: Path, suffix: str, what: str) -> list[Path]:
    if not folder.is_dir():
        raise DatasetError(folder, f"{what} folder not found")
    return sorted(p for p in folder.iterdir() if p.suffix == suffix)


def _read_image(path: Path) -> np.ndarray:
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise DatasetError(path, "missing or not a readable image")
    if image.dtype != np.uint8:
        raise DatasetError(path, f"8-bit image expected, got {image.dtype}")
    return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) if image.ndim == 3 else image  # colour cameras 2 and 3: grey


# ----------------------------------------------------------------------------------------------
# the shared sequence


KITTI_SETTINGS = Path(__file__).with_name("settings") / "kitti.yaml"


class _KittiSequence(Sequence):
    """Camera frames and one Velodyne ring (and odometry and IMU samples, when the log has them) merged in time order."""

    layout = "kitti"  # the format name :func:`dem_graph.datasets.open.open_dataset` knows it by

    def open_options(self) -> dict:
        """The layout and the ring (and the odometry layout's sequence): a run made with ``--ring N``
        must be read again with ring N."""
        return {"format": self.layout, "ring": int(self.ring)}

    def run_settings(self) -> dict:
        """KITTI's run settings (``datasets/settings/kitti.yaml``): a car at 10-14 m/s and 10 Hz. With
        the package's defaults, made for a small robot at 25 Hz, no point is ever tracked."""
        return yaml.safe_load(KITTI_SETTINGS.read_text())

    def __init__(
        self,
        name: str,
        frame_t_s: np.ndarray,
        frame_files: list[Path],
        scan_t_s: np.ndarray,
        scan_files: list[Path],
        T_cam_lidar: np.ndarray,
        P_cam: np.ndarray,
        image_size_px: tuple[int, int],
        truth: Trajectory | None,
        odometry: list[Odometry],
        ring: int | None,
        ground_distance_m: float,
        azimuth_step_deg: float,
        lidar_height_m: float,
        T_world_body_initial: np.ndarray,
        t_start_s: float,
        calib_path: Path | None = None,
        imu: OxtsImu | None = None,
    ):
        self.name = name
        self._frame_t_s, self._frame_files = frame_t_s, frame_files
        self._scan_t_s, self._scan_files = scan_t_s, scan_files
        self._truth = truth
        self._odometry = odometry
        self._imu = imu
        self._t_start_s = float(t_start_s)
        self._T0 = np.array(T_world_body_initial, dtype=float)
        self.T_body_lidar = make_pose(np.eye(3), [0.0, 0.0, lidar_height_m])
        width, height = image_size_px
        rate = 1.0 / float(np.median(np.diff(frame_t_s))) if len(frame_t_s) > 1 else 10.0
        scan_rate = 1.0 / float(np.median(np.diff(scan_t_s))) if len(scan_t_s) > 1 else 10.0
        camera = validated(  # the calibration's intrinsics checked as a rig file's would be
            CameraSpec,
            dict(
                width_px=width,
                height_px=height,
                fx_px=P_cam[0, 0],
                fy_px=P_cam[1, 1],
                cx_px=P_cam[0, 2],
                cy_px=P_cam[1, 2],
                distortion=(0.0, 0.0, 0.0, 0.0, 0.0),
                rate_hz=rate,
                noise_sigma_dn=2.0,
                T_body_cam=self.T_body_lidar @ invert(T_cam_lidar),
            ),
            calib_path,
            "camera",
        )
        half_fov_deg = float(np.degrees(np.arctan2(max(camera.cx_px, width - 1 - camera.cx_px), camera.fx_px)))
        self._ring_laser, self._ring_elevations_deg, self.ring_split = self._make_ring_laser(
            ring, ground_distance_m, half_fov_deg, azimuth_step_deg
        )
        self._rig = SensorRig(
            camera=camera,
            laser=LaserSpec(
                T_body_laser=self.T_body_lidar,
                beams=self._ring_laser.beams(),
                range_min_m=2.0,
                range_max_m=80.0,
                range_sigma_m=0.02,
                rate_hz=scan_rate,
            ),
            odometry=OdometrySpec(rate_hz=rate) if odometry else None,
            imu=imu.spec if imu is not None else None,
        )
        self._elevation: ElevationGrid | None = None
        self._ranges_cache: dict[int, np.ndarray] = {}  # scan index -> the ring's ranges
        # the stream numbers of datasets.base: odometry, laser, camera, IMU (at equal times in that order)
        self._order = merged_order([o.t_s for o in odometry], scan_t_s, frame_t_s, imu.t_s if imu is not None else [])

    def _make_ring_laser(self, ring: int | None, ground_distance_m: float, half_fov_deg: float, step_deg: float):
        if not self._scan_files:
            raise DatasetError(Path(self.name), "no Velodyne scans")
        first = self._scan_files[0]
        points = read_velodyne_bin(first)
        try:
            ring_of, how = split_rings(points)
            if ring is None:
                ring = choose_ring(points, ring_of, half_fov_deg, ground_distance_m)
        except RingSplitError as exc:
            raise DatasetError(first, str(exc)) from None
        if not 0 <= ring < 64:
            raise DatasetError(first, f"ring {ring} does not exist: the Velodyne has rings 0 (highest) to 63")
        el_all = ring_elevations_deg(points, ring_of)
        az = azimuth_deg(points)
        in_view = (ring_of == ring) & (np.abs(az) <= half_fov_deg)
        if in_view.sum() < 10:
            raise DatasetError(first, f"ring {ring} has no returns in the camera's field of view")
        el = float(np.median(elevation_deg(points[in_view])))
        log.info("KITTI: ring %d (elevation %.2f deg, split by %s), %.1f deg either side", ring, el, how, half_fov_deg)
        return RingLaser(ring, el, half_fov_deg, step_deg), el_all, how

    @functools.cached_property
    def initial_speed_mps(self) -> float | None:
        """The speed over the first two Velodyne scans, from registering them (point-to-plane ICP on
        all 64 rings): the log's own estimate of the starting speed, for a run without odometry
        (``motion.initial_speed_from_dataset``). None when it cannot be had. Computed once."""
        if len(self._scan_files) < 2 or not self._scan_t_s[1] > self._scan_t_s[0]:
            return None
        T_first_second, pairs = register_scans(read_velodyne_bin(self._scan_files[1]), read_velodyne_bin(self._scan_files[0]))
        if pairs < 500:
            log.warning("KITTI: the first two scans do not register (%d point pairs): no starting speed from them", pairs)
            return None
        speed = float(np.linalg.norm(T_first_second[:3, 3]) / (self._scan_t_s[1] - self._scan_t_s[0]))
        log.info("KITTI: starting speed %.2f m/s from the first two scans (%d point pairs)", speed, pairs)
        return speed

    @property
    def ring(self) -> int:
        return self._ring_laser.ring

    @property
    def ring_laser(self) -> RingLaser:
        return self._ring_laser

    @property
    def rig(self) -> SensorRig:
        return self._rig

    @property
    def t_start_s(self) -> float:
        return self._t_start_s

    @property
    def T_world_body_initial(self) -> np.ndarray:
        return self._T0.copy()

    @property
    def has_odometry(self) -> bool:
        return bool(self._odometry)

    @property
    def has_imu(self) -> bool:
        """True for a raw drive (its OXTS records' inertial measurements), False for the odometry layout."""
        return self._imu is not None

    @property
    def n_frames(self) -> int:
        return len(self._frame_t_s)

    def event_count(self) -> int:
        return len(self._order)

    def read_scan(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """Scan ``i``'s points (N,4) and their ring numbers."""
        points = read_velodyne_bin(self._scan_files[i])
        try:
            ring_of, _ = split_rings(points, self._ring_elevations_deg)
        except RingSplitError as exc:
            raise DatasetError(self._scan_files[i], str(exc)) from None
        return points, ring_of

    def _scan_ranges(self, i: int) -> np.ndarray:
        """Scan ``i``'s ring as ranges, read and split once (the run and the DEM after it both ask)."""
        if i not in self._ranges_cache:
            points, ring_of = self.read_scan(i)
            self._ranges_cache[i] = self._ring_laser.ranges_m(points, ring_of)
        return self._ranges_cache[i].copy()

    def laser_scans(self) -> tuple[np.ndarray, np.ndarray]:
        ranges = [self._scan_ranges(i) for i in range(len(self._scan_files))]
        return self._scan_t_s.copy(), np.array(ranges, dtype=float).reshape(len(ranges), self._rig.laser.beams.count)

    def events(self) -> Iterator[Event]:
        images = read_ahead(_read_image(path) for path in self._frame_files)  # camera frames come in index order
        for kind, i in self._order:
            if kind == ODOMETRY_STREAM:
                yield self._odometry[i]
            elif kind == LASER_STREAM:
                yield LaserScan(float(self._scan_t_s[i]), self._scan_ranges(i), i)
            elif kind == CAMERA_STREAM:
                yield CameraFrame(float(self._frame_t_s[i]), next(images), i)
            elif kind == IMU_STREAM:
                imu = self._imu
                yield ImuSample(float(imu.t_s[i]), imu.gyro_rad_s[i].copy(), imu.accel_mps2[i].copy(), i)

    @property
    def ground_truth(self) -> GroundTruth | None:
        if self._truth is None:
            return None
        if self._elevation is None:
            self._elevation = self.reference_elevation()
        return GroundTruth(self._truth, self._elevation)

    def reference_elevation(self, resolution_m: float = 0.2, max_range_m: float = 40.0, margin_m: float = 20.0) -> ElevationGrid:
        """The reference ground from all 64 rings of every scan inside the ground truth's time span,
        placed with the ground-truth poses; points farther than ``max_range_m`` from the lidar are
        left out, and the grid covers the trajectory ``margin_m`` around."""
        truth = self._truth
        if truth is None:
            raise DatasetError(Path(self.name), "no ground-truth trajectory: no reference surface")
        clouds = []
        inside = (self._scan_t_s >= truth.t_s[0]) & (self._scan_t_s <= truth.t_s[-1])
        scans = np.flatnonzero(inside)
        T_world_lidar = truth.at(self._scan_t_s[scans]) @ self.T_body_lidar
        for i, T in progress(zip(scans, T_world_lidar), total=len(scans), desc="reference ground", unit="scan"):
            points = read_velodyne_bin(self._scan_files[i])[:, :3]
            points = points[np.linalg.norm(points, axis=1) <= max_range_m]
            clouds.append(scan_in_world(points, T))
        xy = truth.positions_xyz[:, :2]
        lo, hi = xy.min(axis=0) - margin_m, xy.max(axis=0) + margin_m
        try:
            return reference_surface(clouds, resolution_m, bounds_xy_m=(lo[0], lo[1], hi[0], hi[1]))
        except ValueError as exc:
            raise DatasetError(self._scan_files[0], f"no reference surface: {exc}") from None


# ----------------------------------------------------------------------------------------------
# the odometry layout


class KittiOdometrySequence(_KittiSequence):
    """A sequence of the KITTI odometry benchmark (``ROOT/sequences/NN``, ``ROOT/poses/NN.txt``).

    ``ring``: the Velodyne ring used as the line laser (0 highest .. 63); default the one whose
    returns ahead lie nearest ``ground_distance_m``. ``azimuth_step_deg``: its beams' spacing.
    """

    layout = "kitti-odometry"

    def open_options(self) -> dict:
        return {**super().open_options(), "sequence": self.path.name}

    def __init__(
        self,
        root: str | Path,
        sequence: str | int | None = None,
        ring: int | None = None,
        ground_distance_m: float = 10.0,
        azimuth_step_deg: float = 0.25,
        lidar_height_m: float = LIDAR_HEIGHT_M,
    ):
        root = Path(root)
        if (root / "image_0").is_dir() and root.parent.name == "sequences":
            sequence, root = root.name if sequence is None else sequence, root.parent.parent
        seq_root = root / "sequences"
        if not seq_root.is_dir():
            raise DatasetError(seq_root, "not found: not a KITTI odometry folder (ROOT/sequences/NN)")
        if sequence is None:
            names = sorted(p.name for p in seq_root.iterdir() if p.is_dir())
            if len(names) != 1:
                raise DatasetError(seq_root, f"holds {len(names)} sequences ({', '.join(names) or 'none'}): give the sequence number")
            sequence = names[0]
        sequence = f"{int(sequence):02d}" if str(sequence).isdigit() else str(sequence)
        folder = seq_root / sequence
        if not folder.is_dir():
            raise DatasetError(folder, "sequence folder not found")
        self.path = folder
        calib_path = folder / "calib.txt"
        calib = read_calib_file(calib_path)
        P0 = _calib_matrix(calib, "P0", (3, 4), calib_path)
        T_cam_lidar = _pose_from_3x4(_calib_matrix(calib, "Tr", (3, 4), calib_path))
        times_path = folder / "times.txt"
        t_s = read_times(times_path)
        images = _files(folder / "image_0", ".png", "image_0")
        scans = _files(folder / "velodyne", ".bin", "velodyne")
        if len(images) != len(t_s):
            raise DatasetError(times_path, f"{len(t_s)} times but {len(images)} images in image_0: they must match")
        if len(scans) != len(t_s):
            raise DatasetError(times_path, f"{len(t_s)} times but {len(scans)} scans in velodyne: they must match")
        if not images:
            raise DatasetError(folder / "image_0", "no images")
        first = _read_image(images[0])
        T_body_lidar = make_pose(np.eye(3), [0.0, 0.0, lidar_height_m])
        T_body_cam = T_body_lidar @ invert(T_cam_lidar)
        truth = None
        poses_path = root / "poses" / f"{sequence}.txt"
        if poses_path.is_file():
            T_cam0_cam = read_kitti_poses(poses_path)
            if len(T_cam0_cam) != len(t_s):
                raise DatasetError(poses_path, f"{len(T_cam0_cam)} poses but {len(t_s)} times in {times_path}: they must match")
            T_world_body = T_body_cam @ T_cam0_cam @ invert(T_body_cam)
            truth = Trajectory.from_poses(t_s, nearest_pose(T_world_body))
        super().__init__(
            f"kitti-odometry-{sequence}",
            t_s,
            images,
            t_s.copy(),
            scans,
            T_cam_lidar,
            P0,
            (first.shape[1], first.shape[0]),
            truth,
            [],
            ring,
            ground_distance_m,
            azimuth_step_deg,
            lidar_height_m,
            np.eye(4),
            float(t_s[0]),
            calib_path,
        )

    def __repr__(self) -> str:
        return f"KittiOdometrySequence({str(self.path)!r}, frames={self.n_frames}, ring={self.ring})"


# ----------------------------------------------------------------------------------------------
# the raw layout


def oxts_poses(oxts: np.ndarray) -> np.ndarray:
    """(N,4,4) IMU poses ``T_world_imu`` from OXTS rows (lat, lon, alt, roll, pitch, yaw, ...):
    east-north-up metres by the Mercator projection scaled at the first latitude, origin at the first position."""
    lat, lon, alt = oxts[:, 0], oxts[:, 1], oxts[:, 2]
    scale = math.cos(math.radians(lat[0]))
    x = scale * EARTH_RADIUS_M * np.radians(lon)
    y = scale * EARTH_RADIUS_M * np.log(np.tan(np.radians(90.0 + lat) / 2.0))
    t = np.stack([x - x[0], y - y[0], alt - alt[0]], axis=1)
    R = rotation_from_rpy(oxts[:, 3], oxts[:, 4], oxts[:, 5])
    return make_pose(R, t)


RAW_TRUTHS = ("positions", "velocities")  # what a raw drive's true trajectory is built from (orientation: always the OXTS attitude)


def oxts_velocity_poses(t_s: np.ndarray, oxts: np.ndarray) -> np.ndarray:
    """(N,4,4) IMU poses ``T_world_imu`` with the OXTS attitude and the positions its forward,
    leftward and upward velocities ``vf vl vu`` (heading frame, turned to east-north-up by the
    yaw) integrate to (trapezoid rule over ``t_s``), from the origin.

    Over a short drive they keep the direction of travel better than the GPS positions: on drive
    0013 of 2011_09_26 the positions run a degree right of the direction of travel that the
    Velodyne's scans, registered one to the next, give, and these velocities agree with the
    Velodyne to 0.2 degree (tests/test_kitti_shared.py). The OXTS's east and north velocities ``ve
    vn`` are not used: they run 0.4 degree off ``vf vl`` and the yaw on that drive. Over long
    drives the integration drifts and the positions are better."""
    t_s = np.asarray(t_s, dtype=float)
    v_world = np.einsum("nij,nj->ni", rotation_from_rpy(np.zeros(len(oxts)), np.zeros(len(oxts)), oxts[:, 5]), oxts[:, 8:11])
    steps = 0.5 * (v_world[1:] + v_world[:-1]) * np.diff(t_s)[:, None]
    t = np.concatenate([np.zeros((1, 3)), np.cumsum(steps, axis=0)])
    return make_pose(rotation_from_rpy(oxts[:, 3], oxts[:, 4], oxts[:, 5]), t)


def oxts_twists(oxts: np.ndarray) -> np.ndarray:
    """(N,6) twists [angular rate, velocity] in the IMU frame from the OXTS heading-frame rates
    ``wf wl wu`` and velocities ``vf vl vu``, turned by the OXTS roll and pitch."""
    R_heading_imu = rotation_from_rpy(oxts[:, 3], oxts[:, 4], np.zeros(len(oxts)))
    v_heading = oxts[:, 8:11]
    w_heading = oxts[:, 20:23]
    v_imu = np.einsum("nji,nj->ni", R_heading_imu, v_heading)
    w_imu = np.einsum("nji,nj->ni", R_heading_imu, w_heading)
    return np.concatenate([w_imu, v_imu], axis=1)


def odometry_from_oxts(t_s: np.ndarray, oxts: np.ndarray, T_body_imu: np.ndarray, spec: OdometrySpec) -> list[Odometry]:
    """Body increments between consecutive OXTS samples: the mean of the two twists held over the interval."""
    import gtsam

    twists = oxts_twists(oxts)
    T_imu_body = invert(T_body_imu)
    out = []
    for i in range(1, len(t_s)):
        dt = float(t_s[i] - t_s[i - 1])
        xi = 0.5 * (twists[i - 1] + twists[i]) * dt
        T_imu = gtsam.Pose3.Expmap(xi).matrix()
        T_body = nearest_pose(T_body_imu @ T_imu @ T_imu_body)
        distance = float(np.linalg.norm(T_body[:3, 3]))
        out.append(Odometry(float(t_s[i]), float(t_s[i - 1]), T_body, spec.increment_covariance(distance), i - 1))
    return out


# an OXTS record's 30 fields, in order (the drive's oxts/dataformat.txt, whose third acceleration is misnamed "ay")
OXTS_FIELDS = (
    "lat", "lon", "alt", "roll", "pitch", "yaw", "vn", "ve", "vf", "vl", "vu",
    "ax", "ay", "az", "af", "al", "au", "wx", "wy", "wz", "wf", "wl", "wu",
    "pos_accuracy", "vel_accuracy", "navstat", "numsats", "posmode", "velmode", "orimode",
)  # fmt: skip
OXTS_GYRO = slice(17, 20)
"""``wx wy wz``: angular rate about the unit's x (forward), y (left), z (up), rad/s. On drive 0013 they
integrate (trapezoid) over its 4.7 s to the recorded yaw's and pitch's changes: wz -0.0173 rad against
-0.0182, wy -0.0066 against -0.0069 (pitch positive nose down, a turn about +y)."""
OXTS_ACCEL = slice(11, 14)
"""``ax ay az``: acceleration along the unit's x (forward), y (left), z (up), m/s^2. They are specific
force, gravity's reaction included, as :class:`~dem_graph.datasets.events.ImuSample` wants them, and
are passed on unchanged. Measured on drive 0013 of 2011_09_26 (48 records at 11-12 m/s, braking at
0.23 m/s^2, roll and pitch under 0.9 degree): the mean of ``|(ax, ay, az)|`` is 9.800 m/s^2 (9.42 to
10.16; it would be about 0.3 had gravity been taken out), the mean ``az`` 9.791 against 9.809 for
gravity's reaction at the recorded roll and pitch, and the three turned to the world by the recorded
roll, pitch and yaw average 9.792 m/s^2 up (standard deviation 0.18, so 0.026 for the mean) against
gravity's 9.809 there. The mean ``ax``, -0.297, is the braking (-0.230, from ``vf``) plus gravity's
reaction along the nose, pitched 0.34 degree down (-0.058). tests/test_kitti_imu.py checks this."""
_OXTS_IMU_FIELDS = tuple(range(OXTS_ACCEL.start, OXTS_ACCEL.stop)) + tuple(range(OXTS_GYRO.start, OXTS_GYRO.stop))


def _read_oxts(files: list[Path]) -> np.ndarray:
    """(N,30) OXTS records, one file each. A record without its 30 numbers, or whose inertial
    measurements (``ax ay az wx wy wz``) are not finite, is a :class:`DatasetError` naming the file
    and the field."""
    rows = []
    n = len(OXTS_FIELDS)
    for path in files:
        tokens = path.read_text(errors="replace").split()
        if len(tokens) != n:
            missing = f"{'a field is' if len(tokens) == n - 1 else f'{n - len(tokens)} fields are'} missing" if len(tokens) < n else "too many fields"
            raise DatasetError(path, f"{len(tokens)} numbers, an OXTS record has {n} ({' '.join(OXTS_FIELDS)}): {missing}")
        values = np.empty(n)
        for k, token in enumerate(tokens):
            try:
                values[k] = float(token)
            except ValueError:
                raise DatasetError(path, f"{OXTS_FIELDS[k]} (field {k + 1} of {n}) is not a number: {token!r}") from None
        for k in _OXTS_IMU_FIELDS:
            if not math.isfinite(values[k]):
                raise DatasetError(path, f"{OXTS_FIELDS[k]} (field {k + 1} of {n}) is {values[k]}: the IMU's accelerations and angular rates must be finite")
        rows.append(values)
    return np.array(rows).reshape(-1, n)


# The OXTS RT3003 (the unit on KITTI's car, Geiger et al. 2013): no noise density or bias random
# walk of it was found. The white noise densities and bias random walks are those gtsam's KITTI
# example uses for KITTI's OXTS records (gtsam examples/Data/KittiEquivBiasedImu_metadata.txt:
# AccelerometerSigma 0.01, GyroscopeSigma 1.75e-4, AccelerometerBiasSigma 1.67e-4, GyroscopeBiasSigma
# 2.91e-6, used as continuous-time densities with 100 Hz records). The gyroscope's 1.75e-4 rad/s/sqrt(Hz)
# is 0.6 deg/sqrt(h), three times the 0.2 deg/sqrt(h) (5.8e-5) of a navigation unit of this class. The
# synced drives' records come at 10 Hz, so the road's vibration aliases into them: on drive 0013 the
# records scatter from one to the next (second differences) by 0.04-0.15 m/s^2 and 0.0016-0.0065 rad/s
# per axis, 0.013-0.046 m/s^2/sqrt(Hz) and 5e-4-2e-3 rad/s/sqrt(Hz) as densities at 10 Hz: larger than
# either figure, motion the 10 Hz samples do not resolve rather than sensor noise.
RT3003_GYRO_NOISE_DENSITY = 1.75e-4  # rad/s/sqrt(Hz), gtsam's KITTI example
RT3003_ACCEL_NOISE_DENSITY = 1.0e-2  # m/s^2/sqrt(Hz), gtsam's KITTI example
RT3003_GYRO_BIAS_RANDOM_WALK = 2.91e-6  # rad/s^2/sqrt(Hz), gtsam's KITTI example
RT3003_ACCEL_BIAS_RANDOM_WALK = 1.67e-4  # m/s^3/sqrt(Hz), gtsam's KITTI example
# the bias left at the start: the OxTS RT3000 manual's angular-rate bias, 0.01 deg/s 1 sigma (as quoted
# from OxTS-RT500-RT3000-Manual-240215, a later unit of the family); the accelerometer's is assumed
RT3003_GYRO_BIAS_SIGMA = math.radians(0.01)  # rad/s
RT3003_ACCEL_BIAS_SIGMA = 0.01  # m/s^2, about 1 mg: assumed


def normal_gravity_mps2(lat_deg: float, alt_m: float) -> float:
    """Gravity's magnitude at a latitude and height: WGS-84's normal gravity (Somigliana's formula)
    less 3.086e-6 m/s^2 a metre up (9.8095 at drive 0013's 49.01 degrees north, 114 m)."""
    s2 = math.sin(math.radians(lat_deg)) ** 2
    return 9.7803253359 * (1.0 + 0.00193185265241 * s2) / math.sqrt(1.0 - 0.00669437999013 * s2) - 3.086e-6 * alt_m


def oxts_imu_spec(rate_hz: float, T_body_imu: np.ndarray, gravity_mps2: float, source: Path | None = None) -> ImuSpec:
    """The rig's ``imu`` for a raw drive: the RT3003's noise figures (above), mounted at ``T_body_imu``."""
    return validated(
        ImuSpec,
        dict(
            part="OXTS RT3003 (noise densities and bias walks: gtsam's KITTI example; accelerometer bias at the start assumed)",
            rate_hz=rate_hz,
            T_body_imu=T_body_imu,
            gyro_noise_density=RT3003_GYRO_NOISE_DENSITY,
            accel_noise_density=RT3003_ACCEL_NOISE_DENSITY,
            gyro_bias_random_walk=RT3003_GYRO_BIAS_RANDOM_WALK,
            accel_bias_random_walk=RT3003_ACCEL_BIAS_RANDOM_WALK,
            gyro_bias_sigma=RT3003_GYRO_BIAS_SIGMA,
            accel_bias_sigma=RT3003_ACCEL_BIAS_SIGMA,
            gravity_mps2=gravity_mps2,
        ),
        source,
        "imu",
    )


class OxtsImu(NamedTuple):
    """A raw drive's inertial measurements, one per OXTS record, in the unit's frame."""

    t_s: np.ndarray  # (N,) the OXTS time stamps, seconds after the first
    gyro_rad_s: np.ndarray  # (N,3) wx wy wz
    accel_mps2: np.ndarray  # (N,3) ax ay az, specific force
    spec: ImuSpec


def _find_calib(drive: Path, name: str) -> Path:
    for folder in (drive, drive.parent):
        if (folder / name).is_file():
            return folder / name
    return drive.parent / name


RAW_CAMERAS = ("image_00", "image_01", "image_02", "image_03")  # grey left, grey right, colour left, colour right


def raw_cameras(drive: Path) -> list[int]:
    """The cameras a raw drive folder holds (those with a ``data`` folder), by number."""
    return [n for n, name in enumerate(RAW_CAMERAS) if (drive / name / "data").is_dir()]


def rectified_camera_from_cam0(P_rect: np.ndarray, T_rect0_x: np.ndarray) -> np.ndarray:
    """``T_camN_x`` for the rectified camera whose projection is ``P_rect`` (3x4, ``K [I | K t]``),
    from ``T_rect0_x`` in camera 0's rectified frame: a shift by ``t`` (the stereo baseline)."""
    t = np.linalg.solve(P_rect[:, :3], P_rect[:, 3])
    return make_pose(np.eye(3), t) @ T_rect0_x


_RAW_STREAMS = {"image": "camera", "velodyne": "laser", "oxts": "odometry"}  # the counters' stream names


def _skip_unordered_stamps(path: Path, stream: str, sec: np.ndarray, ns: np.ndarray, checks: InputChecks, counts: dict[str, int]) -> np.ndarray:
    """Mask of the lines of a raw drive's ``timestamps.txt`` kept: a stamp not after the one before
    it (a duplicate, a line out of order) costs its one file, with one warning and a count in ``counts``;
    the stream is refused when too many are (:class:`~dem_graph.datasets.checks.SkippedMessages`)."""
    t_s = (sec - sec[0]).astype(float) + (ns - ns[0]) * 1e-9 if len(sec) else np.zeros(0)
    keep = increasing_stamps(t_s)
    skipped = SkippedMessages(path, stream, item="line", first_number=1)
    kept_before = 0
    for i in range(len(t_s)):
        if keep[i]:
            kept_before = i
            continue
        before = f"line {kept_before + 1} kept before it: {_stamp_text(sec[kept_before], ns[kept_before])}" if keep[kept_before] else "no line kept before it"
        skipped.skip(i, STAMP_NOT_AFTER, f"{_stamp_text(sec[i], ns[i])}, {before}")
    skipped.finish(len(t_s), checks)
    counts.update(skipped.counts())
    return keep


def _stamp_text(sec: int, ns: int) -> str:
    """A raw drive's stamp as the file writes it, UTC to the nanosecond."""
    return datetime.fromtimestamp(int(sec), tz=timezone.utc).strftime("%Y-%m-%d %H:%M:%S") + f".{int(ns):09d}"


class KittiRawSequence(_KittiSequence):
    """A synced drive of the KITTI raw data (``DATE/DATE_drive_XXXX_sync``), calibration files in
    the drive folder or its parent. Ground truth and odometry from OXTS. ``camera``: which of
    :data:`RAW_CAMERAS` (0-3; default the first the drive holds). A line of a ``timestamps.txt``
    whose stamp is not after the line before it costs its one file (a warning, a count in
    :meth:`skipped_messages`); ``checks`` says when a stream has too many (None: the defaults).
    Other options as :class:`KittiOdometrySequence`'s."""

    layout = "kitti-raw"

    def open_options(self) -> dict:
        return {**super().open_options(), "camera": self.camera, "truth": self.truth}

    def skipped_messages(self) -> dict[str, int]:
        """The lines of the drive's ``timestamps.txt`` files skipped (stamps not after their predecessors'), by stream."""
        return dict(self._skipped)

    def __init__(
        self,
        drive: str | Path,
        ring: int | None = None,
        ground_distance_m: float = 10.0,
        azimuth_step_deg: float = 0.25,
        lidar_height_m: float = LIDAR_HEIGHT_M,
        odometry_spec: OdometrySpec | None = None,
        camera: int | None = None,
        truth: str | None = None,
        checks: InputChecks | None = None,
    ):
        drive = Path(drive)
        if not drive.is_dir():
            raise DatasetError(drive, "drive folder not found")
        self.truth = truth or RAW_TRUTHS[0]
        if self.truth not in RAW_TRUTHS:
            raise DatasetError(drive, f"unknown truth {self.truth!r}: a raw drive's trajectory is built from {' or '.join(RAW_TRUTHS)}")
        self.path = drive
        present = raw_cameras(drive)
        if not present:
            raise DatasetError(drive, f"no camera: a KITTI raw drive holds one of {', '.join(f'{c}/data' for c in RAW_CAMERAS)}")
        if camera is None:
            camera = present[0]
        elif camera not in present:
            raise DatasetError(drive / RAW_CAMERAS[camera] / "data", f"not found: camera {camera} is not in this drive (it holds camera {', '.join(map(str, present))})")
        self.camera = int(camera)
        image_folder = RAW_CAMERAS[self.camera]
        needed = [f"{f}/{part}" for f in (image_folder, "velodyne_points", "oxts") for part in ("data", "timestamps.txt")]
        missing = [n for n in needed if not (drive / n).exists()]
        missing += [n for n in ("calib_cam_to_cam.txt", "calib_velo_to_cam.txt", "calib_imu_to_velo.txt") if not _find_calib(drive, n).is_file()]
        if missing:
            raise DatasetError(drive, f"not a complete KITTI raw drive: {', '.join(missing)} not found (calibration files in the drive folder or its parent)")
        cam_path = _find_calib(drive, "calib_cam_to_cam.txt")
        velo_path = _find_calib(drive, "calib_velo_to_cam.txt")
        imu_path = _find_calib(drive, "calib_imu_to_velo.txt")
        cam = read_calib_file(cam_path)
        velo = read_calib_file(velo_path)
        imu = read_calib_file(imu_path)
        P_rect = _calib_matrix(cam, f"P_rect_0{self.camera}", (3, 4), cam_path)
        R_rect = make_pose(_calib_matrix(cam, "R_rect_00", (3, 3), cam_path), np.zeros(3))
        T_cam0_velo = make_pose(_calib_matrix(velo, "R", (3, 3), velo_path), _calib_matrix(velo, "T", (3, 1), velo_path)[:, 0])
        # calib_imu_to_velo.txt maps IMU coordinates to Velodyne coordinates
        T_velo_imu = make_pose(_calib_matrix(imu, "R", (3, 3), imu_path), _calib_matrix(imu, "T", (3, 1), imu_path)[:, 0])
        T_cam_lidar = rectified_camera_from_cam0(P_rect, nearest_pose(R_rect @ T_cam0_velo))

        streams = {}
        for key, folder, suffix in (("image", image_folder, ".png"), ("velodyne", "velodyne_points", ".bin"), ("oxts", "oxts", ".txt")):
            stamps_path = drive / folder / "timestamps.txt"
            files = _files(drive / folder / "data", suffix, f"{folder}/data")
            sec, ns = read_kitti_timestamps(stamps_path)
            if len(sec) != len(files):
                raise DatasetError(stamps_path, f"{len(sec)} time stamps but {len(files)} files in {folder}/data: they must match")
            if not files:
                raise DatasetError(drive / folder / "data", "no files")
            streams[key] = (files, sec, ns, stamps_path)
        sec0, ns0 = streams["oxts"][1][0], streams["oxts"][2][0]

        def rel(sec, ns):
            return (sec - sec0).astype(float) + (ns - ns0) * 1e-9

        t = {k: rel(v[1], v[2]) for k, v in streams.items()}
        self._skipped: dict[str, int] = {}
        for k, (files, sec, ns, stamps_path) in list(streams.items()):
            keep = _skip_unordered_stamps(stamps_path, _RAW_STREAMS[k], sec, ns, checks or InputChecks(), self._skipped)
            streams[k] = ([f for f, kept in zip(files, keep) if kept], sec[keep], ns[keep], stamps_path)
            t[k] = t[k][keep]
        oxts = _read_oxts(streams["oxts"][0])
        T_body_lidar = make_pose(np.eye(3), [0.0, 0.0, lidar_height_m])
        T_body_imu = T_body_lidar @ T_velo_imu
        T_world_imu = oxts_poses(oxts) if self.truth == "positions" else oxts_velocity_poses(t["oxts"], oxts)
        T_world_body = T_world_imu @ invert(T_body_imu)
        truth = Trajectory.from_poses(t["oxts"], nearest_pose(T_world_body))
        oxts_rate_hz = 1.0 / float(np.median(np.diff(t["oxts"]))) if len(t["oxts"]) > 1 else 10.0
        spec = odometry_spec or OdometrySpec(rate_hz=oxts_rate_hz)
        odometry = odometry_from_oxts(t["oxts"], oxts, T_body_imu, spec)
        imu_samples = OxtsImu(
            t["oxts"].copy(),
            oxts[:, OXTS_GYRO].copy(),
            oxts[:, OXTS_ACCEL].copy(),  # specific force already (see OXTS_ACCEL): unchanged
            # the odometry's T_body_imu, its rotation (given to 7 digits: 8e-8 from orthonormal on drive 0013) made exactly one
            oxts_imu_spec(oxts_rate_hz, nearest_pose(T_body_imu), normal_gravity_mps2(oxts[0, 0], oxts[0, 2]), imu_path),
        )
        t_start = float(t["oxts"][0])
        keep_img = t["image"] >= t_start
        keep_scan = t["velodyne"] >= t_start
        if not keep_img.all() or not keep_scan.all():
            log.info("KITTI raw: %d frames and %d scans before the first OXTS record left out", (~keep_img).sum(), (~keep_scan).sum())
        images = [f for f, k in zip(streams["image"][0], keep_img) if k]
        scans = [f for f, k in zip(streams["velodyne"][0], keep_scan) if k]
        if not images:
            raise DatasetError(drive / image_folder, "no image after the first OXTS record")
        first = _read_image(images[0])
        super().__init__(
            f"kitti-raw-{drive.name}",
            t["image"][keep_img],
            images,
            t["velodyne"][keep_scan],
            scans,
            T_cam_lidar,
            P_rect,
            (first.shape[1], first.shape[0]),
            truth,
            odometry,
            ring,
            ground_distance_m,
            azimuth_step_deg,
            lidar_height_m,
            truth.poses_se3[0],
            t_start,
            cam_path,
            imu_samples,
        )

    def __repr__(self) -> str:
        return f"KittiRawSequence({str(self.path)!r}, camera={self.camera}, frames={self.n_frames}, ring={self.ring}, truth={self.truth!r})"


def kitti_layout(path: str | Path) -> str | None:
    """``"kitti-odometry"``, ``"kitti-raw"`` or None, from the folder's layout."""
    path = Path(path)
    if (path / "sequences").is_dir() or ((path / "image_0").is_dir() and (path / "times.txt").exists()):
        return "kitti-odometry"
    # a raw drive: two of its three streams are enough to call it one, so that the reader names what is missing
    streams = [(path / "oxts").is_dir(), (path / "velodyne_points").is_dir(), any((path / c).is_dir() for c in RAW_CAMERAS)]
    if sum(streams) >= 2:
        return "kitti-raw"
    return None


def open_kitti(
    path: str | Path,
    layout: str | None = None,
    sequence: str | int | None = None,
    ring: int | None = None,
    ground_distance_m: float = 10.0,
    camera: int | None = None,
    truth: str | None = None,
) -> _KittiSequence:
    """Open a KITTI folder of either layout (``layout`` None: told from the folder); ``camera``: the
    raw layout's camera (0-3); ``truth``: what its true trajectory is built from (:data:`RAW_TRUTHS`)."""
    layout = layout or kitti_layout(path)
    if layout == "kitti-odometry":
        return KittiOdometrySequence(path, sequence, ring, ground_distance_m)
    if layout == "kitti-raw":
        return KittiRawSequence(path, ring, ground_distance_m, camera=camera, truth=truth)
    raise DatasetError(path, "not a KITTI folder (neither sequences/NN nor a raw drive with oxts, velodyne_points and a camera image_00 .. image_03)")


__all__ = [
    "KittiOdometrySequence",
    "RAW_CAMERAS",
    "RAW_TRUTHS",
    "KittiRawSequence",
    "OXTS_ACCEL",
    "OXTS_FIELDS",
    "OXTS_GYRO",
    "OxtsImu",
    "kitti_layout",
    "normal_gravity_mps2",
    "odometry_from_oxts",
    "open_kitti",
    "oxts_imu_spec",
    "oxts_poses",
    "oxts_twists",
    "oxts_velocity_poses",
    "read_calib_file",
    "read_kitti_timestamps",
    "raw_cameras",
    "rectified_camera_from_cam0",
]
