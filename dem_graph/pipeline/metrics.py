"""A run's metrics: the typed :class:`RunMetrics` that ``metrics.json`` is written from, and the lines
``dem-graph run`` prints."""

from __future__ import annotations

import logging
from typing import Any

import numpy as np

from dem_graph.datasets.base import Sequence
from dem_graph.estimators.base import EstimatorResult
from dem_graph.estimators.odometry_only import ODOMETRY_BASELINE
from dem_graph.evaluation.dem_metrics import HeightErrors
from dem_graph.evaluation.results import MetricsModel, Number
from dem_graph.evaluation.timing import GraphUpdateTiming, PhaseTiming, frame_timing_summary, graph_update_timing
from dem_graph.evaluation.trajectory_metrics import (
    NeesSummary,
    TrajectoryAccuracy,
    accuracy_summary,
    nees_summary,
    pose_nees,
    within_truth_span,
)
from dem_graph.geometry.ground_view import laser_view
from dem_graph.pipeline.live_run import LiveMapMetrics
from dem_graph.pipeline.run_dem import DemFailure, DemMetrics

log = logging.getLogger(__name__)


class PointsPerFrame(MetricsModel):
    live_median: float  # live points per frame, median
    live_max: int
    tracked_median: float  # points tracked per frame, median


class TrackingYield(MetricsModel):
    """How the searches for live points ended, from the front end's ``track_*`` counters: the
    fraction matched, the fraction of those the pose update rejected as outliers, and why the rest
    failed (fractions of all searches, by the tracker's status, largest first)."""

    searches: int
    matched_fraction: float
    outlier_fraction_of_matched: float
    failed_fraction: dict[str, float]


def tracking_yield(counters: dict) -> TrackingYield | None:
    """The :class:`TrackingYield` of a run's counters; None when nothing was searched."""
    searches = {k.removeprefix("track_"): int(v) for k, v in counters.items() if k.startswith("track_")}
    total = sum(searches.values())
    if total == 0:
        return None
    matched = searches.pop("ok", 0)
    failed = {k: v / total for k, v in sorted(searches.items(), key=lambda kv: -kv[1]) if v}
    outliers = int(counters.get("outlier_rejected", 0))
    return TrackingYield(searches=total, matched_fraction=matched / total, outlier_fraction_of_matched=outliers / matched if matched else 0.0, failed_fraction=failed)


class StreamHealth(MetricsModel):
    """One input stream of a live source (the ROS 2 node): what came, and what did not as it should."""

    topic: str
    received: int  # messages taken off the wire and decoded
    rate_hz: Number = float("nan")  # the rig's rate of the stream (NaN: none)
    late: int = 0  # came after a later event of another stream had gone to the estimator (given to it out of order)
    waited_out: int = 0  # given to the estimator when the reorder window ran out, before every other stream had caught up
    missing: int = 0  # never came: gaps in the stamps beyond one and a half periods, counted in periods
    undecodable: int = 0  # bytes that were not a message of the topic's type


class LiveSourceMetrics(MetricsModel):
    """What a live source delivered (``metrics.json``'s ``live_source``): the ROS 2 node's streams, the
    transport's cost, and the faults of the graph it was on."""

    source: str  # "ROS 2 domain 0"
    streams: dict[str, StreamHealth]  # by stream: camera, camera_info, laser, odometry, imu, tf, tf_static
    transport_median_ms: Number = float("nan")  # per frame: its messages taken and decoded, its outputs encoded and written
    transport_p95_ms: Number = float("nan")
    # each frame, from its image on the wire: the image's write by its publisher to its take by the node
    # (one clock: a publisher on this machine), its wait for the other streams (the reorder buffer), and
    # its take to its outputs written
    camera_wire_median_ms: Number = float("nan")
    order_wait_median_ms: Number = float("nan")
    publish_median_ms: Number = float("nan")  # each frame's outputs: the local map over the save window, the messages made, encoded and written
    in_node_median_ms: Number = float("nan")
    in_node_p95_ms: Number = float("nan")
    frames_published: int = 0
    incompatible_qos: list[str] | None = None  # one line per topic and policy
    clock_resets: int = 0  # the sources' clocks went back (a player restarted): the run ended there
    frames_skipped: int = 0  # images further behind the newest one than --max-frame-lag-s when their turn came (the machine was slower than the camera)


class RunMetrics(MetricsModel):
    """Everything ``metrics.json`` holds. A field is None (and left out of the file) when it was not
    measured: no frame, no ground truth, no DEM, or (``dem-graph evaluate``) not in the run folder."""

    estimator: str | None = None  # the estimator's name (ekf-gm, ekf-ptpm, isam2, isam2-batch)
    frames: int | None = None
    elapsed_s: float | None = None  # the whole run, wall clock
    error: str | None = None  # why the run stopped early (its results go up to there)
    status: str | None = None  # "ok"; "stopped": it ended early (error); "failed": it ran to its end but measured nothing (failure)
    failure: str | None = None  # why a run that ran is not a result (:func:`tracking_failure`): the trajectory is the motion model's
    laser_view: str | None = None  # where the laser's line meets the ground against the ground the camera sees (geometry.ground_view)
    time_per_frame: dict[str, PhaseTiming] | None = None  # by phase: total, prediction, tracking, update, map, graph, ...
    graph_update: GraphUpdateTiming | None = None  # the graph estimator: its updates' time by phase (in its own process, when it has one)
    points_per_frame: PointsPerFrame | None = None
    tracking: TrackingYield | None = None  # how the searches for live points ended
    map_points: int | None = None  # points ever estimated
    events: dict[str, int | float] | None = None  # the estimator's counters (tracking outcomes, points added and dropped, ...)
    skipped_messages: dict[str, int] | None = None  # the log's messages the reader skipped, by stream and kind (odometry_nonfinite, camera_stamp_not_after, ...)
    trajectory: TrajectoryAccuracy | None = None  # the per-frame estimate against the truth
    # the estimators' extra trajectories (estimators.base.EXTRA_TRAJECTORIES), by their names
    trajectory_smoothed: TrajectoryAccuracy | None = None  # isam2: every frame as smoothed at the end of the run
    trajectory_online: TrajectoryAccuracy | None = None  # isam2-batch: its online pass
    pose_nees: NeesSummary | None = None
    dem: DemMetrics | DemFailure | None = None  # the DEM from the final poses, in hindsight
    live_map: LiveMapMetrics | None = None  # the map built while the run went, as the guidance had it
    live_source: LiveSourceMetrics | None = None  # a live source's streams (the ROS 2 node)
    dataset: str | None = None  # the dataset's path
    dataset_options: dict[str, Any] | None = None  # how it was opened (:meth:`Sequence.open_options`)


def compute_metrics(sequence: Sequence, res: EstimatorResult, error: str | None = None, elapsed_s: float = 0.0) -> RunMetrics:
    """A run's metrics, its DEM and its dataset aside: frames, time and points per frame, events, and
    against the truth the trajectory's accuracy (each extra trajectory's too) and the poses' NEES."""
    metrics = RunMetrics(estimator=res.name, frames=len(res.frames), elapsed_s=elapsed_s, error=error or None)
    metrics.skipped_messages = sequence.skipped_messages() or None
    metrics.status = "stopped" if metrics.error else "ok"
    metrics.laser_view = laser_view(sequence.rig).line()
    if not res.frames:
        return metrics
    phases = sorted({k for f in res.frames for k in f.timing_s})
    metrics.time_per_frame = frame_timing_summary({k: [f.timing_s.get(k, 0.0) for f in res.frames] for k in phases})
    metrics.graph_update = graph_update_timing(res.graph_update_s)
    live = np.array([f.n_live for f in res.frames])
    tracked = np.array([f.n_tracked for f in res.frames])
    metrics.points_per_frame = PointsPerFrame(live_median=float(np.median(live)), live_max=int(live.max()), tracked_median=float(np.median(tracked)))
    metrics.map_points = len(res.points)
    metrics.events = dict(sorted(res.counters.items()))
    metrics.tracking = tracking_yield(metrics.events)
    metrics.failure = tracking_failure(metrics)
    metrics.status = "stopped" if metrics.error else ("failed" if metrics.failure else "ok")
    gt = sequence.ground_truth
    if gt is not None and len(res.frames) > 1:
        est, covered = within_truth_span(res.trajectory(), gt.trajectory)
        if est is None:
            log.warning("the ground truth covers %d of the run's %d frames: no trajectory metrics", int(covered.sum()), len(covered))
            return metrics
        metrics.trajectory = accuracy_summary(est, gt.trajectory)
        for name, extra in res.extra_trajectories().items():
            extra_covered = within_truth_span(extra, gt.trajectory)[0]
            if extra_covered is not None:
                setattr(metrics, name, accuracy_summary(extra_covered, gt.trajectory))
        metrics.pose_nees = nees_summary(pose_nees(est.poses_se3, gt.trajectory.at(est.t_s), res.pose_covariances()[covered]))
    return metrics


def laser_cells_error_text(e: HeightErrors) -> str:
    """The DEM's height RMSE over the laser-swept cells as the summaries print it, or that there is
    no such cell (no laser return fell where the truth is known): never "nan cm"."""
    if e.cells == 0 or not np.isfinite(e.rmse_m):
        return "no laser-swept cell (no height RMSE)"
    return f"height RMSE {100 * e.rmse_m:.1f} cm over the laser-swept cells"


def graph_update_line(g: GraphUpdateTiming, events: dict) -> str:
    """The graph's updates in one line: their time, the window's cuts, how late the results came and
    the keyframes merged while the graph was behind, and the new points the graph's landmark bound
    kept in the front end."""
    line = f"graph: {g.updates} updates, median {g.total.median_ms:.1f} ms, p95 {g.total.p95_ms:.1f} ms"
    cut, rebuild = g.phases.get("cut"), g.phases.get("rebuild")
    if cut is not None and rebuild is not None:
        line += (
            f"; the window's {g.counts['cut']} cuts, made between results: marginal median {cut.median_ms:.1f} ms (p95 {cut.p95_ms:.1f}), "
            f"new iSAM2 median {rebuild.median_ms:.1f} ms (p95 {rebuild.p95_ms:.1f})"
        )
    if "graph_lag_keyframes_median" in events:
        line += f"; results {events['graph_lag_keyframes_median']} keyframes late (median), {events['graph_lag_keyframes_max']} at most"
    merged = int(events.get("keyframes_merged", 0))
    if merged:
        line += f"; {merged} keyframes merged while the graph was behind"
    own = int(events.get("points_front_end_only", 0))
    if own:
        line += f"; {own} new points kept in the front end only (graph_max_landmarks)"
    return line


LOW_YIELD_FRACTION = 0.25
"""Below this fraction of searches matched, a run's summary names the setting to look at (:func:`yield_advice`)."""

# why searches failed, and the setting a vehicle's speed or frame rate makes wrong for that reason
_ADVICE = {
    "search_too_large": "the predicted motion between frames is larger than the search allows: vehicle.speed_mps (the search cap is derived from it and the camera's rate) "
    "or frontend.tracker.max_search_half_size_px, and without odometry motion.initial_speed_mps and motion.sigma_*_acc",
    "out_of_image": "points leave the image before they are found again: vehicle.speed_mps, or frontend.focus (nominal_speed_mps, max_distance_m)",
    "low_texture": "the ground has little texture at the points chosen: frontend.tracker.min_patch_std_dn and frontend.focus.cell_size_m",
    "low_score": "the templates change too much between frames (a low frame rate, motion blur): the camera's rate, or frontend.tracker.min_score",
    "ambiguous": "repeated texture within the search regions: frontend.tracker.ambiguity_margin, or smaller regions (motion.sigma_*_acc)",
    "peak_at_border": "points tracked at the image border: frontend.focus, so that points lie further inside the image",
    "peak_outside_gate": "the motion model predicts badly: motion.sigma_*_acc, or frontend.tracker.refuse_peak_outside_gate off",
}


FAILED_YIELD_FRACTION = 0.10
"""Below this fraction of searches matched, the trajectory is the motion model's rather than a
measurement: the run failed (:func:`tracking_failure`), whatever files it wrote."""


def _main_failure(y: TrackingYield) -> tuple[str, float] | None:
    """The tracker's most frequent failure and its share of the searches; None when none failed."""
    if not y.failed_fraction:
        return None
    return max(y.failed_fraction.items(), key=lambda kv: kv[1])


def tracking_failure(m: RunMetrics, threshold: float = FAILED_YIELD_FRACTION) -> str | None:
    """Why a run that went to its end is not a result, in one line, or None: a tracking estimator
    (not the odometry baseline) that matched under ``threshold`` of its searches, or searched for no
    point at all over two frames or more, measured nothing; its trajectory is what the motion model
    predicted (odometry, the IMU, or a constant velocity), and its map is the scans laid along it."""
    if m.estimator == ODOMETRY_BASELINE or (m.frames or 0) < 2:
        return None
    y = m.tracking
    if y is None:
        return "no ground point was ever tracked (none chosen in the images): the trajectory is the motion model's alone"
    if y.matched_fraction >= threshold:
        return None
    return f"tracking failed: {100 * y.matched_fraction:.0f} % of {y.searches} searches matched (under {100 * threshold:.0f} %): the trajectory is the motion model's alone"


def yield_advice(y: TrackingYield | None, threshold: float = LOW_YIELD_FRACTION) -> str | None:
    """A warning naming the setting to look at when fewer than ``threshold`` of the searches matched
    (the main reason of the failures picks it); None when the yield is fine or nothing was searched."""
    if y is None or y.searches == 0 or y.matched_fraction >= threshold:
        return None
    main = _main_failure(y)
    if main is None:
        return f"warning: only {100 * y.matched_fraction:.0f} % of the searches matched (docs/guide/own_robot.md, tuning)"
    reason, share = main
    advice = _ADVICE.get(reason, "docs/guide/own_robot.md, tuning")
    return (
        f"warning: only {100 * y.matched_fraction:.0f} % of the searches matched (under {100 * threshold:.0f} %), most failed as "
        f"{reason.replace('_', ' ')} ({100 * share:.0f} %): {advice} (docs/guide/own_robot.md, tuning)"
    )


def summary_lines(m: RunMetrics) -> list[str]:
    """A run's metrics in a few lines, as ``dem-graph run`` prints them."""
    lines = [f"{m.estimator}: {m.frames or 0} frames in {m.elapsed_s or 0.0:.1f} s"]
    if m.laser_view is not None:
        lines.append(m.laser_view)
    if m.time_per_frame is not None and m.points_per_frame is not None:
        t, p = m.time_per_frame["total"], m.points_per_frame
        lines.append(f"time per frame: median {t.median_ms:.1f} ms, p95 {t.p95_ms:.1f} ms; live points median {p.live_median:.0f}, tracked {p.tracked_median:.0f}")
    if m.graph_update is not None:
        lines.append(graph_update_line(m.graph_update, m.events or {}))
    if m.tracking is not None:
        y = m.tracking
        failed = ", ".join(f"{k.replace('_', ' ')} {100 * v:.{0 if 100 * v >= 1 else 1}f} %" for k, v in y.failed_fraction.items()) or "none"
        lines.append(
            f"tracking: {100 * y.matched_fraction:.0f} % of {y.searches} searches matched ({100 * y.outlier_fraction_of_matched:.0f} % of them then rejected as outliers); failed: {failed}"
        )
        advice = yield_advice(y)
        if advice is not None and m.failure is None:  # a failed run says it last (:func:`failure_line`)
            lines.append(advice)
    if m.trajectory is not None:
        tr = m.trajectory
        lines.append(f"ATE RMSE {tr.ate_rmse_m:.3f} m ({tr.ate_aligned_rmse_m:.3f} m aligned), final error {tr.final_error_m:.3f} m over {tr.distance_m:.1f} m: drift {tr.drift_percent:.2f} %")
        rpe = tr.rpe
        if rpe.pairs:
            lines.append(f"RPE over {rpe.delta_m:g} m: {rpe.translation_rmse_m:.3f} m, {rpe.rotation_rmse_deg:.2f} deg (RMSE of {rpe.pairs} pairs)")
        else:
            lines.append(f"RPE over {rpe.delta_m:g} m: none ({rpe.reason})")
    d = m.dem
    if isinstance(d, DemMetrics):
        line = f"DEM: {d.covered_cells} cells of {d.resolution_m:g} m from {d.measurements} measurements, rebuilt in {d.rebuild_s:.2f} s"
        if d.height_error_laser_cells is not None and d.corridor is not None:
            e, c = d.height_error_laser_cells, d.corridor
            line += f"; {laser_cells_error_text(e)}, corridor {100 * c.coverage:.0f} % covered"
        lines.append(line)
        lw = d.local_window
        if lw is not None and lw.frames_with_data:
            line = f"local DEM, {lw.width_m:g} m window ahead (Fig. 8): mean error {100 * lw.mean_of_mean_m:.1f} cm, std {100 * lw.mean_of_std_m:.1f} cm"
            if lw.relative_mean_abs_mean_m is not None:
                line += f"; relative to the vehicle: |mean| {100 * lw.relative_mean_abs_mean_m:.1f} cm, std {100 * lw.relative_mean_of_std_m:.1f} cm"
            lines.append(line)
    elif isinstance(d, DemFailure):
        lines.append(f"DEM: not made ({d.error})")
    lm = m.live_map
    if lm is not None:
        line = f"live map: {lm.covered_cells} cells, update median {lm.update_median_ms:.2f} ms, p95 {lm.update_p95_ms:.2f} ms; {lm.returns} returns, re-placed {lm.returns_moved} times by revisions"
        line += f"; whole frame median {lm.whole_frame_median_ms:.1f} ms, p95 {lm.whole_frame_p95_ms:.1f} ms"
        if lm.idle_updates:
            line += f", and between frames {lm.idle_median_ms:.1f} ms median, {lm.idle_p95_ms:.1f} ms p95 ({lm.idle_updates} times)"
        lw = lm.local_window
        if lw is not None and lw.frames_with_data:
            line += f"; Fig. 8 as the guidance had it: mean error {100 * lw.mean_of_mean_m:.1f} cm, std {100 * lw.mean_of_std_m:.1f} cm"
        lines.append(line)
    return lines


def failure_line(m: RunMetrics) -> str | None:
    """A failed run's last line (its failure, the tracker's main reason and the setting to look at),
    None for any other run."""
    if m.failure is None:
        return None
    line = f"dem-graph: run failed: {m.failure}"
    main = _main_failure(m.tracking) if m.tracking is not None else None
    if main is not None:
        reason, share = main
        line += f"; most searches failed as {reason.replace('_', ' ')} ({100 * share:.0f} %): {_ADVICE.get(reason, 'see the tuning guide')}"
    return line + " (the run folder's files were written; docs/guide/own_robot.md, tuning)"


__all__ = ["FAILED_YIELD_FRACTION", "LOW_YIELD_FRACTION", "LiveSourceMetrics", "PointsPerFrame", "RunMetrics", "StreamHealth", "compute_metrics", "failure_line", "laser_cells_error_text", "summary_lines", "tracking_failure", "yield_advice"]
