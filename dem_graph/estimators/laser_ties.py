"""Laser ties: landmarks tied to the scans of their ground, for a laser whose line the camera never
sees (on a bumper, below the image; :func:`~dem_graph.geometry.ground_view.laser_view`).

The paper's method needs a laser return on an image point when the scan is taken. A smoother does
not: the camera tracks the ground ahead, and some tenths of a second later the laser's line passes
over the same ground (or passed over it before, for a laser looking further than the camera). While
the landmark and the keyframe of that scan are both in the window, the landmark can take the
laser's height of its ground, measured from that keyframe: the scale and the tilt then come from
the laser's ranges, not from the camera height the flat-ground seeds guess.

Each keyframe keeps its scans' returns near its ground in its own body frame (the pose at each
scan's time from the pose history's spline, as for laser points: Eq. 2). At each keyframe, every
landmark of the window not yet tied is brought into each keyframe's frame of the window (their latest
estimates) and looked up among that keyframe's returns: the keyframe with most returns within
``radius_m`` of it across the ground (x, y) gives its ground height, their median, when they lie on a
locally flat surface (spread under ``flat_sigma_m``) and within ``gate_m`` of the landmark's own
height. The tie is a point-in-frame measurement of the landmark in that keyframe: its x, y where the
landmark is now (``sigma_xy_m``, loose: the laser does not say where across the ground the camera's
point is), its height the laser's (the range
noise and the returns' spread, tight). A landmark is tied once.

The ties give the ground relative to the vehicle, in the rig's body frame. A rig mounted some degrees
or centimetres off (the camera's pitch and height guessed) keeps the scale right (the laser-camera
transform is a calibration's) but tilts the whole map: the vehicle drives along the ground it sees
tilted. The graph starts with the start pose's roll, pitch and height free (:data:`LEVEL_START_SIGMAS`)
and the ground tied in the first ``level_s`` seconds decides, once that time has passed: a plane
fitted to it in the start pose's frame within ``mount_off_m`` of the ground under the vehicle (body
z = 0) and within ``mount_off_deg`` of level: the mount agrees, and the start pose's own prior is put
back (``pin_start``); otherwise a warning names the rig, and those landmarks define the world's level
instead: each on the start pose's ground plane, within ``sigma_level_m``. Ground whose slope changes
by more than ``mount_off_deg`` within those first metres is taken for a mount off.
"""

from __future__ import annotations

import logging
from collections import Counter, deque
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.spatial import cKDTree

from dem_graph.datasets.events import LaserScan
from dem_graph.frontend.pose_history import PoseHistory
from dem_graph.geometry.rig import SensorRig
from dem_graph.geometry.se3 import invert, transform_points

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class LaserTieSettings:
    radius_m: float = 0.15  # returns this close to a landmark across the ground (x, y) measure its ground
    min_returns: int = 3  # at least this many of them
    flat_sigma_m: float = 0.05  # their heights' spread at most this (a wall or a kerb edge is no ground height)
    gate_m: float = 0.5  # the laser's ground height within this of the landmark's own
    sigma_xy_m: float = 1.0  # the tie across the ground: loose
    keep_s: float = 2.0  # scans kept this long (the keyframe must also still be in the window)
    near_ground_m: float = 1.0  # only returns within this of the body's ground plane are kept (not the walls' and trees' above)
    level_s: float = 1.0  # the ground tied in this first part of the run decides whether the mount agrees with it, and if not levels the world
    mount_off_m: float = 0.05  # the plane of that ground further than this from the start pose's ground (body z = 0) under the vehicle...
    mount_off_deg: float = 1.0  # ... or tilted more than this against it: the mount is off, the world levelled
    min_level_ties: int = 20  # at least this many ties of that ground to decide (fewer: the start pose's prior as given)
    sigma_level_m: float = 0.1  # how far from the start pose's ground plane the ground swept then may lie (a road's camber and undulation over some metres; many landmarks make the plane far tighter), metres


@dataclass(frozen=True)
class LaserTies:
    """Ties for one keyframe message: per tie, the keyframe and frame it is measured from, the
    landmark, its position in that keyframe's body frame (metres) and the covariance (3x3, m^2)."""

    keyframes: np.ndarray  # (n,) int
    frames: np.ndarray  # (n,) int: the frame number of each keyframe (the batch's pose)
    landmarks: np.ndarray  # (n,) int
    p_frame: np.ndarray  # (n,3)
    Sigma_frame: np.ndarray  # (n,3,3)
    level_landmarks: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))  # (l,) landmarks of the start's ground, on the start pose's ground plane (the world's level)
    level_mean: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # (l,3) their world-frame priors (level_prior)
    level_Sigma: np.ndarray = field(default_factory=lambda: np.zeros((0, 3, 3)))  # (l,3,3)
    pin_start: np.ndarray | None = None  # 6x6: the start pose's own prior back (the mount agrees with the laser's ground), sent once

    def __len__(self) -> int:
        return len(self.landmarks)


NO_TIES = LaserTies(np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64), np.zeros((0, 3)), np.zeros((0, 3, 3)))


LEVEL_START_SIGMAS = np.array([0.1, 0.1, 1e-4, 1e-4, 1e-4, 0.2])
"""The start pose's prior sigmas with the world levelled by the laser ([roll, pitch, yaw] rad, [x, y, z] m,
body frame): the rig's mount may be off by some degrees and decimetres; x, y and yaw stay the start's."""


def level_start_covariance(P0: np.ndarray) -> np.ndarray:
    """The start pose's prior ``P0`` with its roll, pitch and height let free (:data:`LEVEL_START_SIGMAS`)."""
    P = np.array(P0, dtype=float)
    for i in (0, 1, 5):
        P[i, :] = 0.0
        P[:, i] = 0.0
        P[i, i] = LEVEL_START_SIGMAS[i] ** 2
    return P


def level_prior(T_world_start: np.ndarray, X_world: np.ndarray, sigma_m: float) -> tuple[np.ndarray, np.ndarray]:
    """A prior putting a landmark near ``X_world`` on the ground plane of the start pose (its body z = 0):
    the mean (``X_world`` moved onto the plane) and the covariance (``sigma_m`` across the plane, 10 m along it)."""
    n = np.asarray(T_world_start, dtype=float)[:3, 2]
    o = np.asarray(T_world_start, dtype=float)[:3, 3]
    X = np.asarray(X_world, dtype=float)
    mean = X - float(n @ (X - o)) * n
    Sigma = 100.0 * (np.eye(3) - np.outer(n, n)) + sigma_m**2 * np.outer(n, n)
    return mean, Sigma


@dataclass
class _KeptScans:
    keyframe: int
    frame: int
    t_s: float
    p_body: np.ndarray  # (n,3) returns in the keyframe's body frame
    tree: cKDTree  # of their x, y


class LaserTieMaker:
    """The scans kept per keyframe and the landmarks tied so far (see the module's notes)."""

    def __init__(
        self, rig: SensorRig, T_world_start: np.ndarray, P_start: np.ndarray, t_start_s: float, counters: Counter | None = None, settings: LaserTieSettings | None = None
    ):
        self.settings = settings or LaserTieSettings()
        self._T_world_start = np.array(T_world_start, dtype=float)
        self._P_start = np.array(P_start, dtype=float)  # the start pose's own prior, put back when the mount agrees
        self.start: str | None = None  # "pinned" (the mount agrees with the laser's ground) or "levelled"; None until level_s has passed
        self._start_ground: dict[int, np.ndarray] = {}  # landmark -> its tie's world point, for the ties of the first level_s
        self._level_until_s = t_start_s + self.settings.level_s
        self._laser = rig.laser
        self._T_body_laser = np.asarray(rig.T_body_laser, dtype=float)
        self._dirs = rig.laser.beam_directions()
        self._kept: deque[_KeptScans] = deque()
        self._tied: set[int] = set()
        self.counters = counters if counters is not None else Counter()  # laser_ties, and the lookups refused: laser_ties_not_flat, laser_ties_gated

    def add_scans(self, keyframe: int, frame: int, t_s: float, T_world_body: np.ndarray, scans: list[LaserScan], history: PoseHistory) -> None:
        """The scans up to keyframe ``keyframe`` (frame number ``frame``, at ``t_s`` with the pose
        ``T_world_body``), each placed with the pose ``history`` gives its time; older kept scans
        beyond ``keep_s`` are let go."""
        s = self.settings
        T_body_world = invert(T_world_body)
        parts = []
        for scan in scans:
            r = np.asarray(scan.ranges_m, dtype=float)
            valid = self._laser.valid_ranges(r)
            if not valid.any():
                continue
            T_kf_laser = T_body_world @ history.at(scan.t_s) @ self._T_body_laser
            parts.append(transform_points(T_kf_laser, self._dirs[valid] * r[valid, None]))
        if parts:
            p_body = np.concatenate(parts)
            p_body = p_body[np.abs(p_body[:, 2]) <= s.near_ground_m]
            self._kept.append(_KeptScans(keyframe, frame, t_s, p_body, cKDTree(p_body[:, :2])))
        while self._kept and self._kept[0].t_s < t_s - s.keep_s:
            self._kept.popleft()

    def _decide_start(self, t_s: float) -> dict:
        """Once ``t_s`` is past the first ``level_s``: pinned or levelled (see the module's notes). Returns
        the :class:`LaserTies` fields that carry the decision (the start pose's prior, or the level priors
        of the start's ground), once; empty otherwise."""
        if self.start is not None or t_s <= self._level_until_s:
            return {}
        s = self.settings
        points = np.array(list(self._start_ground.values())).reshape(-1, 3)
        if len(points) < s.min_level_ties:
            self.start = "pinned"
            return {"pin_start": self._P_start.copy()}
        p = transform_points(invert(self._T_world_start), points)
        A = np.column_stack([np.ones(len(p)), p[:, 0], p[:, 1]])
        (height_m, slope_x, slope_y), *_ = np.linalg.lstsq(A, p[:, 2], rcond=None)
        tilt_deg = float(np.degrees(np.arctan(np.hypot(slope_x, slope_y))))
        self.counters["laser_start_ground_mm"] = int(round(1000.0 * height_m))
        self.counters["laser_start_ground_tilt_mdeg"] = int(round(1000.0 * tilt_deg))
        if abs(height_m) <= s.mount_off_m and tilt_deg <= s.mount_off_deg:
            self.start = "pinned"
            return {"pin_start": self._P_start.copy()}
        self.start = "levelled"
        log.warning(
            "the laser's ground over the first %.1f s lies %.0f cm %s and %.1f degrees tilted against the rig's ground under the vehicle: the "
            "camera's and laser's mount in the rig is probably off; the world's level is taken from that ground",
            s.level_s, 100.0 * abs(height_m), "above" if height_m > 0 else "below", tilt_deg,
        )  # fmt: skip
        landmarks = np.array(list(self._start_ground), dtype=np.int64)
        priors = [level_prior(self._T_world_start, X, s.sigma_level_m) for X in points]
        self.counters["laser_ties_level"] = len(landmarks)
        return {"level_landmarks": landmarks, "level_mean": np.array([m for m, _ in priors]), "level_Sigma": np.array([S for _, S in priors])}

    def ties(self, poses: dict[int, np.ndarray], landmarks: np.ndarray, X_world: np.ndarray, t_now_s: float) -> LaserTies:
        """Ties of the ``landmarks`` (m,) at ``X_world`` (m,3), not tied before, to the kept scans of
        the keyframes in ``poses`` (keyframe -> T_world_body, the latest estimates: the window), at
        the keyframe of ``t_now_s`` (and the start's decision, once due). Each
        keyframe's returns are searched in its own body frame (their across-the-ground tree made once),
        the landmarks brought into it; a landmark takes the keyframe with most returns about it."""
        s = self.settings
        kept = [e for e in self._kept if e.keyframe in poses]
        fresh = np.array([int(lm) not in self._tied for lm in landmarks], dtype=bool) if len(landmarks) else np.zeros(0, dtype=bool)
        if not kept or not fresh.any():
            return self._finish(NO_TIES, t_now_s)
        landmarks, X_world = np.asarray(landmarks)[fresh], np.asarray(X_world, dtype=float)[fresh]
        X_body = np.array([transform_points(invert(poses[e.keyframe]), X_world) for e in kept])  # (kept, m, 3)
        counts = np.array([e.tree.query_ball_point(X[:, :2], s.radius_m, return_length=True) for e, X in zip(kept, X_body)])
        best = np.argmax(counts, axis=0)  # per landmark: the kept scans with most returns about it
        sigma_r2 = self._laser.range_sigma_m**2
        out_k, out_f, out_lm, out_p, out_S = [], [], [], [], []
        for j in np.flatnonzero(counts[best, np.arange(len(landmarks))] >= s.min_returns):
            e, p_lm = kept[int(best[j])], X_body[best[j], j]
            T = poses[e.keyframe]
            z = e.p_body[e.tree.query_ball_point(p_lm[:2], s.radius_m), 2]
            spread = float(np.std(z))
            if spread > s.flat_sigma_m:
                self.counters["laser_ties_not_flat"] += 1
                continue
            z_ground = float(np.median(z))
            if abs(z_ground - p_lm[2]) > s.gate_m:
                self.counters["laser_ties_gated"] += 1
                continue
            p_tie = np.array([p_lm[0], p_lm[1], z_ground])
            out_k.append(e.keyframe)
            out_f.append(e.frame)
            out_lm.append(int(landmarks[j]))
            out_p.append(p_tie)
            # tight along the world's vertical (the range noise and the ground's roughness under the point), loose across it
            R = T[:3, :3]
            out_S.append(R.T @ np.diag([s.sigma_xy_m**2, s.sigma_xy_m**2, sigma_r2 + spread**2]) @ R)
            if self.start is None and e.t_s <= self._level_until_s:
                self._start_ground[int(landmarks[j])] = transform_points(T, p_tie[None])[0]
            self._tied.add(int(landmarks[j]))
        self.counters["laser_ties"] += len(out_lm)
        if not out_lm:
            return self._finish(NO_TIES, t_now_s)
        return self._finish(LaserTies(np.array(out_k, dtype=np.int64), np.array(out_f, dtype=np.int64), np.array(out_lm, dtype=np.int64), np.array(out_p), np.array(out_S)), t_now_s)

    def _finish(self, ties: LaserTies, t_s: float) -> LaserTies:
        """``ties`` with the start's decision when it is made (the level priors, or the start pose's prior back)."""
        decided = self._decide_start(t_s)
        return replace(ties, **decided) if decided else ties

__all__ = ["LEVEL_START_SIGMAS", "NO_TIES", "LaserTieMaker", "LaserTieSettings", "LaserTies", "level_prior", "level_start_covariance"]
