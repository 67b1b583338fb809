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

    def dark(self, points_board: np.ndarray, parity: int) -> np.ndarray:
        """Mask of the (N,2+) board-frame points on a dark square: square ``(i, j)``, its corner nearest the origin
        at ``(i, j) * square_m`` (``i`` from -1 to ``cols - 1``, ``j`` from -1 to ``rows - 1``), is dark when
        ``(i + j) % 2 == parity``."""
        i, j = np.floor(points_board[:, 0] / self.square_m), np.floor(points_board[:, 1] / self.square_m)
        inside = (i >= -1) & (i <= self.cols - 1) & (j >= -1) & (j <= self.rows - 1)
        return inside & ((i + j) % 2 == parity)

    def dark_probability(self, points_board: np.ndarray, parity: int, sigma_m: float) -> np.ndarray:
        """Probability that each (N,2+) board-frame point lies on a dark square when its position is known to
        ``sigma_m`` (one sigma, on each axis): the colour at the point, flipped with the probability of having
        crossed the nearest line between squares in x or in y (the white border counts as a flip too)."""
        from scipy.special import ndtr

        def crossed(c):
            f = np.mod(c / self.square_m, 1.0) * self.square_m
            return ndtr(-np.minimum(f, self.square_m - f) / max(sigma_m, 1e-12))

        px, py = crossed(points_board[:, 0]), crossed(points_board[:, 1])
        flip = px * (1.0 - py) + py * (1.0 - px)
        dark = self.dark(points_board, parity)
        return np.where(dark, 1.0 - flip, flip) * np.all(np.isfinite(points_board[:, :2]), axis=1)

    @property
    def squares(self) -> tuple[int, int]:
        """Squares per row and per column: one more than the inner corners."""
        return self.cols + 1, self.rows + 1

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
    dark_parity: int | None = None  # which squares are dark (see BoardSpec.dark); None when not known


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


def dark_parity(image: np.ndarray, obs: BoardObservation, board: BoardSpec, K: np.ndarray, distortion: np.ndarray, min_contrast_dn: float = 20.0) -> int | None:
    """Which squares of the board in ``image`` are dark (the parity of :meth:`BoardSpec.dark`): the mean grey level
    at the centres of the squares of each parity, the darker one; None when they differ by less than
    ``min_contrast_dn`` grey levels (a corner detector's ordering says nothing about colour)."""
    gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    i, j = np.meshgrid(np.arange(-1, board.cols), np.arange(-1, board.rows))
    centres = np.stack([(i.ravel() + 0.5), (j.ravel() + 0.5), np.zeros(i.size)], axis=1) * board.square_m
    rvec = cv2.Rodrigues(obs.T_cam_board[:3, :3])[0]
    uv, _ = cv2.projectPoints(centres, rvec, obs.T_cam_board[:3, 3], np.asarray(K, float), np.asarray(distortion, float))
    uv = uv.reshape(-1, 2)
    h, w = gray.shape
    seen = np.all(np.isfinite(uv), axis=1) & (uv[:, 0] >= 1) & (uv[:, 0] < w - 2) & (uv[:, 1] >= 1) & (uv[:, 1] < h - 2)
    uv = np.round(np.where(seen[:, None], uv, 0.0)).astype(int)
    if not np.any(seen):
        return None
    u, v = uv[seen, 0], uv[seen, 1]
    grey = np.mean([gray[v + dv, u + du] for dv in (-1, 0, 1) for du in (-1, 0, 1)], axis=0)  # 3x3 mean at each centre
    even = ((i.ravel() + j.ravel()) % 2 == 0)[seen]
    if not np.any(even) or np.all(even):
        return None
    mean_even, mean_odd = float(grey[even].mean()), float(grey[~even].mean())
    if abs(mean_even - mean_odd) < min_contrast_dn:
        return None
    return 0 if mean_even < mean_odd else 1


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
