"""IMU samples preintegrated between two times with gtsam's combined preintegration.

:func:`preintegration_params` turns the rig's :class:`~dem_graph.geometry.rig.ImuSpec` into gtsam's
``PreintegrationCombinedParams`` (gravity along the world's -z, the IMU's pose on the body, the
noise densities as continuous-time covariances), so the preintegrated increment is between *body*
poses and can sit between two pose keys of the graph. :class:`ImuBuffer` keeps the samples as they
come and integrates any span of time: each sample holds from its own time to the next sample's (the
last one until the span's end), the first span's start falls inside the sample before it.
"""

from __future__ import annotations

import bisect

import gtsam
import numpy as np
from scipy.spatial.transform import Rotation

from dem_graph.geometry.rig import ImuSpec

MAX_GAP_PERIODS = 5  # samples further apart than this many sample periods do not measure the span between them
INTEGRATION_SIGMA = 1e-4  # velocity random walk standing for the error of integrating the position with samples held over their interval, m/s per sqrt(s) (the vibration makes it 0.1 mm over a frame in the simulator)


def preintegration_params(spec: ImuSpec) -> gtsam.PreintegrationCombinedParams:
    """gtsam's combined preintegration parameters for ``spec``, in the body frame."""
    params = gtsam.PreintegrationCombinedParams.MakeSharedU(spec.gravity_mps2)
    I3 = np.eye(3)
    params.setGyroscopeCovariance(spec.gyro_noise_density**2 * I3)
    params.setAccelerometerCovariance(spec.accel_noise_density**2 * I3)
    params.setIntegrationCovariance(INTEGRATION_SIGMA**2 * I3)
    params.setBiasOmegaCovariance(spec.gyro_bias_random_walk**2 * I3)
    params.setBiasAccCovariance(spec.accel_bias_random_walk**2 * I3)
    params.setBodyPSensor(gtsam.Pose3(np.asarray(spec.T_body_imu, dtype=float)))
    return params


def bias_sigmas(spec: ImuSpec) -> np.ndarray:
    """The biases' spread at the start in gtsam's bias order (accelerometer m/s^2 x3, gyroscope rad/s x3),
    kept above zero so that a prior on them has a proper noise model."""
    return np.maximum(np.r_[np.full(3, spec.accel_bias_sigma), np.full(3, spec.gyro_bias_sigma)], 1e-6)


def bias(gyro_rad_s=(0.0, 0.0, 0.0), accel_mps2=(0.0, 0.0, 0.0)) -> gtsam.imuBias.ConstantBias:
    """gtsam's bias from a gyroscope and an accelerometer bias (IMU frame)."""
    return gtsam.imuBias.ConstantBias(np.asarray(accel_mps2, dtype=float), np.asarray(gyro_rad_s, dtype=float))


def preintegrate(
    params: gtsam.PreintegrationCombinedParams, t_s: np.ndarray, gyro_rad_s: np.ndarray, accel_mps2: np.ndarray, t_a_s: float, t_b_s: float,
    bias_estimate: gtsam.imuBias.ConstantBias,
) -> gtsam.PreintegratedCombinedMeasurements:
    """Samples (times ``t_s`` increasing, (N,3) rates and forces) integrated from ``t_a_s`` to
    ``t_b_s``: each holds from its time to the next one's, the last until ``t_b_s``; the first must
    be at or before ``t_a_s``."""
    if not t_b_s > t_a_s:
        raise ValueError(f"an IMU span must end after it starts, got {t_a_s} to {t_b_s} s")
    if not len(t_s) or t_s[0] > t_a_s:
        raise ValueError(f"no IMU sample holds at {t_a_s:.6f} s")
    pim = gtsam.PreintegratedCombinedMeasurements(params, bias_estimate)
    k = int(np.searchsorted(t_s, t_a_s, side="right")) - 1  # the sample that holds at t_a
    t = t_a_s
    while t < t_b_s:
        t_next = min(float(t_s[k + 1]), t_b_s) if k + 1 < len(t_s) else t_b_s
        if t_next > t:
            pim.integrateMeasurement(accel_mps2[k], gyro_rad_s[k], t_next - t)
        t = t_next
        k += 1
    return pim


def gyro_rotation(
    spec: ImuSpec, samples: tuple[np.ndarray, np.ndarray, np.ndarray], t_a_s: float, t_b_s: float, gyro_bias_rad_s: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The body's rotation from ``t_a_s`` to ``t_b_s`` by the gyroscope of ``samples`` (:meth:`ImuBuffer.span`),
    ``R_a_b`` (3x3, body frame), and its 3x3 covariance (rad^2, right perturbation: white noise and
    the bias's uncertainty at the start), with ``gyro_bias_rad_s`` taken off."""
    t, gyro, _ = samples
    edges = np.clip(np.append(t, t_b_s), t_a_s, t_b_s)
    rotvecs = (gyro - np.asarray(gyro_bias_rad_s, dtype=float)) * np.diff(edges)[:, None]
    R_imu = np.eye(3)
    for R_k in Rotation.from_rotvec(rotvecs).as_matrix():
        R_imu = R_imu @ R_k
    R_body_imu = np.asarray(spec.T_body_imu, dtype=float)[:3, :3]
    T = t_b_s - t_a_s
    variance = spec.gyro_noise_density**2 * T + (spec.gyro_bias_sigma * T) ** 2  # per axis, isotropic
    return R_body_imu @ R_imu @ R_body_imu.T, variance * np.eye(3)


def with_rotation(U: np.ndarray, Q: np.ndarray, R_prev_curr: np.ndarray, C_rot: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A frame's motion ``U`` (4x4) and covariance ``Q`` (6x6, [rot, trans]) with the rotation
    replaced by a measured one (3x3) and its covariance (3x3), uncorrelated with the translation."""
    U = U.copy()
    U[:3, :3] = R_prev_curr
    Q = Q.copy()
    Q[:3, :] = 0.0
    Q[:, :3] = 0.0
    Q[:3, :3] = C_rot
    return U, Q


def mean_specific_force(samples: tuple[np.ndarray, np.ndarray, np.ndarray], t_a_s: float, t_b_s: float) -> np.ndarray:
    """The accelerometer's mean over ``t_a_s`` to ``t_b_s`` (IMU frame, m/s^2), each sample held
    until the next (:meth:`ImuBuffer.span`)."""
    t, _, accel = samples
    w = np.diff(np.clip(np.append(t, t_b_s), t_a_s, t_b_s))
    return w @ accel / (t_b_s - t_a_s)


class ImuBuffer:
    """The samples received so far (times strictly increasing) and their preintegration over a span."""

    def __init__(self, spec: ImuSpec):
        self.spec = spec
        self.params = preintegration_params(spec)
        self._t: list[float] = []
        self._gyro: list[np.ndarray] = []
        self._accel: list[np.ndarray] = []

    def __len__(self) -> int:
        return len(self._t)

    @property
    def last_t_s(self) -> float | None:
        """The newest sample's time, None before the first."""
        return self._t[-1] if self._t else None

    def add(self, t_s: float, gyro_rad_s: np.ndarray, accel_mps2: np.ndarray) -> None:
        if self._t and t_s <= self._t[-1]:
            raise ValueError(f"IMU sample at {t_s:.6f} s is not after the last one ({self._t[-1]:.6f} s)")
        self._t.append(float(t_s))
        self._gyro.append(np.asarray(gyro_rad_s, dtype=float).reshape(3))
        self._accel.append(np.asarray(accel_mps2, dtype=float).reshape(3))

    def take(self, event) -> None:
        """An estimator's IMU sample (:class:`~dem_graph.datasets.events.ImuSample`), kept unless it is
        not after the newest one (the pipeline skips samples out of order before they reach an
        estimator, so this only guards)."""
        if self._t and event.t_s <= self._t[-1]:
            return
        self.add(event.t_s, event.gyro_rad_s, event.accel_mps2)

    def span(self, t_a_s: float, t_b_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """The samples that measure ``t_a_s`` to ``t_b_s``: times (n,), rates and forces (n,3), from the
        one that holds at ``t_a_s`` to the last before ``t_b_s``; None when the samples do not cover
        the span (none at or before its start, none at or after its end yet, or a gap over
        :data:`MAX_GAP_PERIODS` sample periods)."""
        max_gap_s = MAX_GAP_PERIODS / self.spec.rate_hz
        if not self._t or self._t[0] > t_a_s or self._t[-1] < t_b_s - max_gap_s:
            return None
        i = bisect.bisect_right(self._t, t_a_s) - 1
        j = bisect.bisect_left(self._t, t_b_s)
        t = np.array(self._t[i:j])
        if np.any(np.diff(np.append(t, t_b_s)) > max_gap_s):
            return None
        return t, np.array(self._gyro[i:j]), np.array(self._accel[i:j])

    def preintegrate(self, t_a_s: float, t_b_s: float, bias_estimate: gtsam.imuBias.ConstantBias) -> gtsam.PreintegratedCombinedMeasurements:
        """Every sample's increment from ``t_a_s`` to ``t_b_s`` (> ``t_a_s``), linearised at ``bias_estimate``."""
        return preintegrate(self.params, np.array(self._t), np.array(self._gyro).reshape(-1, 3), np.array(self._accel).reshape(-1, 3), t_a_s, t_b_s, bias_estimate)

    def drop_before(self, t_s: float) -> None:
        """Forget the samples no span from ``t_s`` on needs (the one that holds at ``t_s`` is kept)."""
        k = bisect.bisect_right(self._t, t_s) - 1
        if k > 0:
            del self._t[:k], self._gyro[:k], self._accel[:k]


__all__ = ["MAX_GAP_PERIODS", "ImuBuffer", "bias", "bias_sigmas", "gyro_rotation", "mean_specific_force", "preintegrate", "preintegration_params", "with_rotation"]
