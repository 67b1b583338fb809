"""The front end shared by every estimator: which points live, their patches, and tracking them.

Points are where the guidance wants them, not where the image has corners (the paper, III-A/B):
- laser points: a subset of each scan's returns inside the focus area, made 3D through the pose
  at the scan's time (spline of the pose history) and ``T_body_laser``;
- camera points: seeded at the focus cells that hold no point, on the flat-ground guess with
  about 0.5 m of height uncertainty.
A point is dropped when it leaves the image, falls behind, or fails tracking too often (the frames a
camera gap swallowed count as failures; :mod:`~dem_graph.frontend.gap_bridge` bridges the gap).

The estimator owns the 3D estimates; the front end hands out new points as body-frame positions
with covariances, and tracks a point given the estimator's prediction (pixel and, for an active
search, its 2x2 innovation covariance).
"""

from __future__ import annotations

import logging
from collections import Counter
from dataclasses import dataclass, field
from enum import IntEnum
from typing import Literal

import numpy as np
from pydantic import Field

from dem_graph.config_types import StrictModel
from dem_graph.frontend.focus import FocusArea, FocusConfig
from dem_graph.frontend.gap_bridge import GapBridge, GapBridgeConfig
from dem_graph.frontend.ground_motion import GroundMotion, GroundMotionConfig, GroundShift
from dem_graph.frontend.patch_store import PatchStore
from dem_graph.frontend.search_cap import GroundMotionPx
from dem_graph.frontend.tracker import Patch, PatchTracker, TrackBatch, TrackerConfig, TrackResult, TrackStatus
from dem_graph.frontend.warp_kernel import ground_homographies
from dem_graph.geometry.rig import SensorRig
from dem_graph.geometry.se3 import invert, transform_points

log = logging.getLogger(__name__)


class PointKind(IntEnum):
    """How a map point was seeded: on a laser return, or on the flat-ground guess at a focus cell
    (its value is the ``kind`` column of ``points.ply``)."""

    LASER = 0
    CAMERA = 1

_TRACK_COUNTER = {s: f"track_{s.name.lower()}" for s in TrackStatus}


class FrontendConfig(StrictModel):
    tracker: TrackerConfig = Field(default_factory=TrackerConfig)
    focus: FocusConfig = Field(default_factory=FocusConfig)
    gap_bridge: GapBridgeConfig = Field(default_factory=GapBridgeConfig, description="the motion across a camera gap, refined by the images on either side")
    ground_motion: GroundMotionConfig = Field(default_factory=GroundMotionConfig, description="without odometry, the speed at the start measured from the ground ahead")
    max_points: int = Field(140, ge=1, description="cap n on live points")
    max_laser_points: int = Field(100, ge=0, description="live laser points at most (the rest of the cap is for camera points)")
    laser_points_per_scan: int = Field(30, ge=0, description="returns taken from one scan at most")
    min_separation_px: float = Field(8.0, ge=0, description="a new point keeps this distance from live points, pixels")
    image_margin_px: int = Field(12, ge=0, description="points closer than this to the image border are dropped, pixels")
    max_misses: int = Field(3, ge=1, description="a point that fails tracking this many frames in a row is dropped")
    camera_point_sigma_height_m: float = Field(0.5, gt=0, description="height uncertainty of a new camera point (ground guess), metres")
    camera_point_ground: Literal["live_points", "flat"] = Field(
        "flat",
        description="where a new camera point is guessed: on the plane through the live points around the focus area (the body's ground plane "
        "while there are too few), or always on the body's ground plane (flat: biased wherever the ground ahead is not, docs/isam2_design.md)",
    )
    camera_point_sigma_px: float = Field(1.0, gt=0, description="across-ray uncertainty of a new camera point, pixels")
    interpolation_sigma_m: float = Field(0.002, ge=0, description="uncertainty added by interpolating the pose at a scan's time, metres")
    warp_patches: bool = Field(True, description="warp patches by the ground-plane homography between the two views")
    refresh_patch_every: int = Field(20, ge=0, description="re-record a point's patch at its tracked position every this many successful tracks (0: never)")
    sigma_px: float = Field(
        0.3,
        gt=0,
        description="standard deviation of a tracked position as the estimators weight it (each frame as if independent), pixels; "
        "`dem-graph research track-noise` measures the value a camera and tracker call for (docs/isam2_design.md)",
    )


@dataclass
class PointTrack:
    point_id: int
    kind: PointKind
    patch: Patch
    T_world_cam_source: np.ndarray  # camera pose estimate when the patch was taken
    created_t_s: float
    misses: int = 0
    n_tracked: int = 0
    # patch refreshes so far: each re-cuts the patch at a match, so from then on the track follows
    # the ground point under that match, a few millimetres from the one before
    segment: int = 0


@dataclass
class NewPoint:
    point_id: int
    kind: PointKind
    p_body: np.ndarray  # (3,) current body frame
    Sigma_body: np.ndarray  # (3,3)


@dataclass
class TrackedView:
    """What the front end searched in one frame, for a viewer (the paper's Fig. 6): per point its
    kind, the predicted pixel, the half size of the region searched (pixels) and the match (NaN
    when none). Kept as the tracker's arrays, one part per search call."""

    t_s: float
    parts: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = field(default_factory=list)

    def add(self, kind, uv_pred, half_size, uv) -> None:
        """One search call's points: kinds (n,), predictions (n,2), half sizes (n,2), matches (n,2) (NaN: none)."""
        n = len(np.atleast_1d(kind))
        self.parts.append((
            np.asarray(kind, dtype=np.uint8).reshape(n),
            np.asarray(uv_pred, dtype=float).reshape(n, 2),
            np.asarray(half_size, dtype=float).reshape(n, 2),
            np.asarray(uv, dtype=float).reshape(n, 2),
        ))

    def arrays(self) -> dict[str, np.ndarray]:
        names = ("kind", "uv_pred_px", "search_half_size_px", "uv_px")
        if not self.parts:
            return {"kind": np.zeros(0, dtype=np.uint8), **{k: np.zeros((0, 2)) for k in names[1:]}}
        return {k: np.concatenate([p[i] for p in self.parts]) for i, k in enumerate(names)}


_SEED_CHUNK = 64  # candidates whose distances to the live points are taken at once (a seed needs only the first few)
GROUND_MIN_POINTS = 12  # live points a ground plane is fitted to, at least
GROUND_MIN_EXTENT_M = 0.5  # their spread along and across the body, at least, metres


def ground_plane_through(points_body: np.ndarray, focus: FocusArea) -> np.ndarray | None:
    """``(a, b, c)`` of the ground ``z = a + b x + c y`` (body frame, metres) through the live points
    ``points_body`` (N,3) within a metre of the focus area, fitted by least squares, refitted once
    without the points more than 3 robust sigmas off (stones, a wrong point); None when fewer than
    :data:`GROUND_MIN_POINTS` remain or they do not spread :data:`GROUND_MIN_EXTENT_M` along and across.

    A new camera point's depth along its ray is a guess until parallax measures it. Guessed on the
    body's own ground plane, it is biased wherever the ground ahead is not on that plane (on
    `paper` the ground at the focus cells lies 2-3 cm above it on average: the wheels run in ruts),
    and the guess is a range from the seeding pose: every camera point then pushes its pose away
    from the ground, up. The plane through the points the estimator already has carries no such
    offset."""
    p = np.asarray(points_body, dtype=float).reshape(-1, 3)
    near = (
        (p[:, 0] > focus.x_near_m - 1.0) & (p[:, 0] < focus.x_far_m + 1.0) & (np.abs(p[:, 1]) < focus.half_width_m + 1.0) & np.isfinite(p).all(axis=1)
    )
    p = p[near]
    for _ in range(2):
        if len(p) < GROUND_MIN_POINTS or np.ptp(p[:, 0]) < GROUND_MIN_EXTENT_M or np.ptp(p[:, 1]) < GROUND_MIN_EXTENT_M:
            return None
        A = np.column_stack([np.ones(len(p)), p[:, 0], p[:, 1]])
        coef, *_ = np.linalg.lstsq(A, p[:, 2], rcond=None)
        residual = p[:, 2] - A @ coef
        sigma = 1.4826 * np.median(np.abs(residual - np.median(residual)))
        inliers = np.abs(residual) <= 3.0 * max(sigma, 1e-3)
        if inliers.all():
            break
        p = p[inliers]
    return coef


@dataclass
class FrontEnd:
    config: FrontendConfig
    rig: SensorRig
    tracker: PatchTracker = field(init=False)
    patches: PatchStore = field(init=False, repr=False)  # the live points' patches in arrays, for the templates
    tracks: dict[int, PointTrack] = field(default_factory=dict)
    counters: Counter = field(default_factory=Counter)
    record_view: bool = False  # keep each frame's searches in last_view (a viewer asks for it)
    last_view: TrackedView | None = None  # the latest frame's searches, when recorded
    _next_id: int = 0
    _gap_s: tuple[float, float] | None = None  # the camera gap the current frame ends, (start, end) seconds
    _last_image: tuple[float, np.ndarray] | None = None  # the last frame with texture and its time (the ground's motion is measured from it)
    _ground: GroundMotion | None = None  # made when first asked for

    def __post_init__(self):
        self.tracker = PatchTracker(self.config.tracker.model_copy())  # its own: the search cap follows the speed (follow_speed)
        self._base_cap_px = self.config.tracker.max_search_half_size_px
        self._cap_formula = GroundMotionPx(self.rig)  # the rig's part of the search cap, for follow_speed each frame
        tc = self.config.tracker
        self.patches = PatchStore(2 * (tc.patch_half_size_px + tc.warp_margin_px) + 1)
        self.camera = self.rig.camera_model
        self.T_body_cam = self.rig.T_body_cam
        self.T_cam_body = invert(self.T_body_cam)
        self.gap_bridge = GapBridge(self.config.gap_bridge, self.camera, self.T_body_cam, self.rig.camera.rate_hz, self.counters)
        self.tracker.compile_kernels()

    # --- frames ------------------------------------------------------------------------------
    def begin_frame(self, t_s: float, textureless: bool) -> int:
        """A frame at ``t_s`` begins; returns the camera frames a gap before it swallowed (0: none;
        frames without texture count as swallowed, once the texture is back). Those count as misses
        of every live point, so after a gap of ``max_misses`` frames or more every point is lost and
        the estimator drops it before searching (:meth:`drop_points`): its patch and its prediction
        are staler than after as many failed searches, and on the `smoke` log the few such points
        matched after a 1 s gap pulled the pose 4.6 cm off (GM, seed 5)."""
        missed = 0 if textureless else self.gap_bridge.frames_missed(t_s)
        self._gap_s = (self.gap_bridge.last_t_s, t_s) if missed else None
        if missed:
            self.counters["frames_missed"] += missed
            for track in self.tracks.values():
                track.misses += missed
        return missed

    def end_frame(self, t_s: float, image, textureless: bool) -> None:
        """The frame at ``t_s`` is done: the next frame's gap bridge and ground motion start from it."""
        self.gap_bridge.remember(t_s, image, textureless)
        if not textureless:
            self._last_image = (float(t_s), image)

    # --- the speed ---------------------------------------------------------------------------
    def _ground_motion(self) -> GroundMotion | None:
        """The top view of the ground (made at the first call, a warning if it cannot be), None when
        ``ground_motion`` is off or the camera sees no ground to make it from."""
        if not self.config.ground_motion.enabled:
            return None
        if self._ground is None:
            self._ground = GroundMotion(self.config.ground_motion, self.rig)
            if self._ground.problem:
                log.warning("the speed cannot be measured from the ground: %s; the motion model starts at motion.initial_speed_mps", self._ground.problem)
        return None if self._ground.problem else self._ground

    def ground_shift(self, t_s: float, image) -> GroundShift | None:
        """The body's translation over the ground from the last frame with texture to ``image`` (at ``t_s``)
        (:class:`~dem_graph.frontend.ground_motion.GroundMotion`), None when it is off, there is no
        earlier frame, or the views refuse it (counted, and said at info level)."""
        ground = self._ground_motion()
        if ground is None or self._last_image is None:
            return None
        t_before_s, before = self._last_image
        if not t_s > t_before_s:
            return None
        shift = ground.shift(ground.top_view(before), ground.top_view(image), t_s - t_before_s)
        if isinstance(shift, str):
            self.counters["ground_motion_refused"] += 1
            log.info("the ground's motion not measured: %s", shift)
            return None
        self.counters["ground_motion_measured"] += 1
        return shift

    @property
    def measures_ground_motion(self) -> bool:
        """Whether :meth:`ground_shift` can measure anything (it is on, and the camera sees the ground)."""
        return self._ground_motion() is not None

    def follow_speed(self, speed_mps: float | None) -> None:
        """Search with the cap the estimated ``speed_mps`` calls for (:meth:`~dem_graph.frontend.search_cap.GroundMotionPx.cap_for_speed`)
        when ``tracker.search_cap_follows_speed``; never below the cap configured."""
        if speed_mps is None or not self.config.tracker.search_cap_follows_speed:
            return
        cap = self._cap_formula.cap_for_speed(self._base_cap_px, float(speed_mps))
        if cap != self.tracker.config.max_search_half_size_px:
            self.counters["search_cap_changes"] += 1
            self.tracker.config.max_search_half_size_px = cap

    # --- tracking ----------------------------------------------------------------------------
    def template_warps(self, point_ids, X_world: np.ndarray, T_world_cam: np.ndarray, half_m: float = 0.15) -> np.ndarray | None:
        """Per point, the matrix that samples its template from its stored patch (for
        ``track``), through the homography the horizontal ground plane through the point induces
        between the patch's view and the current one ``T_world_cam``. (n,3,3), NaN where it
        cannot be formed (then the patch is used unwarped); None when warping is off."""
        n = len(point_ids)
        if not self.config.warp_patches:
            return None
        if n == 0:
            return np.zeros((0, 3, 3))
        store = self.patches
        slots = store.slots(point_ids)
        X = np.ascontiguousarray(X_world, dtype=float).reshape(n, 3)
        H = ground_homographies(X, store.T_world_cam_source[slots], np.ascontiguousarray(T_world_cam, dtype=float), self.camera.intrinsics_array, float(half_m))
        return self.tracker.template_warps(store.centers_px[slots], store.regions.shape[1] // 2, H)

    def templates(self, point_ids, warps: np.ndarray | None) -> np.ndarray:
        """(n,t,t) float32: each point's template, its patch warped by its matrix of
        :meth:`template_warps` (``warps`` None, or a matrix with NaN: the patch unwarped)."""
        tracker = self.tracker
        side = 2 * self.config.tracker.patch_half_size_px + 1
        ids = np.asarray(point_ids, dtype=np.int64)
        out = np.empty((len(ids), side, side), dtype=np.float32)
        warped = np.zeros(len(ids), dtype=bool) if warps is None else np.isfinite(warps[:, 2, 2])
        for k in np.flatnonzero(~warped).tolist():
            out[k] = tracker.template(self.tracks[int(ids[k])].patch)
        if warped.any():  # in one compiled pass, reading the regions where they are kept
            out[warped] = tracker.warp_regions(self.patches.regions, self.patches.slots(ids[warped]), warps[warped])
        return out

    def track(self, image, point_id: int, template: np.ndarray, uv_pred, S_px2=None, half_size_px=None, t_s: float = 0.0, T_world_cam=None) -> TrackResult:
        """Track one point with its ``template`` (one of :meth:`templates`), searched around
        ``uv_pred`` in the chi-square region of ``S_px2`` or the square of ``half_size_px``. With
        ``refresh_patch_every``, the patch is re-recorded at the match (taken at ``t_s`` from the
        camera pose estimate ``T_world_cam``). For the point-by-point PTPM; :meth:`track_many`
        tracks a frame's points at once, with the same outcome."""
        result = self.tracker.track(image, template, uv_pred, S_px2=S_px2, half_size_px=half_size_px)
        if self.record_view:
            self._view(t_s).add(self.tracks[point_id].kind, uv_pred, result.search_half_size_px, (np.nan, np.nan) if result.uv_px is None else result.uv_px)
        self._record(image, point_id, result.status, result.uv_px, t_s, T_world_cam)
        return result

    def track_many(self, image, point_ids, templates: np.ndarray, uv_pred: np.ndarray, S_px2=None, half_size_px=None, t_s: float = 0.0, T_world_cam=None) -> TrackBatch:
        """:meth:`track` for ``n`` points at once, with their :meth:`templates` (n,t,t), predictions
        (n,2) and covariances (n,2,2) (or one ``half_size_px``); the outcome as
        :meth:`PatchTracker.track_many` gives it. Counters, misses and patch refreshes follow the
        points' order, as with one :meth:`track` call per point."""
        batch = self.tracker.track_many(image, templates, uv_pred, S_px2=S_px2, half_size_px=half_size_px)
        ids = np.asarray(point_ids, dtype=np.int64)
        if self.record_view:
            self._view(t_s).add([self.tracks[p].kind for p in ids.tolist()], uv_pred, batch.search_half_size_px, batch.uv_px)  # uv_px: NaN unless matched
        self._record_many(image, ids, batch, t_s, T_world_cam)
        return batch

    def _view(self, t_s: float) -> TrackedView:
        """The record of the frame at ``t_s``'s searches (a new one for a new frame)."""
        if self.last_view is None or self.last_view.t_s != t_s:
            self.last_view = TrackedView(float(t_s))
        return self.last_view

    def _record(self, image, point_id: int, status: TrackStatus, uv, t_s: float, T_world_cam) -> None:
        """A track's outcome: counters, misses, and the patch refreshed every ``refresh_patch_every`` matches."""
        track = self.tracks[point_id]
        self.counters[_TRACK_COUNTER[status]] += 1
        if status is not TrackStatus.OK:
            track.misses += 1
        elif self._matched(track, T_world_cam):
            self._refresh_patch(track, image, uv, t_s, T_world_cam)

    def _record_many(self, image, point_ids: np.ndarray, batch: TrackBatch, t_s: float, T_world_cam) -> None:
        """:meth:`_record` for every point of a batch, without a call per point: the same counters
        (each status's count, first added in the order the points first have it), misses and refreshes."""
        for status, count in batch.status_counts():
            self.counters[_TRACK_COUNTER[status]] += count
        tracks = self.tracks
        for point_id in point_ids[~batch.ok].tolist():
            tracks[point_id].misses += 1
        for i in np.flatnonzero(batch.ok).tolist():
            track = tracks[int(point_ids[i])]
            if self._matched(track, T_world_cam):
                self._refresh_patch(track, image, batch.uv_px[i], t_s, T_world_cam)

    def _matched(self, track: PointTrack, T_world_cam) -> bool:
        """A track matched: its misses reset and its matches counted. Returns whether its patch is due
        for a refresh (every ``refresh_patch_every`` matches, with the camera pose to cut it from)."""
        track.misses = 0
        track.n_tracked += 1
        every = self.config.refresh_patch_every
        return bool(every) and T_world_cam is not None and track.n_tracked % every == 0

    def _refresh_patch(self, track: PointTrack, image, uv, t_s: float, T_world_cam) -> None:
        """The track's patch re-cut at its match ``uv`` in this frame (when it can be)."""
        patch = self.tracker.make_patch(image, uv, t_s)
        if patch is not None:
            track.patch = patch
            track.T_world_cam_source = np.array(T_world_cam)
            self.patches.put(track.point_id, patch, track.T_world_cam_source)
            track.segment += 1
            self.counters["patch_refreshed"] += 1

    # --- new points --------------------------------------------------------------------------
    def focus_area(self, speed_mps: float | None) -> FocusArea:
        return FocusArea.for_speed(self.config.focus, self.rig, speed_mps)

    def _budget(self, kind: PointKind) -> int:
        live = len(self.tracks)
        free = self.config.max_points - live
        if kind == PointKind.LASER:
            n_laser = sum(1 for t in self.tracks.values() if t.kind == PointKind.LASER)
            free = min(free, self.config.max_laser_points - n_laser, self.config.laser_points_per_scan)
        return max(free, 0)

    def _far_from_each(self, uv: np.ndarray, occupied_uv: np.ndarray) -> list[bool]:
        """Per pixel of ``uv`` (m,2): whether it is at least ``min_separation_px`` from every pixel of ``occupied_uv`` (n,2)."""
        if len(occupied_uv) == 0:
            return [True] * len(uv)
        return (np.sum((occupied_uv[None, :, :] - uv[:, None, :]) ** 2, axis=2).min(axis=1) >= self.config.min_separation_px**2).tolist()

    def _register(self, kind: PointKind, image, uv, t_s, T_world_cam) -> int | None:
        patch = self.tracker.make_patch(image, uv, t_s)
        if patch is None:
            self.counters["seed_untrackable"] += 1
            return None
        point_id = self._next_id
        self._next_id += 1
        self.tracks[point_id] = track = PointTrack(point_id, kind, patch, np.array(T_world_cam), t_s)
        self.patches.put(point_id, patch, track.T_world_cam_source)
        self.counters["added_laser" if kind == PointKind.LASER else "added_camera"] += 1
        return point_id

    def new_laser_points(self, ranges_m, T_body_laser_now: np.ndarray, image, t_s, T_world_body, focus: FocusArea, occupied_uv: np.ndarray) -> list[NewPoint]:
        """Points from one scan: ``T_body_laser_now`` places the laser (at the scan's time) in the
        current body frame (the paper's Eq. 2 with the spline-interpolated pose)."""
        budget = self._budget(PointKind.LASER)
        laser = self.rig.laser
        valid = laser.valid_ranges(ranges_m)
        if budget == 0 or not valid.any():
            return []
        dirs = laser.beam_directions()
        beams = np.flatnonzero(valid)
        p_body = transform_points(T_body_laser_now, dirs[beams] * ranges_m[beams, None])
        in_focus = focus.contains(p_body)
        beams, p_body = beams[in_focus], p_body[in_focus]
        if len(beams) == 0:
            return []
        uv, in_front = self.camera.project(transform_points(self.T_cam_body, p_body))
        ok = in_front & self.camera.in_image(uv, self.config.image_margin_px + self.config.tracker.patch_half_size_px)
        beams, p_body, uv = beams[ok], p_body[ok], uv[ok]
        # spread: evenly spaced candidates along the scan
        order = np.linspace(0, len(beams) - 1, min(len(beams), 2 * budget + 1)).round().astype(int) if len(beams) else []
        R_ray = T_body_laser_now[:3, :3]
        sigma_r = laser.range_sigma_m
        out: list[NewPoint] = []
        for k, point_id in self._seed(PointKind.LASER, np.unique(order), uv, budget, occupied_uv, image, t_s, T_world_body):
            d = R_ray @ dirs[beams[k]]
            Sigma = sigma_r**2 * np.outer(d, d) + self.config.interpolation_sigma_m**2 * np.eye(3)
            out.append(NewPoint(point_id, PointKind.LASER, p_body[k], Sigma))
        return out

    def _seed(self, kind: PointKind, candidates, uv: np.ndarray, budget: int, occupied_uv: np.ndarray, image, t_s: float, T_world_body: np.ndarray):
        """Yield ``(candidate index, new point id)`` for candidates in order, at most ``budget``, each
        at least ``min_separation_px`` from live and newly seeded points and with a trackable patch.
        The distances to the live points are taken for ``_SEED_CHUNK`` candidates at a time (the same
        squared distances as one candidate at a time), to the seeded ones per candidate."""
        T_world_cam = T_world_body @ self.T_body_cam
        live = np.asarray(occupied_uv, dtype=float).reshape(-1, 2)
        seeded = np.empty((budget, 2))
        n = 0
        candidates = np.fromiter(candidates, dtype=np.int64)
        for start in range(0, len(candidates), _SEED_CHUNK):
            chunk = candidates[start : start + _SEED_CHUNK]
            for k, far in zip(chunk.tolist(), self._far_from_each(uv[chunk], live)):
                if n >= budget:
                    return
                if not far or not self._far_from_each(uv[k : k + 1], seeded[:n])[0]:
                    continue
                point_id = self._register(kind, image, uv[k], t_s, T_world_cam)
                if point_id is None:
                    continue
                seeded[n] = uv[k]
                n += 1
                yield k, point_id

    def new_camera_points(self, image, t_s, T_world_body, focus: FocusArea, live_points_body: np.ndarray, occupied_uv: np.ndarray) -> list[NewPoint]:
        """Points at the empty focus cells, on the ground the live points around them make
        (:func:`ground_plane_through`), or on the body's ground plane (``camera_point_ground``)."""
        budget = self._budget(PointKind.CAMERA)
        if budget == 0:
            return []
        cells = focus.cell_centers_body()
        if self.config.camera_point_ground == "live_points":
            plane = ground_plane_through(live_points_body, focus)
            if plane is not None:
                cells[:, 2] = plane[0] + plane[1] * cells[:, 0] + plane[2] * cells[:, 1]
            self.counters["camera_seed_on_live_plane" if plane is not None else "camera_seed_on_body_plane"] += 1
        taken = np.zeros(len(cells), dtype=bool)
        if len(live_points_body):
            idx = focus.cell_of(live_points_body)
            taken[idx[idx >= 0]] = True
        free = np.flatnonzero(~taken)
        if len(free) == 0:
            return []
        uv, in_front = self.camera.project(transform_points(self.T_cam_body, cells[free]))
        ok = in_front & self.camera.in_image(uv, self.config.image_margin_px + self.config.tracker.patch_half_size_px)
        free, uv = free[ok], uv[ok]
        o = self.T_body_cam[:3, 3]
        out: list[NewPoint] = []
        for k, point_id in self._seed(PointKind.CAMERA, range(len(free)), uv, budget, occupied_uv, image, t_s, T_world_body):
            p = cells[free[k]]
            ray = p - o
            depth = np.linalg.norm(ray)
            r = ray / depth
            sin_elev = max(abs(r[2]), 0.05)
            sigma_along = self.config.camera_point_sigma_height_m / sin_elev
            sigma_across = self.config.camera_point_sigma_px * depth / self.camera.fx_px
            Sigma = sigma_along**2 * np.outer(r, r) + sigma_across**2 * (np.eye(3) - np.outer(r, r))
            out.append(NewPoint(point_id, PointKind.CAMERA, p, Sigma))
        return out

    def drop_points(self, point_ids, X_world: np.ndarray, T_world_body: np.ndarray, archive) -> tuple[np.ndarray, np.ndarray]:
        """Which live points to drop from the pose ``T_world_body`` (:meth:`drop_reasons`): calls
        ``archive(i, reason)`` for each, in index order; returns the mask of the points kept and
        their pixels (m,2)."""
        uv, reasons = self.drop_reasons(point_ids, X_world, T_world_body)
        keep = np.fromiter((r is None for r in reasons), dtype=bool, count=len(reasons))
        for i in np.flatnonzero(~keep).tolist():
            archive(i, reasons[i])
        return keep, uv[keep]

    def drop_reasons(self, point_ids, X_world: np.ndarray, T_world_body: np.ndarray) -> tuple[np.ndarray, list[str | None]]:
        """Which live points to drop from the pose ``T_world_body``: per point, ``"behind"``,
        ``"left_image"``, ``"lost"`` (too many misses) or None (kept); and every point's pixel (n,2)."""
        n = len(point_ids)
        if n == 0:
            return np.zeros((0, 2)), []
        T_body_world = invert(T_world_body)
        p_body = transform_points(T_body_world, X_world)
        uv, in_front = self.camera.project(transform_points(self.T_cam_body, p_body))
        visible = self.camera.in_image(uv, self.config.image_margin_px + self.config.tracker.patch_half_size_px)
        behind = ~np.asarray(in_front, dtype=bool) | (p_body[:, 0] < 0.0)
        reasons: list[str | None] = []
        # (Python scalars: the loop runs for every live point in every frame)
        for b, v, pid in zip(behind.tolist(), np.asarray(visible, dtype=bool).tolist(), np.asarray(point_ids, dtype=np.int64).tolist()):
            if b:
                reasons.append("behind")
            elif not v:
                reasons.append("left_image")
            elif self.tracks[pid].misses >= self.config.max_misses:
                reasons.append("lost")
            else:
                reasons.append(None)
        return uv, reasons

    def new_points(self, image, t_s: float, T_world_body: np.ndarray, scans, history, live_X_world: np.ndarray, occupied_uv: np.ndarray, speed_mps: float | None) -> list[NewPoint]:
        """New laser points from ``scans`` (each placed with the pose ``history`` at its time: Eq. 2),
        then camera points at the empty focus cells; away from the live points' pixels ``occupied_uv``.
        Positions are in the body frame of ``T_world_body``.

        A scan taken during the camera gap this frame ends (:meth:`begin_frame`) seeds nothing: the
        pose at its time is only a guess (interpolated across frames that did not come, or predicted
        at frames without texture), centimetres off the path (a degree of pitch is 5 cm at 3 m), while
        a laser point claims millimetres; tracked, such points would pull the pose after the gap off
        by their error (``scan_in_camera_gap`` counts them). The next frame's search cap follows
        ``speed_mps`` (:meth:`follow_speed`)."""
        self.follow_speed(speed_mps)
        focus = self.focus_area(speed_mps)
        T_body_world = invert(T_world_body)
        new: list[NewPoint] = []
        for scan in scans:
            if self._gap_s is not None and self._gap_s[0] < scan.t_s <= self._gap_s[1]:
                self.counters["scan_in_camera_gap"] += 1
                continue
            T_body_laser_now = T_body_world @ history.at(scan.t_s) @ self.rig.T_body_laser
            pts = self.new_laser_points(scan.ranges_m, T_body_laser_now, image, t_s, T_world_body, focus, occupied_uv)
            if pts:
                occupied_uv = np.concatenate([occupied_uv, self.camera.project(transform_points(self.T_cam_body, np.array([p.p_body for p in pts])))[0]])
            new.extend(pts)
        live_body = transform_points(T_body_world, live_X_world) if len(live_X_world) else np.zeros((0, 3))
        if new:
            live_body = np.concatenate([live_body, np.array([p.p_body for p in new])])
        new.extend(self.new_camera_points(image, t_s, T_world_body, focus, live_body, occupied_uv))
        return new

    def drop(self, point_id: int, reason: str) -> PointTrack:
        self.counters[f"dropped_{reason}"] += 1
        self.patches.remove(point_id)
        return self.tracks.pop(point_id)
