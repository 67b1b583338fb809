"""What a run's pose covariances say about its height and tilt: the marginal sigma of the body
origin's world height and of the body's pitch, frame by frame, and their summary over a drive.

Convention (the package's, as :func:`~dem_graph.evaluation.trajectory_metrics.pose_nees`): a pose
covariance ``P`` (6x6, gtsam order [rotation, translation], radians and metres) is that of the
**right perturbation** ``T_true = T_est @ Exp(xi)``, so both halves of ``xi`` are in the body frame.
To first order the body origin then moves by ``R @ xi_t`` in the world and the body turns by the
world-frame rotation vector ``R @ xi_r``.

Numpy only. No files, no plotting.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def _check(T_world_body, covariances) -> tuple[np.ndarray, np.ndarray]:
    T = np.asarray(T_world_body, dtype=float)
    P = np.asarray(covariances, dtype=float)
    n = len(T)
    if T.shape != (n, 4, 4) or P.shape != (n, 6, 6):
        raise ValueError(f"need (N,4,4) poses and (N,6,6) covariances, got {T.shape} and {P.shape}")
    return T, P


def height_sigma_m(T_world_body, covariances) -> np.ndarray:
    """The marginal sigma of the world height (z) of each body origin, metres (N,).

    ``T_world_body`` (N,4,4); ``covariances`` (N,6,6), right perturbation [rot, trans] (m, rad).
    The origin moves by ``R @ xi_t`` in the world, so ``sigma_z^2 = (R P_tt R^T)[2, 2]`` with
    ``P_tt`` the translation block: the body's own sigma in x, y and z mix in by the tilt."""
    T, P = _check(T_world_body, covariances)
    r_z = T[:, 2, :3]  # world z in body axes: the third row of R
    var = np.einsum("ni,nij,nj->n", r_z, P[:, 3:, 3:], r_z)
    return np.sqrt(np.maximum(var, 0.0))


def pitch_sigma_rad(T_world_body, covariances) -> np.ndarray:
    """The marginal sigma of each body's pitch, radians (N,).

    Pitch is the angle of the body's forward axis (x) to the world's horizontal plane, i.e. the
    pitch of the ZYX (yaw, pitch, roll) Euler angles, ``theta = -asin(R[2, 0])``: a tilt about the
    horizontal axis across the direction of travel, whatever the heading or roll. With the body
    rotation ``xi_r`` (body frame), ``d theta = (R[2,2] xi_r[1] - R[2,1] xi_r[2]) / cos(theta)``,
    ``cos(theta) = sqrt(R[2,1]^2 + R[2,2]^2)``; level and without roll it is ``xi_r[1]``, the
    rotation about the body's lateral axis (y). Not defined at +-90 deg of pitch (nan there)."""
    T, P = _check(T_world_body, covariances)
    R = T[:, :3, :3]
    cos_pitch = np.hypot(R[:, 2, 1], R[:, 2, 2])
    with np.errstate(divide="ignore", invalid="ignore"):
        g = np.stack([np.zeros(len(R)), R[:, 2, 2], -R[:, 2, 1]], axis=1) / cos_pitch[:, None]
    var = np.einsum("ni,nij,nj->n", g, P[:, :3, :3], g)
    return np.where(cos_pitch > 1e-9, np.sqrt(np.maximum(var, 0.0)), np.nan)


@dataclass(frozen=True)
class PosteriorSummary:
    """The height and pitch sigmas over a drive: the root mean square over its frames and at its last frame."""

    frames: int
    height_sigma_rms_m: float
    height_sigma_end_m: float
    pitch_sigma_rms_rad: float
    pitch_sigma_end_rad: float

    @property
    def pitch_sigma_end_deg(self) -> float:
        return float(np.degrees(self.pitch_sigma_end_rad))


def posterior_summary(T_world_body, covariances) -> PosteriorSummary:
    """:func:`height_sigma_m` and :func:`pitch_sigma_rad` over the frames (rms) and at the last one;
    nan for no frame."""
    h = height_sigma_m(T_world_body, covariances)
    p = pitch_sigma_rad(T_world_body, covariances)
    if len(h) == 0:
        return PosteriorSummary(0, np.nan, np.nan, np.nan, np.nan)
    return PosteriorSummary(len(h), _rms(h), float(h[-1]), _rms(p), float(p[-1]))


def _rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(x))))


__all__ = ["PosteriorSummary", "height_sigma_m", "pitch_sigma_rad", "posterior_summary"]
