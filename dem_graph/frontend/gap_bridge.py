"""Across a camera gap: the motion between the images on either side of it, refined by the images.

When the camera is silent for a while (a blackout, dropped frames), the live points, all within a
few metres ahead, have left the view by the time images return: nothing ties the poses after the
gap to the map before it but the motion model. Wheel odometry keeps the distance well, and its
attitude badly (a degree or more of pitch over a metre or two), and the pitch error then lifts or
sinks everything mapped after the gap.

The ground farther ahead (and what stands above it) is seen in both images. :class:`GapBridge`
keeps the last image with texture; on the first frame after a gap it tracks corners of that image
into the new one (pyramidal Lucas-Kanade from the motion model's prediction, checked backwards)
and refines the motion model's increment ``(U, Q)`` by those matches' epipolar (Sampson) errors,
with the increment as the prior: a two-view measurement of the rotation and of the direction of
travel, whose scale stays the odometry's. The result is the increment every estimator then
predicts with, so GM, PTPM and the graph take it the same way, and its covariance carries the
correlations. A bridge that finds too few matches, or a correction the increment's covariance
rules out, is refused with a warning and the increment is used as it was.
"""

from __future__ import annotations

import logging
import math
from collections import Counter
from dataclasses import dataclass, field

import cv2
import numpy as np
from pydantic import Field
from scipy.linalg import cho_factor, cho_solve, solve_triangular
from scipy.optimize import least_squares

from dem_graph.config_types import StrictModel
from dem_graph.geometry.camera import PinholeCamera
from dem_graph.geometry.lie import compose_increments, retract, skew
from dem_graph.geometry.se3 import invert

log = logging.getLogger(__name__)

_FAR_M = 200.0  # corners are taken where the ground plane is nearer than this (the homography holds there), metres


class GapBridgeConfig(StrictModel):
    """Settings of :class:`GapBridge`."""

    enabled: bool = Field(True, description="refine the motion across a camera gap by the images on either side of it")
    after_frames: float = Field(4.0, gt=1, description="a frame more than this many camera periods after the last frame with texture is after a gap")
    max_corners: int = Field(400, ge=8, description="corners taken from the image before the gap")
    min_corner_spacing_px: float = Field(12.0, gt=0, description="least distance between two corners, pixels")
    min_inliers: int = Field(25, ge=6, description="fewest consistent matches the refinement needs")
    sigma_px: float = Field(0.5, gt=0, description="least standard deviation of a match's epipolar error, pixels (the residuals' own spread when larger)")
    outlier_px: float = Field(2.0, gt=0, description="a match whose epipolar error exceeds this after the robust fit is an outlier, pixels")
    max_correction_chi2: float = Field(
        40.0, gt=0, description="refuse a correction whose Mahalanobis distance squared under the increment's covariance exceeds this (6 dof)"
    )


@dataclass
class BridgeReport:
    """What one bridge did: matches tracked and kept, the matches' noise, and the correction."""

    n_tracked: int
    n_inliers: int
    sigma_px: float
    correction: np.ndarray  # (6,) right perturbation of the increment, [rot rad, trans m]
    chi2: float


@dataclass
class GapBridge:
    """Feed it every frame: :meth:`refine` with the frame's increment when it begins, :meth:`remember`
    when it is done. A gap is time without a frame with texture: frames that did not come, and frames
    that came without texture (black, or frozen), whose increments it composes meanwhile."""

    config: GapBridgeConfig
    camera: PinholeCamera
    T_body_cam: np.ndarray
    frame_rate_hz: float
    counters: Counter = field(default_factory=Counter)
    last_report: BridgeReport | None = None
    _last_image: np.ndarray | None = None  # the last frame with texture, as it came (made grey only when a gap needs it)
    _last_t_s: float | None = None  # its time
    # the motion since it over the frames without texture that followed it, and its covariance
    _U_dark: np.ndarray = field(default_factory=lambda: np.eye(4))
    _Q_dark: np.ndarray = field(default_factory=lambda: np.zeros((6, 6)))

    def remember(self, t_s: float, image: np.ndarray, textureless: bool) -> None:
        """The frame just processed: the next gap starts from it if it had texture."""
        if textureless and self._last_t_s is not None:
            return
        self._last_t_s = float(t_s)
        self._last_image = None if textureless else image
        self._U_dark, self._Q_dark = np.eye(4), np.zeros((6, 6))

    @property
    def last_t_s(self) -> float | None:
        """The time of the last frame with texture (None before the first)."""
        return self._last_t_s

    def frames_missed(self, t_s: float) -> int:
        """The camera periods a gap before a frame at ``t_s`` swallowed since the last frame with
        texture: 0 unless the frame comes more than ``after_frames`` periods after it."""
        if self._last_t_s is None:
            return 0
        periods = int(round((t_s - self._last_t_s) * self.frame_rate_hz))  # whole periods: a timestamp's jitter is no frame
        return periods - 1 if periods > self.config.after_frames else 0

    def after_gap(self, t_s: float) -> bool:
        """Whether a frame at ``t_s`` comes after a gap the bridge can span (it starts at a frame with texture)."""
        return self.config.enabled and self._last_image is not None and self.frames_missed(t_s) > 0

    def refine(self, t_s: float, image: np.ndarray, textureless: bool, U: np.ndarray, Q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The increment ``T_prev_curr`` ``U`` (covariance ``Q``, right perturbation [rot, trans])
        since the previous frame, refined by the images on either side when a gap ends at this frame
        (one with texture); else as given.

        After frames without texture, the motion refined is the whole gap's (their increments and
        this one) and its correction ``Exp(xi)`` is applied to this frame's increment; the covariance
        returned is then this frame's own, since the estimator has already taken the dark frames'
        (conservative: it keeps their growth)."""
        self.last_report = None
        if textureless:
            if self._last_image is not None:
                self._U_dark, self._Q_dark = compose_increments(self._U_dark, self._Q_dark, U, Q)
            return U, Q
        if not self.after_gap(t_s):
            return U, Q
        gap_s = t_s - float(self._last_t_s)
        dark = bool(np.any(self._Q_dark))
        U_gap, Q_gap = compose_increments(self._U_dark, self._Q_dark, U, Q) if dark else (U, Q)
        try:
            refined = self._refine(_grey(image), U_gap, Q_gap)
        except (cv2.error, np.linalg.LinAlgError, ValueError) as exc:  # a degenerate image pair: the increment stands
            refined = f"the refinement failed ({exc})"
        if isinstance(refined, str):
            self.counters["gap_bridge_refused"] += 1
            log.warning("camera gap of %.2f s before the frame at %.3f s: %s; the motion model's increment bridges it unrefined", gap_s, t_s, refined)
            return U, Q
        U_new, Q_new, report = refined
        self.last_report = report
        self.counters["gap_bridged"] += 1
        log.info(
            "camera gap of %.2f s before the frame at %.3f s bridged by %d of %d matches (%.2f px): rotation corrected by %.2f deg",
            gap_s, t_s, report.n_inliers, report.n_tracked, report.sigma_px, math.degrees(float(np.linalg.norm(report.correction[:3]))),
        )
        if dark:
            return retract(U, report.correction), Q
        return U_new, Q_new

    # --- the two-view refinement -------------------------------------------------------------
    def _refine(self, image: np.ndarray, U: np.ndarray, Q: np.ndarray) -> tuple[np.ndarray, np.ndarray, BridgeReport] | str:
        """The increment ``U`` (covariance ``Q``) refined by the image pair, with its covariance and
        what was done; or why it was refused (one clause)."""
        cfg = self.config
        uv0, uv1 = self._matches(image, U)
        n_tracked = len(uv0)
        if n_tracked < cfg.min_inliers:
            return f"{n_tracked} corners tracked across it, fewer than gap_bridge.min_inliers = {cfg.min_inliers}"
        x0 = _homogeneous(self.camera.normalized_from_pixels(uv0))
        x1 = _homogeneous(self.camera.normalized_from_pixels(uv1))
        Q = 0.5 * (Q + Q.T)
        L = np.linalg.cholesky(Q)  # the prior's whitening: r = L^-1 xi
        f_px = 0.5 * (self.camera.fx_px + self.camera.fy_px)

        def residuals(xi, x0, x1, sigma_px):
            e_px = f_px * self._sampson(retract(U, xi), x0, x1)
            return np.concatenate([e_px / sigma_px, solve_triangular(L, xi, lower=True)])

        # a robust fit from the increment, then the inliers' least squares at their own noise
        fit = least_squares(residuals, np.zeros(6), args=(x0, x1, cfg.sigma_px), loss="huber", f_scale=2.0, x_scale="jac")
        e_px = f_px * self._sampson(retract(U, fit.x), x0, x1)
        inlier = np.abs(e_px) <= cfg.outlier_px
        n_in = int(inlier.sum())
        if n_in < cfg.min_inliers:
            return f"{n_in} of {n_tracked} tracked corners agree on the motion, fewer than gap_bridge.min_inliers = {cfg.min_inliers}"
        x0, x1 = x0[inlier], x1[inlier]
        sigma = max(cfg.sigma_px, 1.4826 * float(np.median(np.abs(e_px[inlier]))))
        fit = least_squares(residuals, fit.x, args=(x0, x1, sigma), x_scale="jac")
        xi = fit.x
        chi2 = float(xi @ cho_solve(cho_factor(Q), xi))
        if not np.isfinite(chi2) or chi2 > cfg.max_correction_chi2:
            return (
                f"the images call for a correction of {math.degrees(float(np.linalg.norm(xi[:3]))):.2f} deg and {float(np.linalg.norm(xi[3:])):.3f} m, "
                f"beyond the increment's covariance (chi2 {chi2:.1f} > gap_bridge.max_correction_chi2 = {cfg.max_correction_chi2:g})"
            )
        J = fit.jac
        Q_new = np.linalg.inv(J.T @ J)
        U_new = retract(U, xi)
        # the covariance of the right perturbation at U_new (first order: the same, the step being small)
        return U_new, 0.5 * (Q_new + Q_new.T), BridgeReport(n_tracked, n_in, sigma, xi, chi2)

    def _sampson(self, U: np.ndarray, x0: np.ndarray, x1: np.ndarray) -> np.ndarray:
        """Signed Sampson distances (normalized image units) of the matches ``x0 <-> x1`` (homogeneous,
        (n,3)) under the body motion ``U``: ``E = [t]x R`` with ``X_cam0 = R X_cam1 + t``."""
        T_c0_c1 = invert(self.T_body_cam) @ U @ self.T_body_cam
        R, t = T_c0_c1[:3, :3], T_c0_c1[:3, 3]
        E = skew(t) @ R
        Ex1 = x1 @ E.T
        Etx0 = x0 @ E
        num = np.einsum("ni,ni->n", x0, Ex1)
        den = np.sqrt(Ex1[:, 0] ** 2 + Ex1[:, 1] ** 2 + Etx0[:, 0] ** 2 + Etx0[:, 1] ** 2) + 1e-15
        return num / den

    def _matches(self, image: np.ndarray, U: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Matches between the image before the gap and ``image``: pixels in the first (n,2) and in
        the second (n,2). The first image is warped into the second's view by the homography the
        motion ``U`` induces on the body frame's ground plane before the gap, so that the ground
        looks as it does in ``image``; corners of ``image`` are tracked into the warped image
        (pyramidal Lucas-Kanade, kept when tracking back returns within a pixel) and carried back
        through the homography."""
        cfg = self.config
        prev = _grey(self._last_image)
        H = self._ground_homography(U)  # first image's pixels -> second image's
        h, w = image.shape[:2]
        warped = cv2.warpPerspective(prev, H, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        valid = cv2.warpPerspective(np.full(prev.shape[:2], 255, np.uint8), H, (w, h), flags=cv2.INTER_NEAREST, borderValue=0)
        mask = cv2.erode(valid, np.ones((25, 25), np.uint8)) & self._below_horizon_mask(U, h, w)
        corners = cv2.goodFeaturesToTrack(image, cfg.max_corners, 0.01, cfg.min_corner_spacing_px, mask=mask, blockSize=7)
        if corners is None:
            return np.zeros((0, 2)), np.zeros((0, 2))
        p1 = corners.reshape(-1, 1, 2).astype(np.float32)
        lk = dict(winSize=(21, 21), maxLevel=3, criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 0.01))
        pw, st1, _ = cv2.calcOpticalFlowPyrLK(image, warped, p1, None, **lk)
        back, st2, _ = cv2.calcOpticalFlowPyrLK(warped, image, pw, p1.copy(), flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **lk)
        uv1 = p1.reshape(-1, 2).astype(np.float64)
        good = (st1.ravel() == 1) & (st2.ravel() == 1) & (np.linalg.norm(back.reshape(-1, 2) - uv1, axis=1) < 1.0)
        uv0 = cv2.perspectiveTransform(pw.reshape(-1, 1, 2).astype(np.float64), np.linalg.inv(H)).reshape(-1, 2)
        good &= np.isfinite(uv0).all(axis=1) & self.camera.in_image(uv0, margin_px=10)
        return uv0[good], uv1[good]

    def _T_cam1_cam0(self, U: np.ndarray) -> np.ndarray:
        return invert(invert(self.T_body_cam) @ U @ self.T_body_cam)

    def _ground_homography(self, U: np.ndarray) -> np.ndarray:
        """The homography (pixels, lens distortion neglected) the ground plane of the body frame
        before the gap (z = 0) induces from the first camera to the second under the motion ``U``."""
        R_bc, t_bc = self.T_body_cam[:3, :3], self.T_body_cam[:3, 3]
        n_cam0 = R_bc.T @ np.array([0.0, 0.0, 1.0])  # n . X_cam0 = -height on the plane
        height_m = float(t_bc[2])
        T10 = self._T_cam1_cam0(U)
        K = self.camera.K
        return K @ (T10[:3, :3] - np.outer(T10[:3, 3], n_cam0) / height_m) @ np.linalg.inv(K)

    def _below_horizon_mask(self, U: np.ndarray, h: int, w: int) -> np.ndarray:
        """255 on the pixels of the second image whose rays meet the body's ground plane before the
        gap closer than ``_FAR_M`` (where the homography holds), else 0."""
        T01 = invert(self._T_cam1_cam0(U))
        R_bc, t_bc = self.T_body_cam[:3, :3], self.T_body_cam[:3, 3]
        v = np.arange(h, dtype=float)
        u = np.full(h, 0.5 * w)
        d_cam1 = self.camera.bearings_from_pixels(np.stack([u, v], axis=1))
        d_body0 = d_cam1 @ (R_bc @ T01[:3, :3]).T
        origin_z = float((R_bc @ T01[:3, 3] + t_bc)[2])
        with np.errstate(divide="ignore", invalid="ignore"):
            s = -origin_z / d_body0[:, 2]
        rows = np.isfinite(s) & (s > 0) & (s < _FAR_M)
        return np.repeat(np.where(rows, 255, 0).astype(np.uint8)[:, None], w, axis=1)


def _grey(image: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) if image.ndim == 3 else image


def _homogeneous(xy: np.ndarray) -> np.ndarray:
    return np.concatenate([xy, np.ones((len(xy), 1))], axis=1)


__all__ = ["BridgeReport", "GapBridge", "GapBridgeConfig"]
