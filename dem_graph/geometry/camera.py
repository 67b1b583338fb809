"""Pinhole camera with OpenCV's radial-tangential distortion (k1, k2, p1, p2, k3).

Pixel coordinates follow OpenCV: integer ``(u, v)`` is the centre of pixel column u, row v.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np


@dataclass(frozen=True)
class PinholeCamera:
    width_px: int
    height_px: int
    fx_px: float
    fy_px: float
    cx_px: float
    cy_px: float
    distortion: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)
    _cache: dict = field(default_factory=dict, init=False, repr=False, compare=False, hash=False)

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx_px, 0.0, self.cx_px], [0.0, self.fy_px, self.cy_px], [0.0, 0.0, 1.0]])

    @property
    def dist_coeffs(self) -> np.ndarray:
        return np.asarray(self.distortion, dtype=float)

    @property
    def intrinsics_array(self) -> np.ndarray:
        """``fx, fy, cx, cy, k1, k2, p1, p2, k3`` (pixels; OpenCV's distortion), for the compiled kernels."""
        return np.array([self.fx_px, self.fy_px, self.cx_px, self.cy_px, *self.distortion], dtype=float)

    @property
    def has_distortion(self) -> bool:
        return bool(np.any(self.dist_coeffs != 0.0))

    def distort_normalized(self, xy: np.ndarray) -> np.ndarray:
        """Apply the distortion model to (N,2) normalized image coordinates."""
        k1, k2, p1, p2, k3 = self.distortion
        x, y = xy[:, 0], xy[:, 1]
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
        yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
        return np.stack([xd, yd], axis=1)

    def project(self, points_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Project (N,3) camera-frame points to pixels.

        Returns ``(uv_px, in_front)``: (N,2) pixel coordinates and a mask of points with z > 0.
        Points behind the camera get NaN coordinates.
        """
        p = np.atleast_2d(np.asarray(points_cam, dtype=float))
        in_front = p[:, 2] > 1e-9
        z = np.where(in_front, p[:, 2], np.nan)
        xy = p[:, :2] / z[:, None]
        if self.has_distortion:
            xy = self.distort_normalized(xy)
        uv = np.stack([self.fx_px * xy[:, 0] + self.cx_px, self.fy_px * xy[:, 1] + self.cy_px], axis=1)
        return uv, in_front

    def project_with_jacobian(self, points_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`project` plus the (N,2,3) Jacobian of the pixel coordinates w.r.t. the camera-frame point."""
        p = np.atleast_2d(np.asarray(points_cam, dtype=float))
        in_front = p[:, 2] > 1e-9
        z = np.where(in_front, p[:, 2], np.nan)
        x, y = p[:, 0] / z, p[:, 1] / z
        # d(x, y)/d(p): [[1/z, 0, -x/z], [0, 1/z, -y/z]]
        J_xy_p = np.zeros((len(p), 2, 3))
        J_xy_p[:, 0, 0] = 1.0 / z
        J_xy_p[:, 0, 2] = -x / z
        J_xy_p[:, 1, 1] = 1.0 / z
        J_xy_p[:, 1, 2] = -y / z
        k1, k2, p1, p2, k3 = self.distortion
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        d_radial = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)  # d radial / d r2
        xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
        yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
        J_d = np.empty((len(p), 2, 2))
        J_d[:, 0, 0] = radial + 2.0 * x * x * d_radial + 2.0 * p1 * y + 6.0 * p2 * x
        J_d[:, 0, 1] = 2.0 * x * y * d_radial + 2.0 * p1 * x + 2.0 * p2 * y
        J_d[:, 1, 0] = 2.0 * x * y * d_radial + 2.0 * p1 * x + 2.0 * p2 * y
        J_d[:, 1, 1] = radial + 2.0 * y * y * d_radial + 6.0 * p1 * y + 2.0 * p2 * x
        J_d[:, 0, :] *= self.fx_px
        J_d[:, 1, :] *= self.fy_px
        uv = np.stack([self.fx_px * xd + self.cx_px, self.fy_px * yd + self.cy_px], axis=1)
        return uv, J_d @ J_xy_p, in_front

    def in_image(self, uv_px: np.ndarray, margin_px: float = 0.0) -> np.ndarray:
        """Mask of pixel coordinates at least ``margin_px`` inside the image."""
        u, v = uv_px[:, 0], uv_px[:, 1]
        with np.errstate(invalid="ignore"):
            return (
                (u >= margin_px - 0.5)
                & (u <= self.width_px - 0.5 - margin_px)
                & (v >= margin_px - 0.5)
                & (v <= self.height_px - 0.5 - margin_px)
            )

    def normalized_from_pixels(self, uv_px: np.ndarray) -> np.ndarray:
        """Undistorted normalized coordinates (x/z, y/z) of (N,2) pixels."""
        uv = np.ascontiguousarray(np.asarray(uv_px, dtype=np.float64).reshape(-1, 1, 2))
        if not self.has_distortion:
            xy = (uv.reshape(-1, 2) - [self.cx_px, self.cy_px]) / [self.fx_px, self.fy_px]
            return xy
        criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)
        return getattr(cv2, "undistortPointsIter", cv2.undistortPoints)(uv, self.K, self.dist_coeffs, R=None, P=None, criteria=criteria).reshape(-1, 2)  # OpenCV 5 folded undistortPointsIter into undistortPoints

    def bearings_from_pixels(self, uv_px: np.ndarray) -> np.ndarray:
        """Unit viewing directions (camera frame) of (N,2) pixels."""
        xy = self.normalized_from_pixels(uv_px)
        d = np.concatenate([xy, np.ones((len(xy), 1))], axis=1)
        return d / np.linalg.norm(d, axis=1, keepdims=True)

    def pixel_bearings(self) -> np.ndarray:
        """(H*W, 3) unit viewing directions through every pixel centre, row-major; cached."""
        if "bearings" not in self._cache:
            u, v = np.meshgrid(np.arange(self.width_px, dtype=float), np.arange(self.height_px, dtype=float))
            self._cache["bearings"] = self.bearings_from_pixels(np.stack([u.ravel(), v.ravel()], axis=1))
        return self._cache["bearings"]
