"""``T_cam_laser`` from laser points lying on board planes: a closed form, a robust refinement, a covariance.

Every view gives a board plane in the camera frame, ``n_cam . X = d_m``, and laser points ``p`` on it
(laser frame, ``z = 0``); each point gives one constraint ``n_cam . (R p + t) = d_m``.

- Closed form (Zhang and Pless 2004): with ``H = [r1 r2 t]``, ``n_cam^T H [x, y, 1]^T = d_m`` is linear in
  the nine entries of ``H``; least squares over every point of every view, then ``R`` is the rotation
  nearest to ``[r1, r2, r1 x r2]`` and ``t`` the third column.
- Refinement: Gauss-Newton on the six-parameter right perturbation ``T_cam_laser * Exp(xi)``,
  ``xi = [omega, v]`` (gtsam's order, laser frame), with a Huber loss. Each view's residuals are
  whitened by their full covariance: the range noise along each beam plus the board plane's
  uncertainty from its corners, which is shared by all the points of the view. The whitening is
  recomputed at every evaluation, so that the diagonal part makes each residual a range error along
  its beam: with the weights held fixed the fit leans towards rotations that turn the beams to grazing
  incidence, where the range noise shows less (at 2 cm this bias was larger than the noise's spread).
- Covariance: ``s^2 (J^T W J)^-1`` at the solution, ``J`` the whitened Jacobian, ``W`` the Huber weights
  and ``s^2`` the residuals' variance factor; in the order [rot, trans] of the right perturbation, which
  is the convention of :attr:`SensorRig.T_cam_laser_covariance`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from dem_graph.errors import CalibrationError
from dem_graph.geometry.lie import local, retract
from dem_graph.geometry.se3 import make_pose


@dataclass(frozen=True)
class PlaneView:
    """One view for the solver: the board plane (camera frame) and the laser points on it (laser frame)."""

    n_cam: np.ndarray  # (3,) unit normal
    d_m: float
    plane_covariance: np.ndarray  # 4x4, of [n_cam, d_m]
    points_laser: np.ndarray  # (M,3), z = 0
    dark: np.ndarray | None = None  # (M,) probability that the point lies on a dark square (its range may be biased)

    def with_dark_bias(self, bias_m: float) -> PlaneView:
        """The view with its returns moved back along their beams by ``bias_m`` times their probability of being dark."""
        if self.dark is None or bias_m == 0.0 or not np.any(self.dark):
            return self
        ranges = np.linalg.norm(self.points_laser, axis=1)
        scale = 1.0 - bias_m * self.dark / np.maximum(ranges, 1e-9)
        return PlaneView(self.n_cam, self.d_m, self.plane_covariance, self.points_laser * scale[:, None], self.dark)


@dataclass(frozen=True)
class Solution:
    T_cam_laser: np.ndarray
    covariance: np.ndarray  # 6x6, [rot, trans] of the right perturbation, rad^2 and m^2
    T_initial: np.ndarray  # the closed form's estimate
    view_rms_m: np.ndarray  # (V,) point-to-plane RMS per view at the solution
    variance_factor: float  # s^2: whitened residuals' sum of squares per degree of freedom
    n_points: int
    dark_bias_m: float | None = None  # range bias of dark-square returns, when estimated
    dark_bias_sigma_m: float | None = None
    n_dark: int = 0  # returns on dark squares
    robust_variance_factor: float = float("nan")  # (1.4826 median |whitened residual|)^2: s^2 without the outliers' pull


def point_plane_residuals(T_cam_laser: np.ndarray, view: PlaneView) -> np.ndarray:
    """Signed distances (metres) of the view's laser points from its board plane."""
    X = view.points_laser @ T_cam_laser[:3, :3].T + T_cam_laser[:3, 3]
    return X @ view.n_cam - view.d_m


def point_plane_jacobian(T_cam_laser: np.ndarray, view: PlaneView) -> np.ndarray:
    """(M,6) derivative of :func:`point_plane_residuals` by the right perturbation ``xi = [omega, v]``."""
    a = T_cam_laser[:3, :3].T @ view.n_cam
    return _cross_and_normal(view.points_laser, a)


def _cross_and_normal(points: np.ndarray, a: np.ndarray) -> np.ndarray:
    """``[p x a, a]`` for each point ``p`` (rows of ``points``, (..., M, 3)), ``a`` (..., 3): the products and
    differences of ``np.cross`` in its order, without its overhead (the refinements call this thousands of times)."""
    a = a[..., None, :]
    J = np.empty(points.shape[:-1] + (6,))
    J[..., 0] = points[..., 1] * a[..., 2] - points[..., 2] * a[..., 1]
    J[..., 1] = points[..., 2] * a[..., 0] - points[..., 0] * a[..., 2]
    J[..., 2] = points[..., 0] * a[..., 1] - points[..., 1] * a[..., 0]
    J[..., 3:] = a
    return J


def normal_spread(normals_cam: np.ndarray) -> float:
    """Smallest over largest singular value of the stacked unit normals: 0 when they do not span 3-D
    (all boards parallel, or all tilted about one axis only), about the angular spread in radians when small."""
    s = np.linalg.svd(np.asarray(normals_cam, dtype=float), compute_uv=False)
    return float(s[-1] / s[0]) if len(s) == 3 else 0.0


def check_geometry(views: list[PlaneView], min_views: int = 3, min_spread: float = 0.03) -> None:
    """Raise :class:`CalibrationError` when the views cannot determine ``T_cam_laser``."""
    if len(views) < min_views:
        raise CalibrationError(f"{len(views)} usable views, at least {min_views} are needed")
    spread = normal_spread([v.n_cam for v in views])
    if spread < min_spread:
        raise CalibrationError(
            f"the boards are (nearly) parallel: their normals' singular-value ratio is {spread:.3f}, "
            f"at least {min_spread} is needed; tilt the board about different axes"
        )


def closed_form(views: list[PlaneView]) -> np.ndarray:
    """Zhang and Pless' linear estimate of ``T_cam_laser`` (see the module's docstring)."""
    rows, rhs = [], []
    for v in views:
        q = np.column_stack([v.points_laser[:, :2], np.ones(len(v.points_laser))])
        rows.append((v.n_cam[None, :, None] * q[:, None, :]).reshape(len(q), 9))
        rhs.append(np.full(len(q), v.d_m))
    A, b = np.vstack(rows), np.concatenate(rhs)
    scale = np.linalg.norm(A, axis=0)
    scale[scale == 0] = 1.0
    h, _, rank, sv = np.linalg.lstsq(A / scale, b, rcond=None)
    if rank < 9 or sv[-1] < 1e-9 * sv[0]:
        raise CalibrationError(f"the point-on-plane constraints do not determine the transform (rank {rank} of 9); use more views at more varied poses")
    H = (h / scale).reshape(3, 3)
    r1, r2 = H[:, 0], H[:, 1]
    U, _, Vt = np.linalg.svd(np.column_stack([r1, r2, np.cross(r1, r2)]))
    R = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    return make_pose(R, H[:, 2])


def _whiteners(T: np.ndarray, views: list[PlaneView], range_sigma_m: float) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Per view, an inverse square root of the residuals' covariance ``C = D + A S A^T`` at ``T``: ``D`` the
    range noise along each beam (diagonal), ``A = [X, -1]`` and ``S`` the plane's 4x4 covariance. With
    ``B = D^-1/2 A = Q R`` and ``R S R^T = V L V^T``, ``C^-1/2 = (I + U diag((1 + L)^-1/2 - 1) U^T) D^-1/2``
    with ``U = Q V``: cheap, as the plane's part has rank four at most."""
    out = []
    for v in views:
        X = v.points_laser @ T[:3, :3].T + T[:3, 3]
        ranges = np.linalg.norm(v.points_laser, axis=1)
        beams = (v.points_laser / np.maximum(ranges, 1e-9)[:, None]) @ T[:3, :3].T
        sqrt_d = np.sqrt((range_sigma_m * (beams @ v.n_cam)) ** 2 + 1e-12)
        Q, R = np.linalg.qr(np.column_stack([X, -np.ones(len(X))]) / sqrt_d[:, None])
        lam, V = np.linalg.eigh(R @ v.plane_covariance @ R.T)
        out.append((sqrt_d, Q @ V, 1.0 / np.sqrt(1.0 + np.maximum(lam, 0.0)) - 1.0))
    return out


def _apply(whitener: tuple[np.ndarray, np.ndarray, np.ndarray], x: np.ndarray) -> np.ndarray:
    sqrt_d, U, f = whitener
    y = x / (sqrt_d if x.ndim == 1 else sqrt_d[:, None])
    return y + U @ (f[:, None] * (U.T @ y)) if y.ndim == 2 else y + U @ (f * (U.T @ y))


def _whitened(T: np.ndarray, views: list[PlaneView], W: list, with_jacobian: bool):
    res = np.concatenate([_apply(w, point_plane_residuals(T, v)) for v, w in zip(views, W)])
    jac = np.vstack([_apply(w, point_plane_jacobian(T, v)) for v, w in zip(views, W)]) if with_jacobian else None
    return res, jac


class _PackedViews:
    """The views' points in one zero-padded array (view, point, xyz), so that a residual evaluation of
    :func:`refine` whitens every view with a few numpy calls rather than a dozen per view. The arithmetic is
    that of :meth:`PlaneView.with_dark_bias`, :func:`_whiteners` and :func:`_whitened` view by view, to the
    bit: element by element, or in products whose sums do not run over the padding (the QR and ``U^T y``
    take each view's own rows)."""

    def __init__(self, views: list[PlaneView]):
        self.sizes = sizes = [len(v.points_laser) for v in views]
        self.mask = np.arange(max(sizes))[None, :] < np.array(sizes)[:, None]  # (V, M): a point, not padding
        self.points = np.zeros(self.mask.shape + (3,))
        self.points[self.mask] = np.concatenate([v.points_laser for v in views])
        self.dark = np.zeros(self.mask.shape)  # views without dark returns keep their points (a factor of exactly one)
        for k, v in enumerate(views):
            if v.dark is not None and np.any(v.dark):
                self.dark[k, : sizes[k]] = v.dark
        self.ranges = np.linalg.norm(self.points, axis=2)
        self.n_cam = np.array([v.n_cam for v in views])[:, :, None]  # (V, 3, 1)
        self.d_m = np.array([v.d_m for v in views], dtype=float)[:, None]
        self.plane_covariance = np.array([v.plane_covariance for v in views])

    def residuals(self, T: np.ndarray) -> np.ndarray:
        """:func:`point_plane_residuals` of every view, concatenated."""
        return (((self.points @ T[:3, :3].T + T[:3, 3]) @ self.n_cam)[:, :, 0] - self.d_m)[self.mask]

    def jacobian(self, T: np.ndarray) -> np.ndarray:
        """:func:`point_plane_jacobian` of every view, stacked."""
        a = np.array([T[:3, :3].T @ n[:, 0] for n in self.n_cam])  # (view by view: a sum of three products, as there)
        return _cross_and_normal(self.points, a)[self.mask]

    def whitened_residuals(self, T: np.ndarray, range_sigma_m: float, dark_bias_m: float = 0.0) -> np.ndarray:
        """``_whitened(T, moved, _whiteners(T, moved, range_sigma_m), False)[0]`` with ``moved`` the views
        with their dark returns moved by ``dark_bias_m``."""
        P = self.points
        if dark_bias_m != 0.0:
            P = P * (1.0 - dark_bias_m * self.dark / np.maximum(self.ranges, 1e-9))[:, :, None]
        R = T[:3, :3]
        X = P @ R.T + T[:3, 3]
        ranges = self.ranges if P is self.points else np.linalg.norm(P, axis=2)
        beams = (P / np.maximum(ranges, 1e-9)[:, :, None]) @ R.T
        sqrt_d = np.sqrt((range_sigma_m * (beams @ self.n_cam)[:, :, 0]) ** 2 + 1e-12)
        B = np.concatenate([X, -np.ones(X.shape[:2] + (1,))], axis=2) / sqrt_d[:, :, None]
        # the QR view by view: the reflections' norms are sums whose rounding depends on their length
        Q, Rq = np.zeros_like(B), np.empty((len(B), 4, 4))
        for k, m in enumerate(self.sizes):
            Q[k, :m], Rq[k] = np.linalg.qr(B[k, :m])
        lam, V = np.linalg.eigh(Rq @ self.plane_covariance @ Rq.transpose(0, 2, 1))
        U = Q @ V
        f = 1.0 / np.sqrt(1.0 + np.maximum(lam, 0.0)) - 1.0
        y = ((X @ self.n_cam)[:, :, 0] - self.d_m) / sqrt_d
        # U^T y view by view: a dot product's rounding depends on its length, and the padding's zeros would change it
        Uty = np.array([U[k, :m].T @ y[k, :m] for k, m in enumerate(self.sizes)])
        w = y + (U @ (f * Uty)[:, :, None])[:, :, 0]
        return w[self.mask]


MIN_DARK_RETURNS = 20  # fewer returns on dark squares than this: their range bias is not estimated


def refine(
    views: list[PlaneView], T_initial: np.ndarray, range_sigma_m: float, huber_k: float = 2.5, passes: int = 2, dark_bias: bool = True
) -> Solution:
    """Robust weighted least squares from ``T_initial`` (see the module's docstring); ``huber_k`` in standard deviations.

    With ``dark_bias`` and at least :data:`MIN_DARK_RETURNS` returns marked dark, a seventh unknown is the
    range bias of those returns (a dark surface reads long or short on many scanners): each dark return is
    moved back along its beam by it. Its covariance is part of the fit's; ``covariance`` is the 6x6 block
    of ``T_cam_laser``."""
    T = np.array(T_initial, dtype=float)
    n_dark = int(sum(int(np.sum(v.dark > 0.5)) for v in views if v.dark is not None))
    with_bias = dark_bias and n_dark >= MIN_DARK_RETURNS
    n_par = 7 if with_bias else 6
    bias = 0.0

    # (the views as one array: the evaluations below are most of a calibration's time; fewer than four
    # points in a view would make its QR's R short, and such views take the view-by-view path)
    packed = _PackedViews(views) if views and min(len(v.points_laser) for v in views) >= 4 else None

    def residuals(x, T0):
        T1 = retract(T0, x[:6])
        if packed is not None:
            return packed.whitened_residuals(T1, range_sigma_m, x[6] if with_bias else 0.0)
        moved = [v.with_dark_bias(x[6]) for v in views] if with_bias else views
        return _whitened(T1, moved, _whiteners(T1, moved, range_sigma_m), False)[0]

    for _ in range(passes):
        T0 = T
        # the whitening is recomputed at every evaluation: a fixed one lets the fit favour rotations that
        # turn the beams towards grazing (where range noise shows less), a bias of the order of the noise
        x0 = np.append(np.zeros(6), bias) if with_bias else np.zeros(6)
        fit = least_squares(
            residuals, x0, args=(T0,), jac="2-point", diff_step=1e-7, loss="huber", f_scale=huber_k, x_scale=np.full(n_par, 0.01)
        )
        T = retract(T0, fit.x[:6])
        bias = float(fit.x[6]) if with_bias else 0.0
    moved = [v.with_dark_bias(bias) for v in views] if with_bias else views
    L = _whiteners(T, moved, range_sigma_m)
    r, J = _whitened(T, moved, L, True)
    if with_bias:  # d(residual)/d(bias) = -(dark) * beam . n, whitened like the residuals
        cols = []
        for v, w in zip(moved, L):
            beams = v.points_laser / np.maximum(np.linalg.norm(v.points_laser, axis=1), 1e-9)[:, None]
            dark = v.dark if v.dark is not None else np.zeros(len(beams))
            cols.append(_apply(w, -dark * (beams @ T[:3, :3].T @ v.n_cam)))
        J = np.column_stack([J, np.concatenate(cols)])
    w = np.where(np.abs(r) <= huber_k, 1.0, huber_k / np.maximum(np.abs(r), 1e-12))
    dof = max(len(r) - n_par, 1)
    s2 = float(np.sum(w * r**2) / dof)
    info = J.T @ (w[:, None] * J)
    cov_all = s2 * np.linalg.inv(info)
    cov = cov_all[:6, :6]
    rms = np.array([np.sqrt(np.mean(point_plane_residuals(T, v) ** 2)) for v in moved])
    return Solution(
        T, 0.5 * (cov + cov.T), np.array(T_initial, dtype=float), rms, s2, len(r),
        bias if with_bias else None, float(np.sqrt(cov_all[6, 6])) if with_bias else None, n_dark, float((1.4826 * np.median(np.abs(r))) ** 2),
    )


def estimate_range_sigma(
    views: list[PlaneView], T_initial: np.ndarray, sigma_start_m: float, huber_k: float = 2.5, dark_bias: bool = True, max_iterations: int = 8
) -> tuple[Solution, float]:
    """The fit and the range noise that makes its variance factor one (a variance-component estimate of the
    range part, with the board planes' part from the corners held): the noise is scaled by the square root
    of the variance factor and the fit redone until the factor is within 3 % of one. The factor is the robust
    one (from the median absolute whitened residual), so that returns off the board do not inflate the noise,
    which would widen the selection, which would let more of them in. Returns the last fit (made with the
    returned noise) and the noise in metres."""
    sigma = float(sigma_start_m)
    T = np.array(T_initial, dtype=float)
    for _ in range(max_iterations):
        solution = refine(views, T, sigma, huber_k, passes=1, dark_bias=dark_bias)
        T = solution.T_cam_laser
        if abs(solution.robust_variance_factor - 1.0) <= 0.03:
            break
        sigma = float(np.clip(sigma * np.sqrt(solution.robust_variance_factor), 0.1 * sigma, 10.0 * sigma))
    return refine(views, T, sigma, huber_k, dark_bias=dark_bias), sigma


def refine_unweighted(views: list[PlaneView], T_initial: np.ndarray, scale_m: float, max_evaluations: int = 30) -> np.ndarray:
    """A quick robust fit of plain point-to-plane distances (Huber, ``scale_m``): for hypotheses, not for the answer."""

    packed = _PackedViews(views)  # (the views as one array: as the view-by-view functions, to the bit)
    last: list = [None, None]  # the jacobian is asked for at the point whose residuals were just evaluated

    def pose(xi):
        key = xi.tobytes()
        if last[0] != key:
            last[:] = key, retract(T_initial, xi)
        return last[1]

    def residuals(xi):
        return packed.residuals(pose(xi))

    def jacobian(xi):
        return packed.jacobian(pose(xi))

    fit = least_squares(residuals, np.zeros(6), jac=jacobian, loss="huber", f_scale=scale_m, max_nfev=max_evaluations)
    return retract(T_initial, fit.x)


def pose_groups(views: list[PlaneView], angle_tol_rad: float = np.radians(1.0), distance_tol_m: float = 0.01) -> list[list[int]]:
    """Views grouped by board pose: a recording often holds the same pose several times, and those
    views are not independent evidence."""
    groups: list[list[int]] = []
    for k, v in enumerate(views):
        for g in groups:
            ref = views[g[0]]
            if np.arccos(np.clip(v.n_cam @ ref.n_cam, -1.0, 1.0)) <= angle_tol_rad and abs(v.d_m - ref.d_m) <= distance_tol_m:
                g.append(k)
                break
        else:
            groups.append([k])
    return groups


def jackknife_covariance(
    views: list[PlaneView], T: np.ndarray, range_sigma_m: float, huber_k: float = 2.5, dark_bias: bool = True
) -> tuple[np.ndarray, int] | None:
    """Leave-one-pose-out covariance of the right perturbation at ``T`` (order [rot, trans]), and the number
    of poses; None with fewer than four poses. Unlike :func:`refine`'s covariance it does not assume the
    range noise is white: a range bias that differs between poses shows in it."""
    groups = pose_groups(views)
    if len(groups) < 4:
        return None
    xis = []
    for g in groups:
        rest = [v for k, v in enumerate(views) if k not in g]
        xis.append(local(T, refine(rest, T, range_sigma_m, huber_k, passes=1, dark_bias=dark_bias).T_cam_laser))
    xis = np.asarray(xis)
    n = len(xis)
    dev = xis - xis.mean(axis=0)
    return (n - 1) / n * dev.T @ dev, n
