"""A run's metrics: what ``metrics.json`` holds, and the lines ``dem-graph run`` prints."""

from __future__ import annotations

import numpy as np

from dem_graph.datasets.base import Sequence
from dem_graph.estimators.base import EstimatorResult
from dem_graph.evaluation.timing import frame_timing_summary
from dem_graph.evaluation.trajectory_metrics import accuracy_summary, nees_bounds, pose_nees


def compute_metrics(sequence: Sequence, res: EstimatorResult, error: str | None = None, elapsed_s: float = 0.0) -> dict:
    """A run's metrics (``metrics.json`` less its DEM and its dataset): frames, time and points per
    frame, events, and against the truth the trajectory's accuracy and the poses' NEES."""
    metrics: dict = {"estimator": res.name, "frames": len(res.frames), "elapsed_s": elapsed_s}
    if error:
        metrics["error"] = error
    if not res.frames:
        return metrics
    phases = sorted({k for f in res.frames for k in f.timing_s})
    metrics["time_per_frame"] = frame_timing_summary({k: [f.timing_s.get(k, 0.0) for f in res.frames] for k in phases})
    live = np.array([f.n_live for f in res.frames])
    tracked = np.array([f.n_tracked for f in res.frames])
    metrics["points_per_frame"] = {"live_median": float(np.median(live)), "live_max": int(live.max()), "tracked_median": float(np.median(tracked))}
    metrics["map_points"] = len(res.points)
    metrics["events"] = dict(sorted(res.counters.items()))
    gt = sequence.ground_truth
    if gt is not None and len(res.frames) > 1:
        est = res.trajectory()
        metrics["trajectory"] = accuracy_summary(est, gt.trajectory)
        for name, extra in res.extra_trajectories().items():
            metrics[name] = accuracy_summary(extra, gt.trajectory)
        nees = pose_nees(est.poses_se3, gt.trajectory.at(est.t_s), res.pose_covariances())
        lo, hi = nees_bounds(6, 0.95)
        later = nees[1:]
        metrics["pose_nees"] = {"median": float(np.median(later)), "fraction_within_95": float(np.mean((later >= lo) & (later <= hi))), "fraction_below_upper_95": float(np.mean(later <= hi))}
    return metrics


def summary_lines(m: dict) -> list[str]:
    """A run's metrics in a few lines, as ``dem-graph run`` prints them."""
    lines = [f"{m.get('estimator')}: {m.get('frames', 0)} frames in {m.get('elapsed_s', 0.0):.1f} s"]
    if "time_per_frame" in m:
        t = m["time_per_frame"]["total"]
        p = m["points_per_frame"]
        lines.append(f"time per frame: median {t['median_ms']:.1f} ms, p95 {t['p95_ms']:.1f} ms; live points median {p['live_median']:.0f}, tracked {p['tracked_median']:.0f}")
    if "trajectory" in m:
        tr = m["trajectory"]
        lines.append(f"ATE RMSE {tr['ate_rmse_m']:.3f} m ({tr['ate_aligned_rmse_m']:.3f} m aligned), final error {tr['final_error_m']:.3f} m over {tr['distance_m']:.1f} m: drift {tr['drift_percent']:.2f} %")
        rpe = tr["rpe"]
        if rpe["pairs"]:
            lines.append(f"RPE over {rpe['delta_m']:g} m: {rpe['translation_rmse_m']:.3f} m, {rpe['rotation_rmse_deg']:.2f} deg (RMSE of {rpe['pairs']} pairs)")
        else:
            lines.append(f"RPE over {rpe['delta_m']:g} m: none ({rpe['reason']})")
    d = m.get("dem")
    if d and "error" not in d:
        line = f"DEM: {d['covered_cells']} cells of {d['resolution_m']:g} m from {d['measurements']} measurements, rebuilt in {d['rebuild_s']:.2f} s"
        if "height_error_laser_cells" in d:
            e, c = d["height_error_laser_cells"], d["corridor"]
            line += f"; height RMSE {100 * e['rmse_m']:.1f} cm over the laser-swept cells, corridor {100 * c['coverage']:.0f} % covered"
        lines.append(line)
        if "local_window" in d and d["local_window"].get("frames_with_data"):
            lw = d["local_window"]
            line = f"local DEM, {lw['width_m']:g} m window ahead (Fig. 8): mean error {100 * lw['mean_of_mean_m']:.1f} cm, std {100 * lw['mean_of_std_m']:.1f} cm"
            if "relative_mean_abs_mean_m" in lw:
                line += f"; relative to the vehicle: |mean| {100 * lw['relative_mean_abs_mean_m']:.1f} cm, std {100 * lw['relative_mean_of_std_m']:.1f} cm"
            lines.append(line)
    elif d:
        lines.append(f"DEM: not made ({d['error']})")
    return lines


__all__ = ["compute_metrics", "summary_lines"]
