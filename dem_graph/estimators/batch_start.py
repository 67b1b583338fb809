"""The batch's start: every landmark fitted to the online pass's poses, held fixed (``isam2-batch``).

The online pass leaves each landmark where the graph last had it, and the poses where its latest
keyframe estimates put them; the two do not agree (:mod:`~dem_graph.estimators.batch`). With the
poses held, the landmarks no longer see each other through them: each one's fit is a 3-parameter
problem of its own, tied to the others only by the links of a refreshed patch. So it is solved here
for all landmarks at once, in arrays, by Levenberg-Marquardt damped group by group (a landmark with
those its links tie it to):

- each projection (the camera through ``T_body_cam``, OpenCV's distortion), with ``sigma_px`` and
  the Huber weight of its residual, as in the batch's graph;
- each seed as a Gaussian prior on the landmark in its seed frame's body frame (``p_body``,
  ``Sigma_body``): a laser point's factors are that to first order; a camera point's (the range
  along the ray and the seed pixel) are close to it, which is all a start needs;
- each link between the two landmarks it ties (one sparse solve for all).

It replaces a Levenberg-Marquardt run of the whole graph with every pose pinned: on `paper` seed 0
(16 179 landmarks, 216 683 pixels) about 8 s for five iterations, against 0.7-1.0 s for ten here,
and the batch then ends within 8 um of the same answer (docs/isam2_design.md, "The batch's time").
The IMU's velocities and biases, also fitted to the held poses, are left to gtsam (their factors
alone: 0.4 s).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse
import scipy.sparse.csgraph
import scipy.sparse.linalg

from dem_graph.estimators.graph_factors import HUBER_K
from dem_graph.estimators.projection_kernel import pixel_normal_equations
from dem_graph.geometry.camera import PinholeCamera
from dem_graph.geometry.se3 import invert


def _sum_by(index: np.ndarray, values: np.ndarray, n: int) -> np.ndarray:
    """Per group ``0 .. n - 1`` of ``index`` (m,), the sum of ``values`` (m, ...)."""
    flat = values.reshape(len(values), int(np.prod(values.shape[1:])))
    out = np.empty((n, flat.shape[1]))
    for j in range(flat.shape[1]):
        out[:, j] = np.bincount(index, weights=flat[:, j], minlength=n)
    return out.reshape((n,) + values.shape[1:])


_EPS_INFO = 1e-9  # 1/m^2, added to every landmark's information: one with none stays where it is


def _solve(H: np.ndarray, g: np.ndarray, links: np.ndarray, w_link: np.ndarray) -> np.ndarray:
    """The Gauss-Newton step ``-A^-1 g`` of the landmarks (n,3), ``A`` the blocks ``H`` (n,3,3) on the
    diagonal and ``-w_link I`` between the landmarks of each link (a sparse solve: the links chain a
    point's landmarks across its patch refreshes)."""
    n = len(H)
    if not len(links):
        return -np.linalg.solve(H, g[..., None])[..., 0]
    i3 = np.arange(3)
    rows = [(3 * np.arange(n)[:, None, None] + i3[None, :, None]).repeat(3, axis=2).ravel()]
    cols = [(3 * np.arange(n)[:, None, None] + i3[None, None, :]).repeat(3, axis=1).ravel()]
    vals = [H.ravel()]
    for a, b in ((links[:, 0], links[:, 1]), (links[:, 1], links[:, 0])):
        rows.append((3 * a[:, None] + i3).ravel())
        cols.append((3 * b[:, None] + i3).ravel())
        vals.append(np.repeat(-w_link, 3))
    A = scipy.sparse.csc_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(3 * n, 3 * n))
    return -scipy.sparse.linalg.spsolve(A, g.ravel()).reshape(n, 3)


def fit_landmarks(
    X_world: np.ndarray,
    T_world_body: np.ndarray,
    obs_pose: np.ndarray,
    obs_landmark: np.ndarray,
    obs_uv_px: np.ndarray,
    sigma_px: float,
    camera: PinholeCamera,
    T_body_cam: np.ndarray,
    seed_pose: np.ndarray,
    seed_landmark: np.ndarray,
    seed_p_body: np.ndarray,
    seed_Sigma_body: np.ndarray,
    links: np.ndarray,
    link_sigma_m: np.ndarray,
    robust: bool = True,
    max_iterations: int = 10,
    tol_m: float = 1e-6,
) -> tuple[np.ndarray, int]:
    """The landmarks ``X_world`` (n,3) moved to their best fit to the poses ``T_world_body`` (p,4,4),
    held, and the iterations taken. Observation ``i`` is landmark ``obs_landmark[i]`` seen from pose
    ``obs_pose[i]`` at ``obs_uv_px[i]``; seed ``j`` puts landmark ``seed_landmark[j]`` at
    ``seed_p_body[j]`` (covariance ``seed_Sigma_body[j]``, m^2) in pose ``seed_pose[j]``'s body frame;
    ``links`` (l,2) ties landmark pairs within ``link_sigma_m`` (l,). Indices are rows of the arrays.
    Stops when no landmark moves by more than ``tol_m``. A landmark with no information (no seed, no
    usable observation, no link) stays where it is."""
    X = np.array(X_world, dtype=float).reshape(-1, 3)
    n = len(X)
    if not n:
        return X, 0
    T_cam_world = invert(np.asarray(T_world_body, dtype=float) @ np.asarray(T_body_cam, dtype=float))
    R_cw, t_cw = np.ascontiguousarray(T_cam_world[:, :3, :3]), np.ascontiguousarray(T_cam_world[:, :3, 3])
    intrinsics = camera.intrinsics_array
    obs_pose = np.asarray(obs_pose, dtype=np.int64)
    obs_landmark = np.asarray(obs_landmark, dtype=np.int64)
    obs_uv_px = np.asarray(obs_uv_px, dtype=float)
    # the seeds' priors, in the world frame: mean and information
    T_seed = np.asarray(T_world_body, dtype=float)[seed_pose]
    R_seed = T_seed[:, :3, :3]
    seed_mean = np.einsum("kij,kj->ki", R_seed, seed_p_body) + T_seed[:, :3, 3]
    seed_info = R_seed @ np.linalg.inv(seed_Sigma_body) @ np.swapaxes(R_seed, 1, 2)
    H_seed = _sum_by(seed_landmark, seed_info, n)
    links = np.asarray(links, dtype=np.int64).reshape(-1, 2)
    w_link = 1.0 / np.asarray(link_sigma_m, dtype=float) ** 2
    H_link = np.bincount(links[:, 0], weights=w_link, minlength=n) + np.bincount(links[:, 1], weights=w_link, minlength=n)

    def linearised(X: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per landmark at ``X``: its cost (its pixels' Huber losses, its seeds' and its links' to later landmarks squares, halved),
        the Gauss-Newton information (n,3,3) and gradient (n,3), the links' coupling left to :func:`_solve`."""
        cost, H, g = pixel_normal_equations(X, obs_landmark, R_cw, t_cw, obs_pose, obs_uv_px, intrinsics, sigma_px, HUBER_K if robust else 0.0)
        d_seed = X[seed_landmark] - seed_mean
        info_d = np.einsum("kij,kj->ki", seed_info, d_seed)
        cost += np.bincount(seed_landmark, weights=0.5 * np.sum(d_seed * info_d, axis=1), minlength=n)
        H += H_seed
        g += _sum_by(seed_landmark, info_d, n)
        if len(links):
            d = X[links[:, 0]] - X[links[:, 1]]
            g += _sum_by(links[:, 0], w_link[:, None] * d, n) - _sum_by(links[:, 1], w_link[:, None] * d, n)
            cost += np.bincount(links[:, 0], weights=0.5 * w_link * np.sum(d**2, axis=1), minlength=n)  # (once, with the landmark before: a group's sum is its cost)
        return cost, H, g

    # Levenberg-Marquardt, damped group by group (a landmark with those its links tie it to): a group
    # whose cost a step raised goes back and takes a shorter one next time (a pixel's Huber weight can
    # change with the step)
    n_groups, group = scipy.sparse.csgraph.connected_components(scipy.sparse.coo_matrix((np.ones(len(links)), (links[:, 0], links[:, 1])), shape=(n, n)), directed=False)
    damping = np.full(n_groups, 1e-4)
    cost, H, g = linearised(X)
    cost = np.bincount(group, weights=cost, minlength=n_groups)
    iterations = 0
    while iterations < max_iterations:
        iterations += 1
        diag = np.einsum("kii->ki", H)
        A = H + (damping[group][:, None] * diag)[:, :, None] * np.eye(3) + (H_link + _EPS_INFO)[:, None, None] * np.eye(3)
        X_new = X + _solve(A, g, links, w_link)
        cost_new, H_new, g_new = linearised(X_new)
        cost_new = np.bincount(group, weights=cost_new, minlength=n_groups)
        worse = ~(cost_new <= cost)  # (NaN: worse)
        if np.any(worse):
            X_new[worse[group]] = X[worse[group]]
            cost_new, H_new, g_new = linearised(X_new)
            cost_new = np.bincount(group, weights=cost_new, minlength=n_groups)
        damping = np.where(worse, damping * 10.0, np.maximum(damping * 0.1, 1e-9))
        moved = np.max(np.abs(X_new - X), initial=0.0)
        X, cost, H, g = X_new, cost_new, H_new, g_new
        if moved < tol_m:
            break
    return X, iterations


__all__ = ["fit_landmarks"]
