"""How far the graph estimator's search regions are from the ones its smoother's marginals give.

The online estimator (:mod:`dem_graph.estimators.isam2`) searches each point inside the region of
an approximate innovation covariance: the pose covariance relative to the map plus the point's own
covariance (its observations, poses held fixed). The exact one needs the joint marginal of the
keyframe pose and the point, several milliseconds each from iSAM2. This study computes both after
keyframe updates, for the keyframe's pose, and reports per point:

- ``containment``: the largest eigenvalue of ``S_approx^-1 S_exact``. At most 1, the approximate
  gate contains the exact one; above 1, the exact region sticks out by its square root in sigmas;
- ``area_ratio``: ``sqrt(det S_approx / det S_exact)``, how much larger the searched area is.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import gtsam
import numpy as np
from gtsam.symbol_shorthand import L, X

from dem_graph.datasets.base import Sequence
from dem_graph.estimators.isam2 import Isam2Config, Isam2Slam
from dem_graph.estimators.pose_update import project_with_jacobians
from dem_graph.pipeline.run import feed


@dataclass
class SearchRegionStudy:
    containment: list[float] = field(default_factory=list)
    area_ratio: list[float] = field(default_factory=list)
    keyframes: int = 0

    def summary(self) -> dict[str, float]:
        c, a = np.asarray(self.containment), np.asarray(self.area_ratio)
        return {
            "points": int(c.size),
            "keyframes": self.keyframes,
            "contained_fraction": float(np.mean(c <= 1.0)),
            "containment_p95": float(np.percentile(c, 95)),
            "containment_max": float(c.max()),
            "area_ratio_median": float(np.median(a)),
            "area_ratio_p95": float(np.percentile(a, 95)),
        }


def compare_at_keyframe(est: Isam2Slam, study: SearchRegionStudy, points_per_keyframe: int, rng: np.random.Generator) -> None:
    g, live = est.graph, est.live
    k = g.last_keyframe
    if len(live) == 0:
        return
    in_graph = np.flatnonzero([g.in_window(int(lm)) for lm in live.landmark])
    chosen = rng.choice(in_graph, size=min(points_per_keyframe, len(in_graph)), replace=False)
    _, S_approx, in_front = est.search_regions(est.T)
    _, Hp, Hx, _ = project_with_jacobians(est.T, live.X, est.rig.camera_model, est.rig.T_body_cam)
    isam = g.isam
    R = est.config.frontend.sigma_px**2 * np.eye(2)
    study.keyframes += 1
    for i in chosen:
        if not in_front[i]:
            continue
        keys = gtsam.KeyVector([X(k), L(int(live.landmark[i]))])
        joint = isam.jointMarginalCovariance(keys)
        C = np.block([[joint.at(X(k), X(k)), joint.at(X(k), L(int(live.landmark[i])))], [joint.at(L(int(live.landmark[i])), X(k)), joint.at(L(int(live.landmark[i])), L(int(live.landmark[i])))]])
        J = np.concatenate([Hp[i], Hx[i]], axis=1)
        S_exact = J @ C @ J.T + R
        study.containment.append(float(np.max(np.linalg.eigvals(np.linalg.solve(S_approx[i], S_exact)).real)))
        study.area_ratio.append(float(np.sqrt(np.linalg.det(S_approx[i]) / np.linalg.det(S_exact))))


def search_region_study(sequence: Sequence, config: Isam2Config | None = None, every_keyframes: int = 4, points_per_keyframe: int = 20, max_frames: int | None = None, seed: int = 0) -> SearchRegionStudy:
    """Run the online graph estimator over ``sequence``, comparing the regions every ``every_keyframes`` keyframes."""
    est = Isam2Slam(sequence.rig, sequence.T_world_body_initial, sequence.t_start_s, sequence.has_odometry, config)
    study = SearchRegionStudy()
    rng = np.random.default_rng(seed)
    count = {"n": 0}

    def hook(e: Isam2Slam) -> None:
        count["n"] += 1
        if count["n"] % every_keyframes == 0:
            compare_at_keyframe(e, study, points_per_keyframe, rng)

    est.keyframe_hooks.append(hook)
    for _ in feed(est, sequence, max_frames):
        pass
    return study


__all__ = ["SearchRegionStudy", "compare_at_keyframe", "search_region_study"]
