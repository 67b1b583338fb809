"""A frame's template warps and templates in compiled passes.

:func:`homographies_from_4_points` solves each point's 8 x 8 system for the homography that takes
four pixels onto four others (what ``np.linalg.solve`` over the stack did, less its per-call cost).

Each template pixel is sampled (bilinear, the region's border repeated) from its patch's stored
region at the point a 3x3 matrix maps it to (:meth:`~dem_graph.frontend.tracker.PatchTracker.template_warps`):
what ``cv2.warpPerspective`` with ``WARP_INVERSE_MAP`` and ``BORDER_REPLICATE`` does, without its
rounding of the sampling position to 1/32 pixel, and without a call per point.
"""

from __future__ import annotations

import math

import numba
import numpy as np


@numba.njit(cache=True, nogil=True)
def homographies_from_4_points(uv_src: np.ndarray, uv_dst: np.ndarray) -> np.ndarray:
    """(n,3,3) homographies mapping 4 source points (n,4,2) onto 4 destination points, with
    ``H[2,2] = 1``; NaN where the points are not finite or are degenerate (the 8 x 8 system's
    determinant at most 1e-12 in magnitude). Gaussian elimination with partial pivoting."""
    n = uv_src.shape[0]
    H = np.full((n, 3, 3), np.nan)
    A = np.empty((8, 9))  # the system with its right-hand side
    for k in range(n):
        finite = True
        for i in range(4):
            x, y = uv_src[k, i, 0], uv_src[k, i, 1]
            u, v = uv_dst[k, i, 0], uv_dst[k, i, 1]
            if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(u) and math.isfinite(v)):
                finite = False
            A[i, 0], A[i, 1], A[i, 2], A[i, 3], A[i, 4], A[i, 5], A[i, 6], A[i, 7], A[i, 8] = x, y, 1.0, 0.0, 0.0, 0.0, -u * x, -u * y, u
            A[i + 4, 0], A[i + 4, 1], A[i + 4, 2], A[i + 4, 3], A[i + 4, 4], A[i + 4, 5] = 0.0, 0.0, 0.0, x, y, 1.0
            A[i + 4, 6], A[i + 4, 7], A[i + 4, 8] = -v * x, -v * y, v
        if not finite:
            continue
        det = 1.0
        for c in range(8):
            p = c
            for r in range(c + 1, 8):
                if abs(A[r, c]) > abs(A[p, c]):
                    p = r
            if p != c:
                for j in range(9):
                    A[c, j], A[p, j] = A[p, j], A[c, j]
                det = -det
            det *= A[c, c]
            if A[c, c] == 0.0:
                break
            for r in range(c + 1, 8):
                f = A[r, c] / A[c, c]
                for j in range(c, 9):
                    A[r, j] -= f * A[c, j]
        if not abs(det) > 1e-12:
            continue
        h = np.empty(9)
        h[8] = 1.0
        for r in range(7, -1, -1):
            acc = A[r, 8]
            for j in range(r + 1, 8):
                acc -= A[r, j] * h[j]
            h[r] = acc / A[r, r]
        for i in range(3):
            for j in range(3):
                H[k, i, j] = h[3 * i + j]
    return H


@numba.njit(cache=True, nogil=True)
def ground_homographies(X_world: np.ndarray, T_world_cam_source: np.ndarray, T_world_cam: np.ndarray, intrinsics: np.ndarray, half_m: float) -> np.ndarray:
    """(n,3,3) homographies from each point's source view to the current one, induced by the
    horizontal ground square of side ``2 half_m`` centred on the point (``X_world`` (n,3)): its
    corners seen from the source camera ``T_world_cam_source`` (n,4,4) and from the current one
    ``T_world_cam`` (4,4), projected through ``intrinsics`` (fx, fy, cx, cy, k1, k2, p1, p2, k3: OpenCV's
    distortion, as :meth:`~dem_graph.geometry.camera.PinholeCamera.project`), then
    :func:`homographies_from_4_points`. NaN where a corner is not in front of either camera (its
    pixel is NaN, which the solve refuses)."""
    n = X_world.shape[0]
    uv = np.empty((2, n, 4, 2))
    dx = (-half_m, half_m, half_m, -half_m)
    dy = (-half_m, -half_m, half_m, half_m)
    fx, fy, cx, cy = intrinsics[0], intrinsics[1], intrinsics[2], intrinsics[3]
    k1, k2, p1, p2, k3 = intrinsics[4], intrinsics[5], intrinsics[6], intrinsics[7], intrinsics[8]
    for k in range(n):
        for view in range(2):
            T = T_world_cam_source[k] if view == 0 else T_world_cam
            for i in range(4):
                # the corner in the camera: R^T (X - t)
                wx, wy, wz = X_world[k, 0] + dx[i] - T[0, 3], X_world[k, 1] + dy[i] - T[1, 3], X_world[k, 2] - T[2, 3]
                px = T[0, 0] * wx + T[1, 0] * wy + T[2, 0] * wz
                py = T[0, 1] * wx + T[1, 1] * wy + T[2, 1] * wz
                pz = T[0, 2] * wx + T[1, 2] * wy + T[2, 2] * wz
                if not pz > 1e-9:
                    uv[view, k, i, 0] = uv[view, k, i, 1] = np.nan
                    continue
                x, y = px / pz, py / pz
                r2 = x * x + y * y
                radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
                xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
                yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
                uv[view, k, i, 0] = fx * xd + cx
                uv[view, k, i, 1] = fy * yd + cy
    return homographies_from_4_points(uv[0], uv[1])


@numba.njit(cache=True, nogil=True)
def template_warps(centers_src_px: np.ndarray, region_radius_px: int, half: int, H_src_to_cur: np.ndarray) -> np.ndarray:
    """(n,3,3) maps from template pixels to stored-region pixels: template pixel (b, a) is the
    current image's ``c_cur + (b, a) - half``, where ``c_cur`` is the patch centre ``c`` (n,2,
    source image) through ``H`` (n,3,3, source to current image); that pixel goes back to the source
    by ``H^-1`` and into the region, whose centre pixel is ``region_radius_px``. NaN where ``H`` is
    not finite, is singular (determinant at most 1e-12 of its largest entry cubed) or maps the centre
    to infinity (third coordinate at most 1e-12 of it)."""
    n = H_src_to_cur.shape[0]
    M = np.full((n, 3, 3), np.nan)
    for k in range(n):
        h = H_src_to_cur[k]
        finite = True
        scale = 0.0
        for i in range(3):
            for j in range(3):
                if not math.isfinite(h[i, j]):
                    finite = False
                scale = max(scale, abs(h[i, j]))
        if not finite:
            continue
        cx, cy = centers_src_px[k, 0], centers_src_px[k, 1]
        w = h[2, 0] * cx + h[2, 1] * cy + h[2, 2]
        # the inverse by the adjugate
        a00 = h[1, 1] * h[2, 2] - h[1, 2] * h[2, 1]
        a01 = h[0, 2] * h[2, 1] - h[0, 1] * h[2, 2]
        a02 = h[0, 1] * h[1, 2] - h[0, 2] * h[1, 1]
        a10 = h[1, 2] * h[2, 0] - h[1, 0] * h[2, 2]
        a11 = h[0, 0] * h[2, 2] - h[0, 2] * h[2, 0]
        a12 = h[0, 2] * h[1, 0] - h[0, 0] * h[1, 2]
        a20 = h[1, 0] * h[2, 1] - h[1, 1] * h[2, 0]
        a21 = h[0, 1] * h[2, 0] - h[0, 0] * h[2, 1]
        a22 = h[0, 0] * h[1, 1] - h[0, 1] * h[1, 0]
        det = h[0, 0] * a00 + h[0, 1] * a10 + h[0, 2] * a20
        if not (abs(w) > 1e-12 * scale and abs(det) > 1e-12 * scale**3):
            continue
        ox = (h[0, 0] * cx + h[0, 1] * cy + h[0, 2]) / w - half  # the template's corner in the current image
        oy = (h[1, 0] * cx + h[1, 1] * cy + h[1, 2]) / w - half
        inv = np.empty((3, 3))
        inv[0, 0], inv[0, 1], inv[0, 2] = a00 / det, a01 / det, a02 / det
        inv[1, 0], inv[1, 1], inv[1, 2] = a10 / det, a11 / det, a12 / det
        inv[2, 0], inv[2, 1], inv[2, 2] = a20 / det, a21 / det, a22 / det
        for i in range(3):  # H^-1 @ translation(o)
            inv[i, 2] += inv[i, 0] * ox + inv[i, 1] * oy
        tx, ty = region_radius_px - cx, region_radius_px - cy
        for j in range(3):  # translation(radius - c) @ ...
            M[k, 0, j] = inv[0, j] + tx * inv[2, j]
            M[k, 1, j] = inv[1, j] + ty * inv[2, j]
            M[k, 2, j] = inv[2, j]
    return M


@numba.njit(cache=True, nogil=True)
def sample_templates(regions: np.ndarray, slots: np.ndarray, M_region_from_template: np.ndarray, side: int) -> np.ndarray:
    """(n, side, side) float32 templates: pixel (row a, column b) of template k is region
    ``slots[k]`` (of ``regions`` (m, R, R), float32) sampled bilinearly at ``M[k] @ (b, a, 1)``
    (column, row; divided by its third coordinate), the region's border repeated beyond it
    (infinitely far too); float64 arithmetic. A NaN position samples the region's first row or column."""
    n = slots.shape[0]
    height, width = regions.shape[1], regions.shape[2]
    out = np.empty((n, side, side), dtype=np.float32)
    x_max, y_max = width - 1.0, height - 1.0
    for k in range(n):
        M = M_region_from_template[k]
        region = regions[slots[k]]
        template = out[k]
        for a in range(side):
            x_a = M[0, 1] * a + M[0, 2]
            y_a = M[1, 1] * a + M[1, 2]
            w_a = M[2, 1] * a + M[2, 2]
            for b in range(side):
                inv_w = 1.0 / (M[2, 0] * b + w_a)
                x = (M[0, 0] * b + x_a) * inv_w
                y = (M[1, 0] * b + y_a) * inv_w
                # clamped into the region: beyond its border every sample is the border's (NaN: 0)
                if not x >= 0.0:
                    x = 0.0
                elif x > x_max:
                    x = x_max
                if not y >= 0.0:
                    y = 0.0
                elif y > y_max:
                    y = y_max
                c0, r0 = int(x), int(y)
                fx, fy = x - c0, y - r0
                c1, r1 = min(c0 + 1, width - 1), min(r0 + 1, height - 1)
                top = (1.0 - fx) * np.float64(region[r0, c0]) + fx * np.float64(region[r0, c1])
                bottom = (1.0 - fx) * np.float64(region[r1, c0]) + fx * np.float64(region[r1, c1])
                template[a, b] = (1.0 - fy) * top + fy * bottom
    return out


__all__ = ["ground_homographies", "homographies_from_4_points", "sample_templates", "template_warps"]
