"""Synthetic calibration recordings with known ``T_cam_laser``: a checkerboard at varied poses, the laser
crossing it, a room behind.

Everything is analytic: the laser's beams are cast against the board's rectangle and the walls of a box
room; images are rendered by casting each pixel's ray (through the lens distortion) at the board plane,
a few samples per pixel, with blur and grey-level noise. Corners can also be had directly as
the true projections plus Gaussian noise, which is what the accuracy tests use (no image needed).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import yaml

from dem_graph.calibration.board import BoardSpec
from dem_graph.calibration.readers import Intrinsics, ScanSet, write_opencv_intrinsics, write_radlocc_scans, write_times
from dem_graph.errors import DatasetError
from dem_graph.geometry.se3 import invert, make_pose, rotation_from_rpy, transform_points

# laser x forward along the camera's z, laser y to the camera's left (-x), laser z up (-y)
_R_CAM_LASER_NOMINAL = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])


def default_truth() -> np.ndarray:
    """A plausible ``T_cam_laser``: the scanner 12 cm below the camera, looking the same way, a little askew."""
    R = _R_CAM_LASER_NOMINAL @ rotation_from_rpy(np.radians(1.5), np.radians(-2.0), np.radians(0.8))
    return make_pose(R, [0.03, 0.12, -0.04])


def default_intrinsics() -> Intrinsics:
    K = np.array([[520.0, 0.0, 319.5], [0.0, 520.0, 239.5], [0.0, 0.0, 1.0]])
    return Intrinsics(K, np.array([-0.08, 0.05, 0.0, 0.0, 0.0]), 640, 480)


@dataclass(frozen=True)
class SimulatedCalibration:
    T_cam_laser: np.ndarray  # the truth
    intrinsics: Intrinsics
    board: BoardSpec
    T_cam_board: np.ndarray  # (V,4,4)
    corners_px: np.ndarray  # (V,N,2) true projections plus corner noise
    scans: ScanSet  # one scan per view
    image_times_s: np.ndarray
    corner_sigma_px: float
    range_sigma_m: float
    margin_m: float  # white border of the board around its squares
    T_cam_neighbour: np.ndarray | None = None  # (V,4,4) the panel beside the board, when simulated
    dark_bias_m: float = 0.0  # range bias of returns on dark squares
    dark_dropout: float = 0.0  # probability that a return on a dark square is lost


def _project(intrinsics: Intrinsics, points_cam: np.ndarray) -> np.ndarray:
    uv, _ = cv2.projectPoints(points_cam.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), intrinsics.K, intrinsics.distortion)
    return uv.reshape(-1, 2)


def _hit_rectangle(origin: np.ndarray, dirs: np.ndarray, T_cam_rect: np.ndarray, outline: tuple[float, float, float, float]) -> tuple[np.ndarray, np.ndarray]:
    """Ranges along unit ``dirs`` (camera frame) from ``origin`` to the rectangle ``outline`` (its frame's x, y
    limits) in the plane z = 0 of ``T_cam_rect`` (inf where missed), and the hits' (x, y) in that frame."""
    n, p0 = T_cam_rect[:3, 2], T_cam_rect[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        s = ((p0 - origin) @ n) / (dirs @ n)
        local = transform_points(invert(T_cam_rect), origin + s[:, None] * dirs)
    x0, x1, y0, y1 = outline
    hit = (s > 0) & (local[:, 0] >= x0) & (local[:, 0] <= x1) & (local[:, 1] >= y0) & (local[:, 1] <= y1)
    return np.where(hit, s, np.inf), local[:, :2]


def _cast(origin: np.ndarray, dirs: np.ndarray, T_cam_board: np.ndarray, board: BoardSpec, margin_m: float, room_half_m: np.ndarray) -> np.ndarray:
    """Ranges along unit ``dirs`` (camera frame) from ``origin``: the board if hit, else the room's walls."""
    s, _ = _hit_rectangle(origin, dirs, T_cam_board, board.outline(margin_m))
    with np.errstate(divide="ignore", invalid="ignore"):
        # box room centred on the camera: exit distance along each axis
        walls = np.min(np.where(np.abs(dirs) > 1e-12, (room_half_m * np.sign(dirs) - origin) / dirs, np.inf), axis=1)
    return np.where(np.isfinite(s), s, walls)


DARK_PARITY = 0  # the simulated boards' dark squares (BoardSpec.dark)

POSE_PROTOCOLS = ("random", "guided")


def _random_board_pose(
    rng: np.random.Generator, T_cam_laser: np.ndarray, board: BoardSpec, protocol: str = "random", distance_m: tuple[float, float] = (0.9, 2.0)
) -> np.ndarray:
    """A board pose whose centre lies near the laser plane, ``distance_m`` ahead (0.9-2.0 m) and up to 20 degrees to either side.

    ``random``: tilted forward or back by up to 52 degrees and turned sideways by up to 40, uniformly (many
    views nearly upright). ``guided``: as docs/calibration.md asks a person recording to hold it, tilted
    forward or back by 34-57 degrees and turned sideways by 17-40. Both roll the board in its plane by up to
    29 degrees. The board frame: x right, y down, z away from the camera.
    """
    if protocol not in POSE_PROTOCOLS:
        raise ValueError(f"unknown board pose protocol {protocol!r}; one of {', '.join(POSE_PROTOCOLS)}")
    theta = rng.uniform(-0.35, 0.35)
    rho = rng.uniform(*distance_m)
    height = 0.12 * min(1.0, (board.rows - 1) * board.square_m / 0.45)  # the laser crosses the board away from its edges
    centre = transform_points(T_cam_laser, np.array([[rho * np.cos(theta), rho * np.sin(theta), rng.uniform(-height, height)]]))[0]
    if protocol == "random":
        tilt_rad, turn_rad = rng.uniform(-0.9, 0.9), rng.uniform(-0.7, 0.7)
    else:
        tilt_rad = rng.choice([-1.0, 1.0]) * rng.uniform(0.6, 1.0)
        turn_rad = rng.choice([-1.0, 1.0]) * rng.uniform(0.3, 0.7)
    R = rotation_from_rpy(tilt_rad, turn_rad, rng.uniform(-0.5, 0.5))
    half = 0.5 * np.array([(board.cols - 1) * board.square_m, (board.rows - 1) * board.square_m, 0.0])
    return make_pose(R, centre - R @ half)


def _neighbour_pose(rng: np.random.Generator, T_cam_board: np.ndarray, board: BoardSpec, margin_m: float) -> np.ndarray:
    """A panel (:data:`NEIGHBOUR_OUTLINE_M` in its frame) parallel to the board, 3-8 cm beside its outline on
    the left or the right and 1-4 cm behind its plane: returns that fixed tolerances count as the board's."""
    x0, x1, y0, y1 = board.outline(margin_m)
    gap, behind = rng.uniform(0.03, 0.08), rng.uniform(0.01, 0.04)
    width = NEIGHBOUR_OUTLINE_M[1]
    x = x1 + gap if rng.random() < 0.5 else x0 - gap - width
    y = 0.5 * (y0 + y1) - 0.5 * NEIGHBOUR_OUTLINE_M[3]
    return T_cam_board @ make_pose(np.eye(3), [x, y, behind])


NEIGHBOUR_OUTLINE_M = (0.0, 0.3, 0.0, 0.3)


def simulate_calibration(
    seed: int = 0,
    n_views: int = 15,
    corner_sigma_px: float = 0.3,
    range_sigma_m: float = 0.02,
    board: BoardSpec | None = None,
    T_cam_laser: np.ndarray | None = None,
    intrinsics: Intrinsics | None = None,
    angle_increment_rad: float = np.radians(0.25),
    margin_m: float = 0.05,
    pose_protocol: str = "random",
    dark_dropout: float = 0.0,
    dark_bias_m: float = 0.0,
    neighbour: bool = False,
    distance_m: tuple[float, float] | None = None,
) -> SimulatedCalibration:
    """``n_views`` views whose whole board is in the image and is crossed by at least 15 beams;
    ``pose_protocol`` is how the board is held (see :func:`_random_board_pose`).

    What real scanners and rooms add: a return on a dark square is lost with probability ``dark_dropout``
    and, when kept, reads ``dark_bias_m`` too far; ``neighbour`` puts a panel beside the board in every view
    (:func:`_neighbour_pose`). The board is held ``distance_m`` from the laser [default: 0.9-2.0 m for a board
    of the default's size, scaled down with the board's diagonal to 0.45 of that]."""
    rng = np.random.default_rng(seed)
    board = board or BoardSpec(9, 6, 0.09)
    T = default_truth() if T_cam_laser is None else np.asarray(T_cam_laser, dtype=float)
    intr = intrinsics or default_intrinsics()
    if distance_m is None:
        scale = float(np.clip(board.diagonal_m / BoardSpec(9, 6, 0.09).diagonal_m, 0.45, 1.0))
        distance_m = (0.9 * scale, 2.0 * scale)
    n_beams = int(round(np.radians(180.0) / angle_increment_rad)) + 1
    angles = -np.pi / 2 + angle_increment_rad * np.arange(n_beams)
    dirs_laser = np.stack([np.cos(angles), np.sin(angles), np.zeros(n_beams)], axis=1)
    dirs_cam = dirs_laser @ T[:3, :3].T
    room = np.array([3.0, 2.0, 5.0])
    poses, neighbours, corners, ranges = [], [], [], []
    while len(poses) < n_views:
        T_cb = _random_board_pose(rng, T, board, pose_protocol, distance_m)
        pts = transform_points(T_cb, board.corners_board)
        if np.any(pts[:, 2] < 0.3) or T_cb[2, 2] < 0.3:
            continue
        uv = _project(intr, pts)
        if np.any(uv < 15) or np.any(uv[:, 0] > intr.width_px - 16) or np.any(uv[:, 1] > intr.height_px - 16):
            continue
        r = _cast(T[:3, 3], dirs_cam, T_cb, board, margin_m, room)
        s_board, xy_board = _hit_rectangle(T[:3, 3], dirs_cam, T_cb, board.outline(margin_m))
        on_board = np.isfinite(s_board)
        if on_board.sum() < 15:
            continue
        T_cn = _neighbour_pose(rng, T_cb, board, margin_m) if neighbour else None
        if T_cn is not None:
            s_n, _ = _hit_rectangle(T[:3, 3], dirs_cam, T_cn, NEIGHBOUR_OUTLINE_M)
            r = np.where(~on_board & (s_n < r), s_n, r)
        corners.append(uv + corner_sigma_px * rng.standard_normal(uv.shape))  # drawn first: seeds keep their recordings
        noisy = r + range_sigma_m * rng.standard_normal(len(r))
        dark = on_board & board.dark(xy_board, DARK_PARITY)
        noisy = np.where(dark, noisy + dark_bias_m, noisy)
        if dark_dropout > 0:
            noisy[dark & (rng.random(len(r)) < dark_dropout)] = np.nan
        poses.append(T_cb)
        neighbours.append(T_cn)
        ranges.append(noisy)
    times = 1.0 + 2.0 * np.arange(n_views)
    scans = ScanSet(times + rng.uniform(-0.01, 0.01, n_views), float(angles[0]), float(angle_increment_rad), np.asarray(ranges))
    return SimulatedCalibration(
        T, intr, board, np.asarray(poses), np.asarray(corners), scans, times, corner_sigma_px, range_sigma_m, margin_m,
        np.asarray(neighbours) if neighbour else None, dark_bias_m, dark_dropout,
    )


def render_board_image(sim: SimulatedCalibration, view: int, rng: np.random.Generator, noise_dn: float = 2.0, samples: int = 3) -> np.ndarray:
    """A grey 8-bit image of view ``view``: the board (black squares, white border) before a grey background."""
    intr = sim.intrinsics
    h, w = intr.height_px, intr.width_px
    offsets = (np.arange(samples) + 0.5) / samples - 0.5
    v, u = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
    shape = (h, w, samples, samples)
    uu = np.broadcast_to(u[..., None, None] + offsets[:, None], shape).ravel()
    vv = np.broadcast_to(v[..., None, None] + offsets[None, :], shape).ravel()
    xy = cv2.undistortPoints(np.stack([uu, vv], axis=1).reshape(-1, 1, 2), intr.K, intr.distortion).reshape(-1, 2)
    rays = np.column_stack([xy, np.ones(len(xy))])
    s_board, xy = _hit_rectangle(np.zeros(3), rays, sim.T_cam_board[view], sim.board.outline(sim.margin_m))
    value = np.where(sim.board.dark(xy, DARK_PARITY), 25.0, 225.0)
    background = 110.0 + 20.0 * np.sin(0.02 * uu)
    if sim.T_cam_neighbour is not None:
        s_n, _ = _hit_rectangle(np.zeros(3), rays, sim.T_cam_neighbour[view], NEIGHBOUR_OUTLINE_M)
        background = np.where(np.isfinite(s_n), 160.0, background)
    value = np.where(np.isfinite(s_board), value, background)
    img = value.reshape(h, w, samples * samples).mean(axis=2)
    img = cv2.GaussianBlur(img, (0, 0), 0.6) + noise_dn * rng.standard_normal(img.shape)
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


def write_recording(sim: SimulatedCalibration, out_dir: str | Path, seed: int = 0, samples: int = 2) -> Path:
    """Write ``sim`` in the RADLOCC layout :func:`~dem_graph.calibration.readers.read_radlocc_recording` reads,
    with ``truth.yaml`` (the true ``T_cam_laser`` and the noise figures) beside ``data/`` and ``xml/``."""
    out = Path(out_dir)
    data, xml = out / "data", out / "xml"
    try:
        data.mkdir(parents=True, exist_ok=True)
        xml.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise DatasetError(out, f"cannot create the recording folder ({exc.strerror or exc})") from None
    rng = np.random.default_rng(seed + 7919)
    for k in range(len(sim.T_cam_board)):
        path = data / f"RGB{k + 1}.png"
        if not cv2.imwrite(str(path), render_board_image(sim, k, rng, samples=samples)):
            raise DatasetError(path, "cannot write the image")
    write_times(sim.image_times_s, data / "camera.txt")
    write_radlocc_scans(sim.scans, data / "laser.txt")
    write_opencv_intrinsics(sim.intrinsics, sim.board, xml / "out_camera_data.xml")
    truth = {
        "T_cam_laser": np.asarray(sim.T_cam_laser).tolist(),
        "range_sigma_m": sim.range_sigma_m,
        "dark_bias_m": sim.dark_bias_m,
        "dark_dropout": sim.dark_dropout,
        "neighbour": sim.T_cam_neighbour is not None,
        "views": len(sim.T_cam_board),
        "board": {"cols": sim.board.cols, "rows": sim.board.rows, "square_m": sim.board.square_m, "margin_m": sim.margin_m},
    }
    (out / "truth.yaml").write_text(yaml.safe_dump(truth, sort_keys=False, default_flow_style=None))
    return out
