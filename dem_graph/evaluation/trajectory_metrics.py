"""Trajectory accuracy: errors against ground truth, summary metrics, alignment and pose NEES.

Every estimator starts at the dataset's initial pose ``T_world_body_initial``, so its trajectory
is expressed in the ground truth's world frame and is compared **as is**, without any alignment:
the "ATE anchored at the initial pose". :func:`ate_aligned_rmse_m` (the usual ATE after a best
rigid alignment, as evo's ``--align``) is given alongside for comparison with other papers, and
:func:`relative_pose_errors` gives the RPE over a travelled distance (10 m by default), which
measures local drift whatever happened before. :func:`accuracy_summary` gathers them all.

The estimate is compared at its own sample times; the ground truth is interpolated there with
:meth:`Trajectory.at` (slerp for rotation, linear for translation).

Numpy and scipy only, plus gtsam's ``Pose3.Logmap`` for the NEES. No files, no plotting.
"""

from __future__ import annotations

import logging
import math
from dataclasses import asdict, dataclass

import numpy as np
from scipy.spatial.transform import Rotation
from scipy.stats import chi2

from dem_graph.errors import DemGraphError
from dem_graph.evaluation.results import MetricsModel, Number
from dem_graph.geometry.se3 import invert
from dem_graph.geometry.trajectory import Trajectory

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class TrajectoryErrors:
    """Per-pose errors of an estimate against the ground truth, at the estimate's times."""

    t_s: np.ndarray  # (N,)
    position_error_m: np.ndarray  # (N, 3) estimate minus truth, world frame
    rotation_error_rad: np.ndarray  # (N,) angle of R_true^T @ R_est, in [0, pi]
    distance_travelled_m: np.ndarray  # (N,) along the truth, from the first estimate time


@dataclass(frozen=True)
class TrajectoryMetrics:
    """Summary of :class:`TrajectoryErrors` (anchored, no alignment)."""

    ate_rmse_m: float  # RMS of the position error norms
    ate_max_m: float  # largest position error norm
    rotation_rmse_deg: float  # RMS of the rotation error angles
    final_error_m: float  # position error norm at the last estimate pose
    distance_m: float  # distance travelled along the truth over the estimate's span
    drift_percent: float  # final_error_m / distance_m * 100 (NaN when distance_m is 0)
    n_poses: int
    final_height_error_m: float = math.nan  # signed: the last pose's world z minus the truth's (positive: too high)

    def as_dict(self) -> dict:
        """The fields as plain Python numbers (``float``, ``int`` for ``n_poses``), for JSON."""
        return {k: (int(v) if k == "n_poses" else float(v)) for k, v in asdict(self).items()}


def within_truth_span(estimate: Trajectory, truth: Trajectory) -> tuple[Trajectory | None, np.ndarray]:
    """The part of ``estimate`` inside the truth's time span (None with fewer than two samples
    there), and which samples that is; a warning
    when the truth covers only part of the run (its metrics are then over that part)."""
    lo, hi = truth.t_s[0], truth.t_s[-1]
    eps = 1e-9 * max(1.0, abs(hi))  # the tolerance Trajectory.at accepts
    covered = (estimate.t_s >= lo - eps) & (estimate.t_s <= hi + eps)
    if not covered.all():
        log.warning(
            "the ground truth spans %.3f to %.3f s and covers %d of the run's %d frames: the trajectory metrics are over those",
            lo, hi, int(covered.sum()), len(covered),
        )  # fmt: skip
    return (estimate.slice(lo - eps, hi + eps) if covered.sum() >= 2 else None), covered


def trajectory_errors(estimate: Trajectory, truth: Trajectory) -> TrajectoryErrors:
    """Errors of ``estimate`` against ``truth`` at the estimate's sample times, without alignment.

    Raises :class:`DemGraphError` when an estimate time lies outside the truth's time span.
    """
    t = estimate.t_s
    lo, hi = truth.t_s[0], truth.t_s[-1]
    eps = 1e-9 * max(1.0, abs(hi))  # the tolerance Trajectory.at accepts
    outside = (t < lo - eps) | (t > hi + eps)
    if np.any(outside):
        raise DemGraphError(
            f"{int(np.count_nonzero(outside))} of {len(t)} estimate times lie outside the ground truth's span "
            f"[{lo:.6f}, {hi:.6f}] s (first at t={float(t[np.argmax(outside)]):.6f} s)"
        )
    T_true = truth.at(t)
    if T_true.ndim == 2:
        T_true = T_true[None]
    T_est = estimate.poses_se3

    position_error = T_est[:, :3, 3] - T_true[:, :3, 3]
    R_rel = np.einsum("nji,njk->nik", T_true[:, :3, :3], T_est[:, :3, :3])  # R_true^T R_est
    rotation_error = Rotation.from_matrix(R_rel).magnitude()

    # The truth is piecewise linear in position between its samples, so the distance along it is
    # piecewise linear in time: interpolate its cumulative length.
    cumulative = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(truth.positions_xyz, axis=0), axis=1))])
    s = np.interp(np.clip(t, lo, hi), truth.t_s, cumulative)
    return TrajectoryErrors(
        t_s=t.copy(),
        position_error_m=position_error,
        rotation_error_rad=np.asarray(rotation_error, dtype=float),
        distance_travelled_m=s - s[0],
    )


def trajectory_metrics(estimate: Trajectory, truth: Trajectory) -> TrajectoryMetrics:
    """Anchored ATE, rotation RMSE, final error and drift of ``estimate`` against ``truth``."""
    errors = trajectory_errors(estimate, truth)
    norms = np.linalg.norm(errors.position_error_m, axis=1)
    distance = float(errors.distance_travelled_m[-1])
    final = float(norms[-1])
    return TrajectoryMetrics(
        ate_rmse_m=float(np.sqrt(np.mean(norms**2))),
        ate_max_m=float(np.max(norms)),
        rotation_rmse_deg=float(np.degrees(np.sqrt(np.mean(errors.rotation_error_rad**2)))),
        final_error_m=final,
        distance_m=distance,
        drift_percent=final / distance * 100.0 if distance > 0.0 else math.nan,
        n_poses=len(errors.t_s),
        final_height_error_m=float(errors.position_error_m[-1, 2]),
    )


def umeyama_alignment(source_xyz, target_xyz, with_scale: bool = False) -> tuple[np.ndarray, np.ndarray, float]:
    """The similarity (or rigid, ``with_scale=False``) transform that best maps source onto target.

    Returns ``(R, t, s)`` minimizing ``sum_i |target_i - (s * R @ source_i + t)|^2`` (Umeyama 1991,
    closed form by SVD of the cross-covariance, with the reflection correction), ``s = 1`` when
    ``with_scale`` is False. For degenerate point sets (fewer than 3 points, or all collinear) the
    rotation is not unique; one of the minimizers is returned, so the residual is still the least.

    Raises :class:`DemGraphError` for mismatched or empty inputs, and for ``with_scale`` when the
    source points all coincide.
    """
    x = np.asarray(source_xyz, dtype=float)
    y = np.asarray(target_xyz, dtype=float)
    if x.ndim != 2 or x.shape[1] != 3 or x.shape != y.shape:
        raise DemGraphError(f"alignment needs two (N, 3) point sets of the same shape, got {x.shape} and {y.shape}")
    if len(x) == 0:
        raise DemGraphError("alignment needs at least one point")
    mean_x = x.mean(axis=0)
    mean_y = y.mean(axis=0)
    xc = x - mean_x
    yc = y - mean_y
    cov = yc.T @ xc / len(x)  # cross-covariance, target x source
    U, d, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0.0:
        S[2, 2] = -1.0
    R = U @ S @ Vt
    if with_scale:
        var_x = float(np.mean(np.sum(xc**2, axis=1)))
        if not var_x > 0.0:
            raise DemGraphError("scale alignment needs source points that do not all coincide")
        s = float(np.sum(d * np.diag(S)) / var_x)
    else:
        s = 1.0
    t = mean_y - s * (R @ mean_x)
    return R, t, s


def ate_aligned_rmse_m(estimate: Trajectory, truth: Trajectory) -> float:
    """RMS position error after the best rigid (SE(3), no scale) alignment of the estimate onto the truth.

    Positions only (as evo's ``align``), at the estimate's times. Raises as :func:`trajectory_errors`.
    """
    errors = trajectory_errors(estimate, truth)
    est = estimate.positions_xyz
    true = est - errors.position_error_m
    R, t, _ = umeyama_alignment(est, true, with_scale=False)
    residual = est @ R.T + t - true
    return float(np.sqrt(np.mean(np.sum(residual**2, axis=1))))


RPE_DELTA_M = 10.0  # the distance the RPE is measured over, metres


@dataclass(frozen=True)
class RelativePoseErrors:
    """Relative-pose errors (RPE) between estimate poses ``delta_m`` apart along the ground truth.

    For each pair ``(i, j)`` the error is ``E = (Q_i^-1 Q_j)^-1 (P_i^-1 P_j)``, with ``Q`` the true
    and ``P`` the estimated ``T_world_body``: the estimate's motion from i to j compared with the
    true motion, in the body frame at i. ``translation_error_m`` is the norm of E's translation,
    ``rotation_error_deg`` the angle of E's rotation. ``reason`` says why there is no pair (the run
    is shorter than ``delta_m``); the summary numbers are then NaN.
    """

    delta_m: float
    tolerance_m: float
    pairs: np.ndarray  # (K, 2) indices into the estimate's poses, i < j
    translation_error_m: np.ndarray  # (K,)
    rotation_error_deg: np.ndarray  # (K,)
    distance_m: float  # distance along the truth over the estimate's span
    reason: str | None = None

    def summary(self) -> RpeSummary:
        """The summary numbers (NaN when there is no pair)."""
        n = len(self.pairs)
        t = self.translation_error_m
        r = self.rotation_error_deg
        nan = math.nan
        return RpeSummary(
            delta_m=float(self.delta_m),
            pairs=int(n),
            translation_rmse_m=float(np.sqrt(np.mean(t**2))) if n else nan,
            translation_mean_m=float(np.mean(t)) if n else nan,
            translation_max_m=float(np.max(t)) if n else nan,
            translation_rmse_percent=float(100.0 * np.sqrt(np.mean(t**2)) / self.delta_m) if n else nan,
            rotation_rmse_deg=float(np.sqrt(np.mean(r**2))) if n else nan,
            reason=self.reason,
        )


class RpeSummary(MetricsModel):
    """The RPE over ``delta_m`` in numbers (``metrics.json``'s ``trajectory.rpe``)."""

    _keep_none = frozenset({"reason"})

    delta_m: float
    pairs: int
    translation_rmse_m: Number
    translation_mean_m: Number
    translation_max_m: Number
    translation_rmse_percent: Number
    rotation_rmse_deg: Number
    reason: str | None = None  # why there is no pair


def _pairs_at_distance(s_m: np.ndarray, delta_m: float, tolerance_m: float) -> np.ndarray:
    """For every pose i, the later pose j whose distance ``s_j - s_i`` is nearest ``delta_m`` (the
    earliest such j on a tie), kept when it is within ``tolerance_m`` of it. ``s_m`` never decreases."""
    pairs = []
    n = len(s_m)
    for i in range(n - 1):
        target = s_m[i] + delta_m
        above = int(np.searchsorted(s_m, target, side="left"))  # first j with s_j >= target
        candidates = []
        if above - 1 > i:
            # the last distance below the target; its earliest index, as the earliest j wins a tie
            candidates.append(max(int(np.searchsorted(s_m, s_m[above - 1], side="left")), i + 1))
        if above < n:
            candidates.append(max(above, i + 1))
        if not candidates:
            continue
        gaps = [abs((s_m[j] - s_m[i]) - delta_m) for j in candidates]
        k = int(np.argmin(gaps))
        if gaps[k] <= tolerance_m:
            pairs.append((i, candidates[k]))
    return np.array(pairs, dtype=int).reshape(-1, 2)


def relative_pose_errors(estimate: Trajectory, truth: Trajectory, delta_m: float = RPE_DELTA_M, relative_tolerance: float = 0.01) -> RelativePoseErrors:
    """RPE of ``estimate`` over ``delta_m`` of distance travelled along ``truth`` (see :class:`RelativePoseErrors`).

    Distances are measured along the truth's positions at the estimate's times (straight between
    them). Every estimate pose starts a pair, ending at the later pose whose distance from it is
    nearest ``delta_m``, if within ``relative_tolerance * delta_m``: evo's ``RPE`` with ``delta=10``,
    ``delta_unit=meters``, ``all_pairs=True``, ``pairs_from_reference=True`` and ``rel_delta_tol``
    = ``relative_tolerance``. The default (1 %, 10 cm over 10 m) is tighter than evo's (10 %), so that
    the pairs near the end of a run, or of a run a little shorter than ``delta_m``, are not shorter
    than ``delta_m`` by up to a metre. A run shorter than that gives no pair and a ``reason``, not an error. Raises as :func:`trajectory_errors`, and :class:`DemGraphError`
    for a ``delta_m`` that is not positive.
    """
    if not (math.isfinite(delta_m) and delta_m > 0.0):
        raise DemGraphError(f"the RPE distance must be a positive number of metres, got {delta_m!r}")
    trajectory_errors(estimate, truth)  # the same checks of the time spans
    Q = truth.at(estimate.t_s).reshape(-1, 4, 4)
    # distance along the truth's poses at the estimate's times, as evo measures it
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(Q[:, :3, 3], axis=0), axis=1))])
    tolerance = relative_tolerance * delta_m
    distance = float(s[-1])
    pairs = _pairs_at_distance(s, delta_m, tolerance)
    reason = None
    if len(pairs) == 0:
        if distance < delta_m - tolerance:
            reason = f"the run covers {distance:.2f} m along the ground truth, less than the RPE's {delta_m:g} m"
        else:
            reason = f"no two poses lie {delta_m:g} +- {tolerance:g} m apart along the ground truth"
    P = estimate.poses_se3
    i, j = pairs[:, 0], pairs[:, 1]
    E = invert(invert(Q[i]) @ Q[j]) @ (invert(P[i]) @ P[j])
    angles = Rotation.from_matrix(E[:, :3, :3]).magnitude() if len(pairs) else np.zeros(0)
    return RelativePoseErrors(
        delta_m=float(delta_m),
        tolerance_m=float(tolerance),
        pairs=pairs,
        translation_error_m=np.linalg.norm(E[:, :3, 3], axis=1),
        rotation_error_deg=np.degrees(np.asarray(angles, dtype=float)),
        distance_m=distance,
        reason=reason,
    )


class TrajectoryAccuracy(MetricsModel):
    """Every trajectory number of a run (``metrics.json``'s ``trajectory``): the anchored metrics of
    :class:`TrajectoryMetrics`, the ATE after the best rigid alignment, and the RPE."""

    ate_rmse_m: Number
    ate_max_m: Number
    rotation_rmse_deg: Number
    final_error_m: Number
    distance_m: Number
    drift_percent: Number
    n_poses: int
    ate_aligned_rmse_m: Number
    rpe: RpeSummary
    final_height_error_m: Number = math.nan  # signed: the last pose's world z minus the truth's


def accuracy_summary(estimate: Trajectory, truth: Trajectory, rpe_delta_m: float = RPE_DELTA_M) -> TrajectoryAccuracy:
    """Every trajectory number of a run: the anchored metrics of :func:`trajectory_metrics` (ATE,
    drift in % of distance, ...), the aligned ATE and the RPE over ``rpe_delta_m``."""
    anchored = trajectory_metrics(estimate, truth).as_dict()
    aligned = ate_aligned_rmse_m(estimate, truth)
    return TrajectoryAccuracy(**anchored, ate_aligned_rmse_m=aligned, rpe=relative_pose_errors(estimate, truth, rpe_delta_m).summary())


def pose_nees(estimate_T, truth_T, covariances) -> np.ndarray:
    """Normalized estimation error squared of each pose: ``xi^T P^-1 xi`` (N,).

    Convention (the README's): the covariance ``P`` (6x6, gtsam order [rotation, translation],
    radians and metres) is that of the **right perturbation of the estimate**,
    ``T_true = T_est @ Exp(xi)``, so ``xi = Log(T_est^-1 @ T_true)`` with gtsam's
    ``Pose3.Logmap`` / ``Pose3.Expmap``. This is the tangent space of a gtsam marginal covariance
    of the estimate. For a consistent estimator, the NEES follows a chi-square law with 6 degrees of
    freedom (mean 6); see :func:`nees_bounds`.

    Raises :class:`DemGraphError` for wrong shapes or a covariance that is not symmetric positive definite.
    """
    import gtsam

    T_est = np.asarray(estimate_T, dtype=float)
    T_true = np.asarray(truth_T, dtype=float)
    P = np.asarray(covariances, dtype=float)
    n = len(T_est)
    if T_est.shape != (n, 4, 4) or T_true.shape != (n, 4, 4) or P.shape != (n, 6, 6):
        raise DemGraphError(
            f"pose_nees needs (N,4,4) estimates and truths and (N,6,6) covariances, got {T_est.shape}, {T_true.shape}, {P.shape}"
        )
    if not np.allclose(P, np.swapaxes(P, -1, -2), rtol=1e-9, atol=1e-12 * max(1.0, float(np.max(np.abs(P), initial=0.0)))):
        raise DemGraphError("pose_nees: a covariance is not symmetric")
    T_rel = invert(T_est) @ T_true
    xi = np.empty((n, 6))
    for i in range(n):
        xi[i] = gtsam.Pose3.Logmap(gtsam.Pose3(T_rel[i]))
    try:
        L = np.linalg.cholesky(0.5 * (P + np.swapaxes(P, -1, -2)))
    except np.linalg.LinAlgError:
        raise DemGraphError("pose_nees: a covariance is not positive definite") from None
    # xi^T P^-1 xi = |L^-1 xi|^2 with P = L L^T
    whitened = np.linalg.solve(L, xi[..., None])[..., 0] if n else np.empty((0, 6))
    return np.sum(whitened**2, axis=1)


class NeesSummary(MetricsModel):
    """The poses' NEES over a run (``metrics.json``'s ``pose_nees``), the first pose left out (it is
    the anchor): its mean (6 for a consistent estimator) and median (5.35), the fraction inside the
    two-sided 95 % chi-square interval and the fraction below its upper bound."""

    mean: Number | None = None  # (absent from the metrics of older runs)
    median: Number
    fraction_within_95: Number
    fraction_below_upper_95: Number


def nees_summary(nees: np.ndarray) -> NeesSummary:
    """:class:`NeesSummary` of the poses' NEES (:func:`pose_nees`), the first left out."""
    lo, hi = nees_bounds(6, 0.95)
    later = nees[1:]
    return NeesSummary(mean=float(np.mean(later)), median=float(np.median(later)), fraction_within_95=float(np.mean((later >= lo) & (later <= hi))), fraction_below_upper_95=float(np.mean(later <= hi)))


def nees_bounds(dof: int = 6, probability: float = 0.95) -> tuple[float, float]:
    """Two-sided chi-square interval holding one NEES sample with ``probability`` for a consistent estimator.

    ``(chi2.ppf((1 - p) / 2, dof), chi2.ppf((1 + p) / 2, dof))``; about (1.24, 14.45) for the defaults.
    """
    if not 0.0 < probability < 1.0:
        raise DemGraphError(f"probability must lie in (0, 1), got {probability!r}")
    if dof < 1:
        raise DemGraphError(f"degrees of freedom must be at least 1, got {dof!r}")
    alpha = 1.0 - probability
    return float(chi2.ppf(alpha / 2.0, dof)), float(chi2.ppf(1.0 - alpha / 2.0, dof))
