"""The tracking-noise measurement: its statistics against errors of known law, and its truth (the
true projection of each tracked point) against a hand-made log of exact projections."""

from __future__ import annotations

import numpy as np
import pytest

from dem_graph.datasets.events import CameraFrame
from dem_graph.errors import DemGraphError
from dem_graph.estimators.measurement_log import MeasurementLog
from dem_graph.frontend.frontend import NewPoint
from dem_graph.geometry.se3 import invert, transform_points
from dem_graph.sim.raycast import TerrainScene
from dem_graph.studies.tracking_noise import tracking_errors, tracking_noise_statistics


def _tracks(n_tracks: int, length: int, sigma_white: float, sigma_ar: float, rho: float, rng, sigma_offset: float = 0.0):
    """Errors of ``n_tracks`` tracks of ``length`` frames: a constant offset per track, plus white
    noise, plus a stationary AR(1); as (track, frame, error) in a shuffled order."""
    ar = np.zeros((n_tracks, length, 2))
    ar[:, 0] = rng.normal(0.0, sigma_ar, (n_tracks, 2))
    for k in range(1, length):
        ar[:, k] = rho * ar[:, k - 1] + rng.normal(0.0, sigma_ar * np.sqrt(1 - rho**2), (n_tracks, 2))
    errors = ar + rng.normal(0.0, sigma_white, ar.shape) + rng.normal(0.0, sigma_offset, (n_tracks, 1, 2))
    track = np.repeat(np.arange(n_tracks), length)
    frame = np.tile(np.arange(length), n_tracks) + 7 * track  # tracks start at different frames
    order = rng.permutation(track.size)  # the statistics must not depend on the input order
    return track[order], frame[order], errors.reshape(-1, 2)[order]


def _equivalent_sigma(n: int, sigma_white: float, sigma_ar: float, rho: float, sigma_offset: float = 0.0) -> float:
    """sqrt(n var(mean of n consecutive errors)) for an offset plus white noise plus a stationary AR(1)."""
    lags = np.abs(np.subtract.outer(np.arange(n), np.arange(n)))
    var_mean = sigma_offset**2 + sigma_white**2 / n + sigma_ar**2 * np.sum(rho**lags) / n**2
    return float(np.sqrt(n * var_mean))


def test_independent_errors_have_their_sigma_over_every_window():
    """White errors of 0.2 px: the equivalent sigma is 0.2 px for every window, within 5 % (about 3
    standard errors with 2000 windows of 20 frames); about each track's mean sigma is 0.2 px within
    2 % (the degrees of freedom counted) and the lag-1 correlation that of removing a mean."""
    track, frame, err = _tracks(2000, 20, 0.2, 0.0, 0.0, np.random.default_rng(0))
    noise = tracking_noise_statistics(track, frame, err)
    assert noise.n_tracks == 2000 and noise.median_track_frames == 20
    for n, sigma in noise.sigma_equivalent_px.items():
        assert sigma == pytest.approx([0.2, 0.2], rel=0.05), n
    assert noise.rms_px == pytest.approx([0.2, 0.2], rel=0.02)
    # about each 20-frame track's mean the lag-1 correlation is -1/19 in expectation
    assert noise.lag1_correlation == pytest.approx([-1 / 19] * 2, abs=0.02)
    assert noise.sigma_about_offset_px == pytest.approx([0.2, 0.2], rel=0.02)


def test_correlated_errors_weigh_as_fewer_frames():
    """Tracks of 1000 frames: an offset of 0.15 px per track plus an AR(1) of 0.13 px and rho 0.7.
    About each track's offset, sigma is found within 2 % and rho within 0.01 (a few standard errors;
    removing each track's mean biases both by under 1 % at this length), so the weight sigma
    0.13 sqrt(1.7 / 0.3) = 0.31 px within 3 %. The raw errors' equivalent sigma over n frames,
    offset included, follows its law within 5 %."""
    s_o, s_a, rho = 0.15, 0.13, 0.7
    track, frame, err = _tracks(100, 1000, 0.0, s_a, rho, np.random.default_rng(1), sigma_offset=s_o)
    noise = tracking_noise_statistics(track, frame, err)
    assert noise.sigma_about_offset_px == pytest.approx([s_a, s_a], rel=0.02)
    assert noise.lag1_correlation == pytest.approx([rho, rho], abs=0.01)
    assert noise.recommended_sigma_px == pytest.approx(s_a * np.sqrt((1 + rho) / (1 - rho)), rel=0.03)
    assert noise.offset_std_px == pytest.approx([s_o, s_o], rel=0.25)  # 100 tracks: 7 % standard error, plus their AR(1) means
    for n in (1, 2, 5, 10, 20):
        assert noise.sigma_equivalent_px[n] == pytest.approx([_equivalent_sigma(n, 0.0, s_a, rho, s_o)] * 2, rel=0.05), n


def test_windows_do_not_span_a_gap_in_a_track():
    """Frames 0-2 and 4-6 of one track (frame 3 missing), errors +1 then -1: windows of 3 are exactly
    the two runs, so the equivalent sigma over 3 frames is sqrt(3); the lag-1 correlation uses
    the 4 consecutive pairs only (all +1 * +1 or -1 * -1: correlation 1)."""
    frame = np.array([0, 1, 2, 4, 5, 6])
    err = np.repeat([[1.0, 1.0], [-1.0, -1.0]], 3, axis=0)
    noise = tracking_noise_statistics(np.zeros(6), frame[::-1], err[::-1], windows=(1, 3, 20))
    assert noise.sigma_equivalent_px[3] == pytest.approx([np.sqrt(3)] * 2, abs=1e-12)
    assert noise.lag1_correlation == pytest.approx([1.0, 1.0], abs=1e-12)
    assert 20 not in noise.sigma_equivalent_px  # no whole window of 20 frames


def test_mismatched_or_too_few_errors_are_refused():
    with pytest.raises(DemGraphError, match="do not match"):
        tracking_noise_statistics(np.zeros(3), np.zeros(2), np.zeros((3, 2)))
    with pytest.raises(DemGraphError, match="at least 2"):
        tracking_noise_statistics(np.zeros(2), np.arange(2), np.array([[0.1, 0.1], [np.nan, 0.0]]))


def test_errors_are_measured_against_the_true_projection(smoke_log):
    """A hand-made log on the smoke scenario: points seeded at frame 0 where chosen pixels' rays meet
    the true terrain, then observed at frames 1-9 at their exact projections through the true
    poses plus a known offset (0.3, -0.2) px. The measured errors are that offset within 0.01 px
    (the ray cast is in float32), for every observation, with the right track and frame."""
    truth = smoke_log.ground_truth
    camera, T_body_cam = smoke_log.rig.camera_model, np.asarray(smoke_log.rig.T_body_cam, dtype=float)
    t = np.array([e.t_s for e in smoke_log.events() if isinstance(e, CameraFrame)][:10])
    T_world_cam = truth.trajectory.at(t) @ T_body_cam
    uv_seed = np.array([[100.0, 180.0], [160.0, 200.0], [220.0, 170.0], [140.0, 220.0]])
    d_world = (T_world_cam[0, :3, :3] @ camera.bearings_from_pixels(uv_seed).T).T
    origin = np.repeat(T_world_cam[0, :3, 3][None], len(uv_seed), axis=0)
    t_hit = np.asarray(TerrainScene(truth.elevation).cast(origin.astype(np.float32), d_world.astype(np.float32)).t_hit_m, dtype=float)
    assert np.isfinite(t_hit).all()
    X_world = origin + t_hit[:, None] * d_world
    T_body_world0 = invert(truth.trajectory.at(t[:1])[0])
    log = MeasurementLog()
    landmarks = np.array([11, 12, 13, 14])
    offset = np.array([0.3, -0.2])
    for f in range(10):
        uv, ok = camera.project(transform_points(invert(T_world_cam[f]), X_world))
        assert ok.all()
        log.add_frame(t[f], np.eye(4), np.eye(6), landmarks if f else [], (uv + offset) if f else np.zeros((0, 2)))
        if f == 0:
            seeds = [
                NewPoint(int(lm), 0, transform_points(T_body_world0, X[None])[0], np.eye(3) * 1e-4)
                for lm, X in zip(landmarks, X_world, strict=True)
            ]
            log.add_seeds(0, seeds, landmarks)
    track, frame, err = tracking_errors(smoke_log, log)
    assert len(err) == 9 * len(landmarks)
    assert np.abs(err - offset).max() < 0.01
    assert sorted(set(track.tolist())) == landmarks.tolist() and sorted(set(frame.tolist())) == list(range(1, 10))


def test_a_sequence_without_true_terrain_is_refused(smoke_log):
    class NoTerrain:
        name = "no-terrain"
        ground_truth = None
        rig = smoke_log.rig

    with pytest.raises(DemGraphError, match="no-terrain: measuring the tracking error needs the true terrain"):
        tracking_errors(NoTerrain(), MeasurementLog())


def test_the_tracker_is_unbiased_and_sub_pixel_on_the_smoke_scenario(smoke_log):
    """The whole measurement on the smoke scenario (320x240, 4 m): the tracker's bias is under
    0.05 px and its RMS under 0.5 px on each axis."""
    from dem_graph.studies.tracking_noise import measure_tracking_noise

    noise = measure_tracking_noise(smoke_log)
    assert noise.n_observations > 1000
    assert np.all(np.abs(noise.mean_px) < 0.05) and np.all(noise.rms_px < 0.5)


def test_track_noise_command_on_a_dataset_without_terrain_says_so(tmp_path):
    """`dem-graph track-noise` on a folder that is not a dataset: a one-line error, exit code 2."""
    from click.testing import CliRunner

    from dem_graph.cli import main

    result = CliRunner().invoke(main, ["--no-progress", "research", "track-noise", str(tmp_path / "missing")])
    assert result.exit_code == 2
    assert "missing" in result.output and "Traceback" not in result.output
