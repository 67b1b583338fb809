"""Active-search patch tracking.

The points the front end tracks are not corners: they sit wherever the guidance wants them (on the
ground ahead, in the laser's path, ...). Tracking them therefore relies on a good prediction of each
point's position in the current image, on a search region derived from the predicted uncertainty
(the chi-square gate of the 2x2 innovation covariance, "active search"), and on a template warped
by the homography the ground induces between the two views when the viewpoint changes a lot.

A :class:`Patch` stores the grey levels around a point in the image it was seen in, with a margin
so that it can be warped; :meth:`PatchTracker.template` turns it into the template expected in the
current image; :meth:`PatchTracker.track` finds that template by zero-mean normalised
cross-correlation (NCC) in the gated region and refines the peak to sub-pixel (a quadratic fit of
the 3x3 scores around it).

Pixel convention (OpenCV): integer ``(u, v)`` is the centre of pixel column ``u``, row ``v``.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

import cv2
import numpy as np
from pydantic import Field

from dem_graph.config_types import StrictModel

_DILATE_KERNEL = np.ones((3, 3), np.uint8)


class TrackerConfig(StrictModel):
    """Settings of :class:`PatchTracker`."""

    patch_half_size_px: int = Field(7, ge=1, le=64, description="half side of the matched template, pixels (7: a 15x15 template)")
    warp_margin_px: int = Field(
        8, ge=0, le=64, description="extra border stored around the template in a patch so that it can be warped, pixels"
    )
    min_patch_std_dn: float = Field(
        3.0, ge=0, description="a template whose grey-level standard deviation is below this is not trackable, grey levels (DN)"
    )
    min_score: float = Field(
        0.7, ge=-1, le=1, description="minimum zero-mean normalised cross-correlation of an accepted match, dimensionless"
    )
    ambiguity_margin: float = Field(
        0.08, ge=0, le=2, description="a match is ambiguous when the best score minus the second peak's score is below this, dimensionless"
    )
    exclusion_radius_px: int = Field(3, ge=0, description="the second peak is sought farther than this from the best one, pixels")
    gate_probability: float = Field(
        0.99, gt=0, lt=1, description="probability of the chi-square gate (2 dof) on the innovation, dimensionless"
    )
    max_search_half_size_px: int = Field(40, ge=0, description="a search region with a larger half size on either axis is refused, pixels")
    subpixel: bool = Field(
        True, description="refine the match to sub-pixel by a quadratic fit of the scores around the peak (offset at most 0.5 px per axis)"
    )


class TrackStatus(enum.Enum):
    """Outcome of one :meth:`PatchTracker.track` call."""

    OK = "ok"
    OUT_OF_IMAGE = "out_of_image"  # the template cannot be placed at the predicted position
    SEARCH_TOO_LARGE = "search_too_large"  # the gated region exceeds max_search_half_size_px
    LOW_TEXTURE = "low_texture"  # the (warped) template is too flat to be matched
    LOW_SCORE = "low_score"  # no candidate in the region reaches min_score
    AMBIGUOUS = "ambiguous"  # a second peak in the region scores nearly as well as the best


@dataclass(frozen=True)
class Patch:
    """Grey levels around a point in the image where it was seen.

    ``region`` is a uint8 square of side ``2 * (patch_half_size_px + warp_margin_px) + 1`` whose
    centre pixel is ``center_px`` of the source image (sampled with sub-pixel accuracy).
    """

    region: np.ndarray
    center_px: np.ndarray
    t_s: float


@dataclass(frozen=True)
class TrackResult:
    """Outcome of a search.

    ``uv_px`` is the matched position (pixels, shape (2,)) when ``status`` is OK, else None.
    ``score`` is the best NCC in the region and ``second_score`` the best other peak farther than
    ``exclusion_radius_px`` from it; each is NaN when it was not computed or does not exist.
    ``search_half_size_px`` is the (u, v) half size of the region searched (before clipping at
    the image border), ``(0, 0)`` when no search was made.
    """

    status: TrackStatus
    uv_px: np.ndarray | None
    score: float
    second_score: float
    search_half_size_px: tuple[int, int]

    @property
    def ok(self) -> bool:
        return self.status is TrackStatus.OK


def _grey_image(image: np.ndarray) -> np.ndarray:
    """Check an image is uint8 grey (H, W) or BGR (H, W, 3); returned unchanged (converted lazily)."""
    if not isinstance(image, np.ndarray) or image.dtype != np.uint8:
        raise ValueError(f"expected a uint8 image, got {getattr(image, 'dtype', type(image))}")
    if image.ndim == 2 or (image.ndim == 3 and image.shape[2] == 3):
        return image
    raise ValueError(f"expected a grey (H, W) or BGR (H, W, 3) image, got shape {image.shape}")


def _to_grey(window: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(window, cv2.COLOR_BGR2GRAY) if window.ndim == 3 else window


def _point(uv_px, what: str) -> np.ndarray:
    uv = np.asarray(uv_px, dtype=float)
    if uv.shape != (2,):
        raise ValueError(f"{what} must have shape (2,), got {uv.shape}")
    return uv


def _parabola_offset(left: float, centre: float, right: float) -> float:
    """Vertex offset of the parabola through three equally spaced samples, clamped to +-0.5."""
    curvature = left - 2.0 * centre + right
    if not curvature < 0.0:  # not a maximum (or NaN): keep the integer peak
        return 0.0
    return min(0.5, max(-0.5, 0.5 * (left - right) / curvature))


def _subpixel_offset(scores: np.ndarray, i: int, j: int) -> tuple[float, float]:
    """Sub-pixel (u, v) offset of the score peak at row ``i``, column ``j``, each clamped to +-0.5.

    A 2-D quadratic through the 3x3 neighbourhood (gradient and Hessian, cross term included) when
    the peak is inside the grid and the Hessian is negative definite; otherwise a 1-D parabola
    along each axis whose two neighbours exist. The cross term matters: the NCC peak of a small
    window of natural texture is often a tilted ellipse, and per-axis parabolas through the
    integer peak then miss its top (on blurred noise, 15x15 templates: worst error 0.47 px with
    per-axis parabolas, 0.11 px with the 2-D fit).
    """
    n_rows, n_cols = scores.shape
    inner_u = 0 < j < n_cols - 1
    inner_v = 0 < i < n_rows - 1
    if inner_u and inner_v:
        w = scores[i - 1 : i + 2, j - 1 : j + 2].astype(float)
        g_u = 0.5 * (w[1, 2] - w[1, 0])
        g_v = 0.5 * (w[2, 1] - w[0, 1])
        h_uu = w[1, 2] - 2.0 * w[1, 1] + w[1, 0]
        h_vv = w[2, 1] - 2.0 * w[1, 1] + w[0, 1]
        h_uv = 0.25 * (w[2, 2] - w[2, 0] - w[0, 2] + w[0, 0])
        det = h_uu * h_vv - h_uv * h_uv
        if h_uu < 0.0 and det > 0.0:
            off_u = -(h_vv * g_u - h_uv * g_v) / det
            off_v = -(h_uu * g_v - h_uv * g_u) / det
            return min(0.5, max(-0.5, off_u)), min(0.5, max(-0.5, off_v))
    off_u = _parabola_offset(float(scores[i, j - 1]), float(scores[i, j]), float(scores[i, j + 1])) if inner_u else 0.0
    off_v = _parabola_offset(float(scores[i - 1, j]), float(scores[i, j]), float(scores[i + 1, j])) if inner_v else 0.0
    return off_u, off_v


class PatchTracker:
    """Extracts patches, predicts templates and finds them by active search (see the module doc)."""

    def __init__(self, config: TrackerConfig | None = None):
        self.config = TrackerConfig() if config is None else config

    @property
    def gate_chi2(self) -> float:
        """The chi-square quantile (2 dof) of ``gate_probability``: the gate on the squared Mahalanobis distance."""
        # for 2 degrees of freedom the quantile has the closed form -2 ln(1 - p)
        return -2.0 * math.log1p(-self.config.gate_probability)

    # ------------------------------------------------------------------ patches and templates

    def make_patch(self, image: np.ndarray, uv_px, t_s: float) -> Patch | None:
        """The patch around ``uv_px`` in ``image``, or None when it is not fully inside or too flat."""
        img = _grey_image(image)
        uv = _point(uv_px, "uv_px")
        if not np.all(np.isfinite(uv)):
            return None
        cfg = self.config
        half = cfg.patch_half_size_px
        radius = half + cfg.warp_margin_px
        height, width = img.shape[:2]
        u, v = float(uv[0]), float(uv[1])
        # bilinear samples at u - radius ... u + radius need both neighbours inside the image
        if u - radius < 0 or v - radius < 0 or u + radius > width - 1 or v + radius > height - 1:
            return None
        # the integer window holding every sample, made grey before sampling
        u0, v0 = math.floor(u) - radius, math.floor(v) - radius
        u1, v1 = min(math.floor(u) + radius + 2, width), min(math.floor(v) + radius + 2, height)
        window = _to_grey(img[v0:v1, u0:u1])
        side = 2 * radius + 1
        region = cv2.getRectSubPix(np.ascontiguousarray(window), (side, side), (u - u0, v - v0))
        central = region[cfg.warp_margin_px : cfg.warp_margin_px + 2 * half + 1, cfg.warp_margin_px : cfg.warp_margin_px + 2 * half + 1]
        if float(central.std()) < cfg.min_patch_std_dn:
            return None
        return Patch(region=region, center_px=uv.copy(), t_s=float(t_s))

    def template(self, patch: Patch, H_src_to_cur: np.ndarray | None = None, uv_pred_px=None) -> np.ndarray:
        """The (2h+1, 2h+1) float32 template expected around the patch's point in the current image.

        Without ``H_src_to_cur`` it is the centre of the stored region. With it (3x3, source image
        pixels to current image pixels, e.g. induced by the ground plane), the template pixel at
        offset ``q`` from the template centre is sampled (bilinear) from the source image at
        ``H^-1(H(c) + q)``, where ``c = patch.center_px``: the template centre is always the
        patch's point, so the match position refers to that point even when the prediction
        ``uv_pred_px`` is off. ``uv_pred_px`` therefore does not change the template; it is
        accepted so that call sites can pass the prediction they will search at. Samples that
        fall outside the stored region repeat its border.
        """
        cfg = self.config
        half = cfg.patch_half_size_px
        side = 2 * half + 1
        region = patch.region
        radius = region.shape[0] // 2
        margin = radius - half
        if region.ndim != 2 or region.shape[0] != region.shape[1] or margin < 0:
            raise ValueError(f"patch region of shape {region.shape} does not hold a {side}x{side} template")
        if H_src_to_cur is None:
            return region[margin : margin + side, margin : margin + side].astype(np.float32)
        H = np.asarray(H_src_to_cur, dtype=float)
        if H.shape != (3, 3) or not math.isfinite(float(H.sum())):
            raise ValueError(f"H_src_to_cur must be a finite 3x3 matrix, got shape {H.shape}")
        c_src = np.array([patch.center_px[0], patch.center_px[1], 1.0])
        c_h = H @ c_src
        if not abs(c_h[2]) > 1e-12 * float(np.abs(H).max()):
            raise ValueError("H_src_to_cur maps the patch centre to infinity")
        c_cur = c_h[:2] / c_h[2]
        ok, H_inv = cv2.invert(H)  # ~10x cheaper than np.linalg.inv on a 3x3
        if not ok:
            raise ValueError("H_src_to_cur is singular")
        # template pixel (a, b) -> current image (c_cur + (a, b) - half) -> source image -> region pixel
        cur_from_tpl = np.array([[1.0, 0.0, c_cur[0] - half], [0.0, 1.0, c_cur[1] - half], [0.0, 0.0, 1.0]])
        reg_from_src = np.array([[1.0, 0.0, radius - c_src[0]], [0.0, 1.0, radius - c_src[1]], [0.0, 0.0, 1.0]])
        reg_from_tpl = reg_from_src @ H_inv @ cur_from_tpl
        return cv2.warpPerspective(
            region.astype(np.float32),
            reg_from_tpl,
            (side, side),
            flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
            borderMode=cv2.BORDER_REPLICATE,
        )

    # ------------------------------------------------------------------ active search

    def track(
        self,
        image: np.ndarray,
        template: np.ndarray,
        uv_pred_px,
        S_px2: np.ndarray | None = None,
        half_size_px: int | None = None,
    ) -> TrackResult:
        """Search ``template`` around the prediction ``uv_pred_px`` in ``image``.

        Give exactly one of ``S_px2`` (the 2x2 innovation covariance, px^2: candidates inside the
        chi-square ellipse of ``gate_probability``) and ``half_size_px`` (a square region, as in
        the paper's GM); anything else is a ``ValueError``. The candidate nearest to the
        prediction is always searched, however small the ellipse.
        """
        if (S_px2 is None) == (half_size_px is None):
            raise ValueError("give exactly one of S_px2 and half_size_px")
        img = _grey_image(image)
        tpl = np.asarray(template, dtype=np.float32)
        if tpl.ndim != 2 or tpl.shape[0] != tpl.shape[1] or tpl.shape[0] % 2 != 1:
            raise ValueError(f"template must be an odd square, got shape {tpl.shape}")
        uv = _point(uv_pred_px, "uv_pred_px")
        cfg = self.config
        not_searched = (0, 0)

        S_inv = None
        gamma = math.inf
        if S_px2 is not None:
            S = np.asarray(S_px2, dtype=float)
            if S.shape != (2, 2):
                raise ValueError(f"S_px2 must be a 2x2 matrix, got shape {S.shape}")
            (s_uu, s_uv_upper), (s_uv_lower, s_vv) = S.tolist()
            s_uv = 0.5 * (s_uv_upper + s_uv_lower)
            det = s_uu * s_vv - s_uv * s_uv
            if not (0 < s_uu < math.inf and 0 < s_vv < math.inf and det > 0):
                raise ValueError("S_px2 is not a finite positive definite matrix")
            gamma = self.gate_chi2
            half_u = max(1, math.ceil(math.sqrt(gamma * s_uu)))
            half_v = max(1, math.ceil(math.sqrt(gamma * s_vv)))
            S_inv = (s_vv / det, -s_uv / det, s_uu / det)
        else:
            half_u = half_v = int(half_size_px)
            if half_u < 0:
                raise ValueError(f"half_size_px must be >= 0, got {half_size_px}")
        if half_u > cfg.max_search_half_size_px or half_v > cfg.max_search_half_size_px:
            return TrackResult(TrackStatus.SEARCH_TOO_LARGE, None, math.nan, math.nan, not_searched)

        ht = tpl.shape[0] // 2
        height, width = img.shape[:2]
        u_pred, v_pred = float(uv[0]), float(uv[1])
        if not (math.isfinite(u_pred) and math.isfinite(v_pred)):
            return TrackResult(TrackStatus.OUT_OF_IMAGE, None, math.nan, math.nan, not_searched)
        cu, cv = math.floor(u_pred + 0.5), math.floor(v_pred + 0.5)
        if cu - ht < 0 or cv - ht < 0 or cu + ht > width - 1 or cv + ht > height - 1:
            return TrackResult(TrackStatus.OUT_OF_IMAGE, None, math.nan, math.nan, not_searched)

        _, tpl_std = cv2.meanStdDev(tpl)
        if float(tpl_std[0, 0]) < cfg.min_patch_std_dn:
            return TrackResult(TrackStatus.LOW_TEXTURE, None, math.nan, math.nan, not_searched)

        # candidate template centres: the region plus a one-pixel ring (for the sub-pixel fit at
        # the region's edge), clipped to where the template fits in the image
        u_lo, u_hi = max(cu - half_u - 1, ht), min(cu + half_u + 1, width - 1 - ht)
        v_lo, v_hi = max(cv - half_v - 1, ht), min(cv + half_v + 1, height - 1 - ht)
        roi = _to_grey(img[v_lo - ht : v_hi + ht + 1, u_lo - ht : u_hi + ht + 1]).astype(np.float32)
        scores = cv2.matchTemplate(roi, tpl, cv2.TM_CCOEFF_NORMED)  # scores[i, j]: centre (u_lo + j, v_lo + i)
        n_rows, n_cols = scores.shape

        # the region inside the computed grid: rows i0:i1, columns j0:j1; scores outside it (and
        # outside the ellipse) are -inf in `gated`
        i0, i1 = max(cv - half_v, v_lo) - v_lo, min(cv + half_v, v_hi) - v_lo + 1
        j0, j1 = max(cu - half_u, u_lo) - u_lo, min(cu + half_u, u_hi) - u_lo + 1
        gated = np.full_like(scores, -np.inf)
        if S_inv is not None:
            # per row dv, the ellipse a du^2 + 2 b du dv + c dv^2 <= gamma is an interval of du
            a, b, c = S_inv
            dv = np.arange(i1 - i0) + (v_lo + i0 - v_pred)
            quarter_disc = b * b * dv * dv - a * (c * dv * dv - gamma)
            du_half = np.sqrt(np.maximum(quarter_disc, 0.0)) / a
            du_half[quarter_disc < 0.0] = -1.0  # the row misses the ellipse
            du_mid = (-b / a) * dv
            du = np.arange(j1 - j0) + (u_lo + j0 - u_pred)
            inside = np.abs(du[None, :] - du_mid[:, None]) <= du_half[:, None]
            inside[cv - v_lo - i0, cu - u_lo - j0] = True  # the nearest candidate, even for a tiny ellipse
            gated[i0:i1, j0:j1] = np.where(inside, scores[i0:i1, j0:j1], -np.inf)
        else:
            gated[i0:i1, j0:j1] = scores[i0:i1, j0:j1]
        searched = (half_u, half_v)

        i_best, j_best = divmod(int(gated.argmax()), n_cols)
        best = float(gated[i_best, j_best])
        if not best >= cfg.min_score:
            return TrackResult(TrackStatus.LOW_SCORE, None, best, math.nan, searched)

        # the second peak: a local maximum of the scores (3x3, over every computed candidate, so a
        # flank cut by the gate is not a peak), inside the region, outside the exclusion disk
        peaks = np.flatnonzero(gated >= cv2.dilate(scores, _DILATE_KERNEL))
        peak_i, peak_j = np.divmod(peaks, n_cols)
        far = (peak_i - i_best) ** 2 + (peak_j - j_best) ** 2 > cfg.exclusion_radius_px**2
        second = float(gated.flat[peaks[far]].max()) if far.any() else math.nan
        if second == second and best - second < cfg.ambiguity_margin:
            return TrackResult(TrackStatus.AMBIGUOUS, None, best, second, searched)

        off_u, off_v = _subpixel_offset(scores, i_best, j_best) if cfg.subpixel else (0.0, 0.0)
        uv_match = np.array([u_lo + j_best + off_u, v_lo + i_best + off_v])
        return TrackResult(TrackStatus.OK, uv_match, best, second, searched)
