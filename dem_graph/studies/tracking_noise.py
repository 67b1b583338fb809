"""How well the front end tracks: every tracked pixel against the true projection of its point.

The estimators weight a tracked pixel with ``frontend.sigma_px`` and treat frames as independent.
A tracker's errors are not independent: a patch that has slipped stays slipped for a few frames.
This module measures both the size of the errors and their correlation from frame to frame, and
from them the per-frame sigma that, frames treated as independent, carries the information a long
track really has.

The truth for a point is the ground under its seed pixel: the ray of that pixel, from the true
camera pose at the seed frame, cast onto the true terrain. Its true projection at every later frame
uses the true pose of that frame. Only a point's first patch segment is measured (a patch refresh
starts a new landmark whose seed pixel is not logged).

Each track's error is an offset (where its patch locked) plus a part that varies from frame to
frame and is correlated along the track (a slipped patch stays slipped for a while). The offset is
absorbed by the point's position (a few tenths of a pixel against the point's own uncertainty of
pixels), so the weight is set by the varying part: its standard deviation about the track's mean,
``sigma``, and its lag-1 correlation ``rho``. Modelled as AR(1), n frames of it carry the
information of n independent frames of ``sigma sqrt((1 + rho) / (1 - rho))`` (n large): the
``frontend.sigma_px`` to use. ``sigma_equivalent_px[n]`` also gives, without the model, the per-frame
sigma that n consecutive raw errors (offset included) are worth: ``sqrt(n var(their mean))``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dem_graph.datasets.base import Sequence
from dem_graph.errors import DemGraphError
from dem_graph.geometry.se3 import invert, transform_points
from dem_graph.pipeline.config import RunConfig, run_config
from dem_graph.pipeline.run import feed, make_estimator

WINDOWS = (1, 2, 5, 10, 20)


@dataclass(frozen=True)
class TrackingNoise:
    """Per image axis (u, v), pixels: the size of the tracked pixels' errors, their frame-to-frame
    correlation, and ``sigma_equivalent_px[n]``: the per-frame sigma at which ``n`` frames treated as
    independent carry the information ``n`` consecutive frames of one track really carry,
    ``sqrt(n var(mean of n consecutive errors))``. For independent errors it is the RMS for every n."""

    n_observations: int
    n_tracks: int
    median_track_frames: float
    mean_px: np.ndarray  # (2,) bias
    rms_px: np.ndarray  # (2,) raw errors
    offset_std_px: np.ndarray  # (2,) spread of the tracks' mean errors
    sigma_about_offset_px: np.ndarray  # (2,) about each track's mean (tracks of 3 frames or more)
    lag1_correlation: np.ndarray  # (2,) of consecutive errors about the track's mean
    sigma_equivalent_px: dict[int, np.ndarray]  # window n -> (2,), raw errors

    @property
    def sigma_weight_px(self) -> np.ndarray:
        """(2,) the per-frame sigma that carries the varying part's information, frames treated as
        independent: ``sigma sqrt((1 + rho) / (1 - rho))``."""
        rho = np.clip(self.lag1_correlation, 0.0, 0.999)
        return self.sigma_about_offset_px * np.sqrt((1.0 + rho) / (1.0 - rho))

    @property
    def recommended_sigma_px(self) -> float:
        """One sigma for both axes: the root mean square of the two axes' weight sigmas."""
        return float(np.sqrt(np.mean(self.sigma_weight_px**2)))

    def as_dict(self) -> dict:
        return {
            "observations": self.n_observations,
            "tracks": self.n_tracks,
            "median_track_frames": self.median_track_frames,
            "mean_px": self.mean_px.round(4).tolist(),
            "rms_px": self.rms_px.round(4).tolist(),
            "offset_std_px": self.offset_std_px.round(4).tolist(),
            "sigma_about_offset_px": self.sigma_about_offset_px.round(4).tolist(),
            "lag1_correlation": self.lag1_correlation.round(3).tolist(),
            "sigma_weight_px": self.sigma_weight_px.round(4).tolist(),
            "sigma_equivalent_px": {str(n): v.round(4).tolist() for n, v in self.sigma_equivalent_px.items()},
            "recommended_sigma_px": round(self.recommended_sigma_px, 3),
        }

    def table(self) -> str:
        head = f"{'tracking error, pixels':<44} {'u':>8} {'v':>8}"
        rows = [("mean (bias)", self.mean_px), ("RMS", self.rms_px), ("std of the tracks' offsets", self.offset_std_px)]
        rows += [("sigma about the track's offset", self.sigma_about_offset_px), ("its lag-1 correlation rho", self.lag1_correlation)]
        rows += [("weight sigma, sigma sqrt((1+rho)/(1-rho))", self.sigma_weight_px)]
        rows += [(f"raw errors: equivalent sigma over {n} frames", v) for n, v in self.sigma_equivalent_px.items()]
        lines = [head, "-" * len(head)] + [f"{name:<44} {a[0]:>8.3f} {a[1]:>8.3f}" for name, a in rows]
        lines.append(
            f"{self.n_observations} observations of {self.n_tracks} tracks (median {self.median_track_frames:g} frames); "
            f"recommended frontend.sigma_px: {self.recommended_sigma_px:.2f}"
        )
        return "\n".join(lines)


def tracking_noise_statistics(
    track: np.ndarray, frame: np.ndarray, error_px: np.ndarray, windows: tuple[int, ...] = WINDOWS
) -> TrackingNoise:
    """The statistics of tracking errors ``error_px`` (N,2), observed pixel minus true projection,
    of observation ``N`` of track ``track`` at camera frame ``frame``. A window takes ``n``
    consecutive frames of one track; windows do not overlap."""
    track = np.asarray(track, dtype=np.int64).reshape(-1)
    frame = np.asarray(frame, dtype=np.int64).reshape(-1)
    error_px = np.asarray(error_px, dtype=float).reshape(-1, 2)
    if not (len(track) == len(frame) == len(error_px)):
        raise DemGraphError(f"tracking errors: {len(track)} tracks, {len(frame)} frames and {len(error_px)} errors do not match")
    keep = np.isfinite(error_px).all(axis=1)
    track, frame, error_px = track[keep], frame[keep], error_px[keep]
    if len(error_px) < 2:
        raise DemGraphError(f"tracking errors: {len(error_px)} finite errors; at least 2 are needed")
    order = np.lexsort((frame, track))
    track, frame, error_px = track[order], frame[order], error_px[order]
    # runs of consecutive frames of one track: run id and position inside the run
    new_run = np.ones(len(track), dtype=bool)
    new_run[1:] = (track[1:] != track[:-1]) | (frame[1:] != frame[:-1] + 1)
    run_id = np.cumsum(new_run) - 1
    run_start = np.flatnonzero(new_run)
    position = np.arange(len(track)) - run_start[run_id]
    run_length = np.diff(np.append(run_start, len(track)))
    centred = error_px - error_px.mean(axis=0)
    sigma_eq = {}
    for n in windows:
        # window w of run r holds positions [w n, (w + 1) n); only whole windows count
        whole = (position // n + 1) * n <= run_length[run_id]
        if not whole.any():
            continue
        key = run_id[whole] * (int(run_length.max()) // n + 1) + position[whole] // n
        _, window = np.unique(key, return_inverse=True)
        sums = np.stack([np.bincount(window, weights=centred[whole, a]) for a in (0, 1)], axis=1)
        means = sums / n
        sigma_eq[n] = np.sqrt(n * np.mean(means**2, axis=0))
    # about each track's mean (the offset the point's position absorbs)
    _, track_index, track_frames = np.unique(track, return_inverse=True, return_counts=True)
    offsets = np.stack([np.bincount(track_index, weights=error_px[:, a]) for a in (0, 1)], axis=1) / track_frames[:, None]
    long_enough = track_frames[track_index] >= 3
    if not long_enough.any():
        raise DemGraphError("tracking errors: no track of 3 frames or more")
    deviation = error_px - offsets[track_index]
    dof = long_enough.sum() - np.count_nonzero(track_frames >= 3)
    sigma_about = np.sqrt(np.sum(deviation[long_enough] ** 2, axis=0) / dof)
    pairs = ~new_run[1:] & long_enough[1:]
    a, b = deviation[:-1][pairs], deviation[1:][pairs]
    lag1 = np.sum(a * b, axis=0) / np.sqrt(np.sum(a * a, axis=0) * np.sum(b * b, axis=0)) if pairs.any() else np.zeros(2)
    return TrackingNoise(
        n_observations=len(error_px),
        n_tracks=len(track_frames),
        median_track_frames=float(np.median(track_frames)),
        mean_px=error_px.mean(axis=0),
        rms_px=np.sqrt(np.mean(centred**2, axis=0)),
        offset_std_px=offsets.std(axis=0),
        sigma_about_offset_px=sigma_about,
        lag1_correlation=lag1,
        sigma_equivalent_px=sigma_eq,
    )


def tracking_errors(sequence: Sequence, log) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Track, frame and error (observed minus true pixel) of every observation in ``log`` (a
    :class:`~dem_graph.estimators.measurement_log.MeasurementLog`) of a point whose seed is logged,
    against the sequence's true trajectory and terrain."""
    from dem_graph.sim.raycast import TerrainScene

    truth = sequence.ground_truth
    if truth is None or truth.elevation is None:
        raise DemGraphError(f"{sequence.name}: measuring the tracking error needs the true terrain (a simulated dataset)")
    camera = sequence.rig.camera_model
    T_body_cam = np.asarray(sequence.rig.T_body_cam, dtype=float)
    T_world_cam = truth.trajectory.at(np.asarray(log.t_s)) @ T_body_cam
    seed_frame = np.asarray(log.seed_frame, dtype=np.int64)
    seed_landmark = np.asarray(log.seed_landmark, dtype=np.int64)
    if seed_frame.size == 0:
        raise DemGraphError(f"{sequence.name}: no point was tracked")
    p_cam = transform_points(invert(T_body_cam), np.array([s.p_body for s in log.seeds]))
    uv_seed, _ = camera.project(p_cam)
    R_world_cam = T_world_cam[seed_frame, :3, :3]
    d_world = np.einsum("nij,nj->ni", R_world_cam, camera.bearings_from_pixels(uv_seed))
    origins = T_world_cam[seed_frame, :3, 3]
    hits = TerrainScene(truth.elevation).cast(origins.astype(np.float32), d_world.astype(np.float32))
    t_hit = np.asarray(hits.t_hit_m, dtype=float)
    known = np.isfinite(t_hit)
    X_world = dict(zip(seed_landmark[known].tolist(), origins[known] + t_hit[known, None] * d_world[known], strict=True))

    frames, landmarks, uv = log.observations()
    has_truth = np.array([lm in X_world for lm in landmarks.tolist()], dtype=bool)
    frames, landmarks, uv = frames[has_truth], landmarks[has_truth], uv[has_truth]
    X = np.array([X_world[lm] for lm in landmarks.tolist()]).reshape(-1, 3)
    T_cam_world = invert(T_world_cam[frames])
    p = np.einsum("nij,nj->ni", T_cam_world[:, :3, :3], X) + T_cam_world[:, :3, 3]
    uv_true, ok = camera.project(p)
    return landmarks[ok], frames[ok], uv[ok] - uv_true[ok]


def measure_tracking_noise(sequence: Sequence, max_frames: int | None = None, config: RunConfig | None = None) -> TrackingNoise:
    """Run the front end (inside the graph estimator's online pass, which logs every observation)
    over ``sequence`` and measure its tracking errors."""
    config = (config or run_config(sequence)).model_copy(update={"estimator": "isam2-batch", "max_frames": max_frames})
    estimator = make_estimator(sequence, config)
    for _ in feed(estimator, sequence, max_frames, finish=False):
        pass
    return tracking_noise_statistics(*tracking_errors(sequence, estimator.log))


__all__ = ["TrackingNoise", "measure_tracking_noise", "tracking_errors", "tracking_noise_statistics"]
