"""The checkerboard: its corners in an image, its pose, and its plane in the camera frame with a covariance.

The board frame has x along a row of inner corners, y along a column, z out of the board; corner ``(i, j)``
(column ``i``, row ``j``) sits at ``(i * square_m, j * square_m, 0)``, in the order OpenCV's detector
returns them. The plane is ``n_cam . X = d_m`` with ``n_cam`` a unit vector pointing away from the camera.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from dem_graph.geometry.se3 import make_pose


@dataclass(frozen=True)
class BoardSpec:
    """A checkerboard: inner corners per row (``cols``) and per column (``rows``), square side in metres."""

    cols: int
    rows: int
    square_m: float

    @property
    def corners_board(self) -> np.ndarray:
        """(cols*rows, 3) inner corners in the board frame, row by row."""
        i, j = np.meshgrid(np.arange(self.cols), np.arange(self.rows))
        return np.stack([i.ravel(), j.ravel(), np.zeros(i.size)], axis=1) * self.square_m

    def outline(self, margin_m: float = 0.0) -> tuple[float, float, float, float]:
        """``x_min, x_max, y_min, y_max`` (board frame, metres) of the squares' area grown by ``margin_m``."""
        sq = self.square_m
        return (-sq - margin_m, self.cols * sq + margin_m, -sq - margin_m, self.rows * sq + margin_m)

    def contains(self, points_board: np.ndarray, margin_m: float = 0.0) -> np.ndarray:
        """Mask of the (N,3) board-frame points whose x, y lie within :meth:`outline`."""
        x0, x1, y0, y1 = self.outline(margin_m)
        x, y = points_board[:, 0], points_board[:, 1]
        return (x >= x0) & (x <= x1) & (y >= y0) & (y <= y1)

    @property
    def diagonal_m(self) -> float:
        """Diagonal of the squares' area ((cols+1) x (rows+1) squares)."""
        return float(np.hypot(self.cols + 1, self.rows + 1) * self.square_m)


@dataclass(frozen=True)
class BoardObservation:
    """The board seen in one image: corners, pose, plane and the plane's covariance."""

    corners_px: np.ndarray  # (N,2)
    T_cam_board: np.ndarray  # 4x4
    n_cam: np.ndarray  # (3,) unit normal, away from the camera
    d_m: float  # n_cam . X = d_m on the board
    plane_covariance: np.ndarray  # 4x4 covariance of [n_cam, d_m] from the corner noise
    reprojection_rms_px: float
    sigma_px: float  # corner noise used for the covariance


def detect_corners(image: np.ndarray, board: BoardSpec) -> np.ndarray | None:
    """(N,2) inner corners refined to sub-pixel, or None when the whole board is not found."""
    gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
    found, corners = cv2.findChessboardCorners(gray, (board.cols, board.rows), flags=flags)
    if not found:
        return None
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-3)
    corners = cv2.cornerSubPix(gray, corners, (5, 5), (-1, -1), criteria)
    return corners.reshape(-1, 2).astype(float)


def _plane(rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    R = cv2.Rodrigues(np.asarray(rvec, dtype=float).reshape(3, 1))[0]
    n = R[:, 2]
    return np.append(n, n @ np.asarray(tvec, dtype=float).ravel())


def board_from_corners(corners_px: np.ndarray, board: BoardSpec, K: np.ndarray, distortion: np.ndarray, sigma_px: float | None = None) -> BoardObservation:
    """The board's pose and plane from its corners (``cv2.solvePnP``), with the plane's covariance from the
    Jacobian of the corners' projection: ``sigma_px`` per coordinate, or, when None, the noise the
    reprojection residuals show."""
    corners_px = np.asarray(corners_px, dtype=float).reshape(-1, 2)
    obj = board.corners_board
    K, dist = np.asarray(K, dtype=float), np.asarray(distortion, dtype=float)
    ok, rvec, tvec = cv2.solvePnP(obj, corners_px, K, dist, flags=cv2.SOLVEPNP_ITERATIVE)
    rvec, tvec = cv2.solvePnPRefineLM(obj, corners_px, K, dist, rvec, tvec)
    projected, jac = cv2.projectPoints(obj, rvec, tvec, K, dist)
    residual = projected.reshape(-1, 2) - corners_px
    rms = float(np.sqrt(np.mean(np.sum(residual**2, axis=1))))
    if sigma_px is None:
        sigma_px = float(np.sqrt(np.sum(residual**2) / max(residual.size - 6, 1)))
    J = jac[:, :6]  # d(uv)/d(rvec, tvec)
    pose_cov = sigma_px**2 * np.linalg.inv(J.T @ J)
    x0 = np.concatenate([rvec.ravel(), tvec.ravel()])
    G = np.zeros((4, 6))
    for k in range(6):  # the plane's derivative by central differences (it is smooth and cheap)
        step = np.zeros(6)
        step[k] = 1e-6
        G[:, k] = (_plane(*np.split(x0 + step, 2)) - _plane(*np.split(x0 - step, 2))) / 2e-6
    plane = _plane(rvec, tvec)
    sign = 1.0 if plane[3] >= 0 else -1.0
    T = make_pose(cv2.Rodrigues(rvec)[0], tvec.ravel())
    return BoardObservation(corners_px, T, sign * plane[:3], float(sign * plane[3]), G @ pose_cov @ G.T, rms, float(sigma_px))
