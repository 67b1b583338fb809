"""Active-search patch tracking.

The points the front end tracks are not corners: they sit wherever the guidance wants them (on the
ground ahead, in the laser's path, ...). Tracking them therefore relies on a good prediction of each
point's position in the current image, on a search region derived from the predicted uncertainty
(the chi-square gate of the 2x2 innovation covariance, "active search"), and on a template warped
by the homography the ground induces between the two views when the viewpoint changes a lot.

A :class:`Patch` stores the grey levels around a point in the image it was seen in, with a margin
so that it can be warped; :meth:`PatchTracker.template` turns it into the template expected in the
current image; :meth:`PatchTracker.track` finds that template by zero-mean normalised
cross-correlation (NCC, OpenCV's ``TM_CCOEFF_NORMED``, computed by
:func:`~dem_graph.frontend.match_kernel.ncc_grid`) in the gated region and refines the peak to sub-pixel (a quadratic fit of
the 3x3 scores around it).

Pixel convention (OpenCV): integer ``(u, v)`` is the centre of pixel column ``u``, row ``v``.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass, field

import cv2
import numpy as np
from pydantic import Field

from dem_graph.config_types import StrictModel
from dem_graph.frontend.match_kernel import (
    AMBIGUOUS,
    BAD_COVARIANCE,
    LOW_SCORE,
    LOW_TEXTURE,
    OK,
    OUT_OF_IMAGE,
    PEAK_AT_BORDER,
    PEAK_OUTSIDE_GATE,
    SEARCH,
    SEARCH_TOO_LARGE,
    TEXTURE_BORDERLINE,
    ncc_grid,
    ncc_grids,
    plan_searches,
    select_match,
    select_matches,
)
from dem_graph.frontend.warp_kernel import ground_homographies, homographies_from_4_points, sample_templates, template_warps


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
    max_search_half_size_px: int = Field(
        40,
        ge=0,
        description="a search region with a larger half size on either axis is refused, pixels; left at 40 (1.5 m/s at 25 Hz), a run derives it "
        "from vehicle.speed_mps and the camera's rate",
    )
    search_cap_follows_speed: bool = Field(
        True,
        description="raise max_search_half_size_px while the estimated speed asks for a quarter more than it (frontend.search_cap), never below it; "
        "a run turns it off where max_search_half_size_px is given",
    )
    refuse_peak_outside_gate: bool = Field(
        False,
        description="refuse a match when a candidate just outside the gate scores higher than the best inside (the peak is outside the gate); "
        "off: the best inside is taken, off towards the prediction (docs/isam2_design.md)",
    )
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
    PEAK_AT_BORDER = "peak_at_border"  # the best candidate is at the image border: the peak may lie beyond it
    PEAK_OUTSIDE_GATE = "peak_outside_gate"  # refuse_peak_outside_gate: a candidate just outside the gate scores higher than the best inside


@dataclass(frozen=True)
class Patch:
    """Grey levels around a point in the image where it was seen.

    ``region`` is a uint8 square of side ``2 * (patch_half_size_px + warp_margin_px) + 1`` whose
    centre pixel is ``center_px`` of the source image (sampled with sub-pixel accuracy).
    """

    region: np.ndarray
    center_px: np.ndarray
    t_s: float
    region_f32: np.ndarray = field(init=False, repr=False, compare=False)  # ``region`` as float32, for the templates

    def __post_init__(self):
        object.__setattr__(self, "region_f32", np.asarray(self.region, dtype=np.float32))


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


# the status of each code of the compiled kernels (dem_graph.frontend.match_kernel)
_STATUS_OF_CODE = {
    OK: TrackStatus.OK,
    LOW_SCORE: TrackStatus.LOW_SCORE,
    AMBIGUOUS: TrackStatus.AMBIGUOUS,
    OUT_OF_IMAGE: TrackStatus.OUT_OF_IMAGE,
    SEARCH_TOO_LARGE: TrackStatus.SEARCH_TOO_LARGE,
    LOW_TEXTURE: TrackStatus.LOW_TEXTURE,
    PEAK_AT_BORDER: TrackStatus.PEAK_AT_BORDER,
    PEAK_OUTSIDE_GATE: TrackStatus.PEAK_OUTSIDE_GATE,
}
_SEARCHED = np.array([OK, LOW_SCORE, AMBIGUOUS, PEAK_AT_BORDER, PEAK_OUTSIDE_GATE], dtype=np.int8)  # codes of points whose region was searched
_NO_COVARIANCE = np.zeros((0, 2, 2))


@dataclass(frozen=True)
class TrackBatch:
    """Outcome of :meth:`PatchTracker.track_many`, as arrays over its ``n`` points: what
    :class:`TrackResult` holds per point. ``status`` (n,) int8 codes (:meth:`statuses` gives the
    :class:`TrackStatus`), ``uv_px`` (n,2) NaN unless OK, ``score`` and ``second_score`` (n,),
    ``search_half_size_px`` (n,2) int."""

    status: np.ndarray
    uv_px: np.ndarray
    score: np.ndarray
    second_score: np.ndarray
    search_half_size_px: np.ndarray

    def __len__(self) -> int:
        return len(self.status)

    @property
    def ok(self) -> np.ndarray:
        """(n,) bool: which points were matched."""
        return self.status == OK

    def statuses(self) -> list[TrackStatus]:
        return [_STATUS_OF_CODE[c] for c in self.status.tolist()]

    def status_counts(self) -> list[tuple[TrackStatus, int]]:
        """How many points have each status, the statuses in the order the points first have them."""
        codes, first, counts = np.unique(self.status, return_index=True, return_counts=True)
        return [(_STATUS_OF_CODE[int(codes[k])], int(counts[k])) for k in np.argsort(first, kind="stable").tolist()]


def _grey_image(image: np.ndarray) -> np.ndarray:
    """Check an image is uint8 grey (H, W) or BGR (H, W, 3); returned unchanged (converted lazily)."""
    if not isinstance(image, np.ndarray) or image.dtype != np.uint8:
        raise ValueError(f"expected a uint8 image, got {getattr(image, 'dtype', type(image))}")
    if image.ndim == 2 or (image.ndim == 3 and image.shape[2] == 3):
        return image
    raise ValueError(f"expected a grey (H, W) or BGR (H, W, 3) image, got shape {image.shape}")


def _to_grey(window: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(window, cv2.COLOR_BGR2GRAY) if window.ndim == 3 else window


def _spread_below(grey: np.ndarray, min_std: float) -> bool:
    """Whether the grey levels' standard deviation (numpy's ``std``) is below ``min_std``. OpenCV's
    ``meanStdDev`` (about 10 times faster on a 15x15 patch) decides, unless it is within rounding of
    the minimum; then numpy's own value does, so that the answer is numpy's in every case."""
    _, std = cv2.meanStdDev(grey)
    fast = float(std[0, 0])
    if abs(fast - min_std) > 1e-9 * max(1.0, min_std):
        return fast < min_std
    return float(grey.std()) < min_std


def _point(uv_px, what: str) -> np.ndarray:
    uv = np.asarray(uv_px, dtype=float)
    if uv.shape != (2,):
        raise ValueError(f"{what} must have shape (2,), got {uv.shape}")
    return uv


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
        if _spread_below(central, cfg.min_patch_std_dn):
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
            return patch.region_f32[margin : margin + side, margin : margin + side].copy()
        H = np.asarray(H_src_to_cur, dtype=float)
        if H.shape != (3, 3):
            raise ValueError(f"H_src_to_cur must be a 3x3 matrix, got shape {H.shape}")
        M = self.template_warps(np.asarray(patch.center_px, dtype=float)[None], radius, H[None])[0]
        if not np.all(np.isfinite(M)):
            raise ValueError("H_src_to_cur is not finite, singular, or maps the patch centre to infinity")
        return self.warp_template(patch, M)

    def compile_kernels(self) -> None:
        """Run every compiled kernel of tracking once on a small image, so that numba compiles them
        (the first run after an install, some seconds) or loads them from its cache before a run's
        first frame rather than in it."""
        rng = np.random.default_rng(0)
        image = rng.integers(0, 256, (64, 64), dtype=np.uint8)
        patch = self.make_patch(image, (32.0, 32.0), 0.0)
        if patch is None:
            return
        M = self.template_warps(np.array([patch.center_px]), patch.region.shape[0] // 2, np.eye(3)[None])
        templates = self.warp_templates([patch], M)
        uv = np.array([[32.0, 32.0]])
        read_only = image.copy()
        read_only.flags.writeable = False  # as a ROS bag's raw images come: numba types them apart
        for img in (image, read_only):
            self.track_many(img, templates, uv, S_px2=np.eye(2)[None])
            self.track_many(img, templates, uv, half_size_px=1)
        for img in (image, read_only, cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)):  # a grey region is a view, a BGR one a copy
            self.track(img, templates[0], uv[0], S_px2=np.eye(2))
        homographies_from_4_points(np.zeros((0, 4, 2)), np.zeros((0, 4, 2)))
        ground_homographies(np.zeros((0, 3)), np.zeros((0, 4, 4)), np.eye(4), np.zeros(9), 0.15)  # the front end's template warps

    def template_warps(self, centers_src_px: np.ndarray, region_radius_px: int, H_src_to_cur: np.ndarray) -> np.ndarray:
        """(n,3,3) maps from template pixels to stored-region pixels, for :meth:`warp_template`,
        computed for ``n`` patches at once (patch centres (n,2) in their source images, homographies
        (n,3,3) from source to current image); NaN where a homography is not finite, is singular,
        or maps the centre to infinity. See :meth:`template` for the geometry; one compiled pass
        (:func:`~dem_graph.frontend.warp_kernel.template_warps`)."""
        H = np.ascontiguousarray(H_src_to_cur, dtype=float).reshape(-1, 3, 3)
        centers = np.ascontiguousarray(centers_src_px, dtype=float).reshape(len(H), 2)
        return template_warps(centers, int(region_radius_px), self.config.patch_half_size_px, H)

    def warp_template(self, patch: Patch, M_region_from_template: np.ndarray) -> np.ndarray:
        """The template sampled (bilinear, border repeated) from the patch's stored region through one
        matrix of :meth:`template_warps`."""
        return self.warp_templates([patch], np.asarray(M_region_from_template, dtype=float)[None])[0]

    def warp_templates(self, patches: list[Patch], M_region_from_template: np.ndarray) -> np.ndarray:
        """(n,t,t) float32: :meth:`warp_template` for ``n`` patches (their regions of one size) and
        their matrices (n,3,3), in one compiled pass (:func:`~dem_graph.frontend.warp_kernel.sample_templates`)."""
        side = 2 * self.config.patch_half_size_px + 1
        if not patches:
            return np.zeros((0, side, side), dtype=np.float32)
        regions = np.stack([p.region_f32 for p in patches])
        return self.warp_regions(regions, np.arange(len(patches)), M_region_from_template)

    def warp_regions(self, regions: np.ndarray, slots: np.ndarray, M_region_from_template: np.ndarray) -> np.ndarray:
        """(n,t,t) float32: :meth:`warp_templates` for the stored regions ``regions[slots]`` ((m,R,R)
        float32; ``slots`` (n,)), read in place (a :class:`~dem_graph.frontend.patch_store.PatchStore`'s)."""
        side = 2 * self.config.patch_half_size_px + 1
        slots = np.ascontiguousarray(slots, dtype=np.int64)
        return sample_templates(regions, slots, np.ascontiguousarray(M_region_from_template, dtype=float).reshape(len(slots), 3, 3), side)

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

        The same search as :meth:`track_many` for one point, to the bit (tests/test_track_many.py),
        in Python scalars around the same compiled :func:`select_match`: for the point-by-point
        PTPM, whose calls each hold one point, it costs about half of a one-point
        :meth:`track_many` (two compiled calls and the array set-up, 101 against 57 us median,
        alternating, on a loaded machine).
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
        roi = _to_grey(img[v_lo - ht : v_hi + ht + 1, u_lo - ht : u_hi + ht + 1])
        n_rows, n_cols = v_hi - v_lo + 1, u_hi - u_lo + 1
        flat = np.empty(n_rows * n_cols)
        ncc_grid(roi, 0, 0, n_rows, n_cols, tpl, flat)
        scores = flat.astype(np.float32).reshape(n_rows, n_cols)  # scores[i, j]: centre (u_lo + j, v_lo + i)

        # the region inside the computed grid: rows i0:i1, columns j0:j1
        i0, i1 = max(cv - half_v, v_lo) - v_lo, min(cv + half_v, v_hi) - v_lo + 1
        j0, j1 = max(cu - half_u, u_lo) - u_lo, min(cu + half_u, u_hi) - u_lo + 1
        a, b, c = S_inv if S_inv is not None else (1.0, 0.0, 1.0)
        status, i_best, j_best, best, second, off_u, off_v = select_match(
            scores,
            i0,
            i1,
            j0,
            j1,
            S_inv is not None,
            a,
            b,
            c,
            gamma,
            v_lo + i0 - v_pred,
            u_lo + j0 - u_pred,
            cv - v_lo,
            cu - u_lo,
            cfg.min_score,
            cfg.exclusion_radius_px,
            cfg.ambiguity_margin,
            cfg.subpixel,
            cfg.refuse_peak_outside_gate,
        )
        searched = (half_u, half_v)
        if status != OK:  # select_match's second is NaN unless the status is OK or AMBIGUOUS
            return TrackResult(_STATUS_OF_CODE[status], None, best, second, searched)
        uv_match = np.array([u_lo + j_best + off_u, v_lo + i_best + off_v])
        return TrackResult(TrackStatus.OK, uv_match, best, second, searched)

    def track_many(
        self,
        image: np.ndarray,
        templates: np.ndarray,
        uv_pred_px: np.ndarray,
        S_px2: np.ndarray | None = None,
        half_size_px: int | None = None,
    ) -> TrackBatch:
        """:meth:`track` for ``n`` points at once: ``templates`` (n,t,t), predictions (n,2), and
        either innovation covariances ``S_px2`` (n,2,2) or one ``half_size_px`` for all.

        Each point's outcome is the one :meth:`track` gives it alone, to the bit: the gates, the
        regions, the correlations and the choice of the match are three compiled passes over all
        the points (:func:`~dem_graph.frontend.match_kernel.plan_searches`,
        :func:`~dem_graph.frontend.match_kernel.ncc_grids`,
        :func:`~dem_graph.frontend.match_kernel.select_matches`), with no Python per point.
        """
        if (S_px2 is None) == (half_size_px is None):
            raise ValueError("give exactly one of S_px2 and half_size_px")
        img = _grey_image(image)
        tpl = np.asarray(templates, dtype=np.float32)
        if tpl.ndim != 3 or tpl.shape[1] != tpl.shape[2] or tpl.shape[1] % 2 != 1:
            raise ValueError(f"templates must be odd squares (n, t, t), got shape {tpl.shape}")
        n = len(tpl)
        uv = np.asarray(uv_pred_px, dtype=float)
        if uv.shape != (n, 2):
            raise ValueError(f"uv_pred_px must have shape ({n}, 2), got {uv.shape}")
        cfg = self.config
        if S_px2 is not None:
            S = np.asarray(S_px2, dtype=float)
            if S.shape != (n, 2, 2):
                raise ValueError(f"S_px2 must have shape ({n}, 2, 2), got {S.shape}")
            gamma, half = self.gate_chi2, 0
        else:
            S, gamma, half = _NO_COVARIANCE, math.inf, int(half_size_px)
            if half < 0:
                raise ValueError(f"half_size_px must be >= 0, got {half_size_px}")
        height, width = img.shape[:2]
        plan = np.array([gamma, cfg.max_search_half_size_px, cfg.min_patch_std_dn, width, height], dtype=float)
        status, box, ellipse = plan_searches(uv, S, half, tpl, plan)
        if np.any(status == BAD_COVARIANCE):
            raise ValueError("S_px2 is not a finite positive definite matrix")
        for k in np.flatnonzero(status == TEXTURE_BORDERLINE):
            _, tpl_std = cv2.meanStdDev(tpl[k])
            status[k] = LOW_TEXTURE if float(tpl_std[0, 0]) < cfg.min_patch_std_dn else SEARCH

        # one score grid per point searched: candidate centres u_lo..u_hi, v_lo..v_hi (the region
        # plus a one-pixel ring for the sub-pixel fit, clipped to where the template fits), all in
        # one compiled pass
        searched = status == SEARCH
        if img.ndim == 2:
            grey, u0, v0 = img, 0, 0
        elif searched.any():  # BGR: made grey over the box holding every region only
            ht = tpl.shape[1] // 2
            lo = box[searched, 4:8].min(axis=0) - ht
            hi = box[searched, 4:8].max(axis=0) + ht + 1
            u0, v0 = int(lo[0]), int(lo[2])
            grey = _to_grey(img[v0 : int(hi[3]), u0 : int(hi[1])])
        else:
            grey, u0, v0 = np.zeros((0, 0), dtype=np.uint8), 0, 0
        scores, offsets = ncc_grids(grey, u0, v0, tpl, status, box)
        select = np.array(
            [S_px2 is not None, cfg.min_score, cfg.exclusion_radius_px, cfg.ambiguity_margin, cfg.subpixel, cfg.refuse_peak_outside_gate], dtype=float
        )
        status, uv_match, score, second = select_matches(status, box, ellipse, uv, scores, offsets, gamma, select)
        half_sizes = np.where(np.isin(status, _SEARCHED)[:, None], box[:, :2], 0)
        return TrackBatch(status, uv_match, score, second, half_sizes)
