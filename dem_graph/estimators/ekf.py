"""The paper's estimator: an EKF over the pose and the live points, in two variants (III-C).

- ``gm`` (Algorithm 1): predict, track every point in a constant-size region, one update with all
  matches (a 2n_t x 2n_t innovation covariance).
- ``ptpm`` (Algorithm 2): predict, then one point at a time, most informative first: its search
  region comes from the current innovation covariance (a chi-square gate), so regions shrink after
  the first updates; track it; update.

Prediction uses wheel odometry when the dataset has it (``motion_model: auto``) and a
constant-velocity model otherwise. With an IMU (the rig's ``imu`` section, ``motion.use_imu``) the
gyroscope's rotation over the frame replaces the prediction's (the gyroscope's bias joins the
state), and the accelerometer's mean over the frame updates roll and pitch as gravity's direction.
"""

from __future__ import annotations

import logging
import math
import time
from typing import Literal

import numpy as np
from pydantic import Field, PositiveFloat
from scipy.stats import chi2

from dem_graph.config_types import StrictModel
from dem_graph.datasets.events import CameraFrame, ImuSample
from dem_graph.estimators.base import EstimatorResult, FrameDrivenEstimator, FrameRecord
from dem_graph.estimators.ekf_filter import EkfState
from dem_graph.estimators.false_matches import FalseMatches
from dem_graph.estimators.imu_preintegration import ImuBuffer, gyro_rotation, mean_specific_force, with_rotation
from dem_graph.estimators.point_archive import PointArchive
from dem_graph.estimators.settings import MotionConfig, SharedSettings
from dem_graph.frontend.frontend import FrontEnd
from dem_graph.frontend.pose_history import PoseHistory
from dem_graph.geometry.ground_view import laser_view
from dem_graph.geometry.rig import SensorRig

log = logging.getLogger(__name__)


class EkfOptions(StrictModel):
    """What only the EKF baselines have (the variant is the estimator's name)."""

    gm_search_half_size_px: int = Field(20, ge=1, description="GM: constant half size of every search region, pixels")
    imu_gravity_sigma_mps2: PositiveFloat = Field(
        0.2, description="with an IMU: the body's horizontal acceleration the tilt update does not model (speeding up, slowing down, vibration), m/s^2 per axis"
    )


class EkfConfig(SharedSettings, EkfOptions):
    """The EKF's options with the settings every estimator shares."""

    variant: Literal["gm", "ptpm"] = Field("ptpm", description="gm: one batch update per image; ptpm: point to point")


GRAVITY_GATE_CHI2 = float(chi2.ppf(0.99, 2))  # a frame whose specific force is further from gravity is not a tilt measurement


class EkfSlam(FrameDrivenEstimator):
    """EKF SLAM with the shared front end; feed it events in time order."""

    def __init__(self, rig: SensorRig, T_world_body_initial: np.ndarray, t_start_s: float, has_odometry: bool, config: EkfConfig | None = None):
        self.config = config or EkfConfig()
        self.name = f"ekf-{self.config.variant}"
        self.rig = rig
        self.frontend = FrontEnd(self.config.frontend, rig)
        self._speed_from_ground = False
        self._start_speed(self.config.motion, self.frontend)  # without odometry: measured from the ground on the first frames (_measure_speed)
        view = laser_view(rig)
        if not view.in_view:  # the paper's method ties a return to the image point it falls on, in the frame it is measured
            log.warning("%s: the laser's line is not in the camera's view (%d of its %d ground points in the image): this EKF cannot use "
                        "its returns, its scale and tilt come from the camera's mount alone",
                        self.name, view.in_image, view.on_ground)
        m = self.config.motion
        super().__init__(m, has_odometry, t_start_s)
        v0 = np.zeros(6)
        v0[3] = m.initial_speed_mps
        P_v0 = np.diag([0.3**2] * 3 + [m.initial_sigma_speed_mps**2] * 3)
        # the IMU's samples until the frame they measure (motion.use_imu and a rig with an imu section)
        self._imu = ImuBuffer(rig.imu) if m.use_imu and rig.imu is not None else None
        bias_sigmas = None if self._imu is None else (rig.imu.gyro_bias_sigma, rig.imu.accel_bias_sigma)
        self.state = EkfState(T_world_body_initial, np.eye(6) * m.initial_sigma_pose**2, v0, P_v0, bias_sigmas)
        self.history = PoseHistory()
        self.history.append(self.t_s, self.state.T_world_body)
        self._frames: list[FrameRecord] = []
        self._archived = PointArchive(self.frontend)
        self._false_matches = FalseMatches(self.config.false_matches, self.frontend.counters)
        self._gate = self.frontend.tracker.gate_chi2
        self._R = self.config.frontend.sigma_px**2
        # per point searched in the last frame, in search order: the region's half sizes (px) as
        # searched, and (PTPM) as the prior covariance of the frame would have made it
        self.last_search_sizes: list[tuple[int, int]] = []
        self.last_prior_search_sizes: list[tuple[int, int]] = []

    def _process(self, event: CameraFrame) -> FrameRecord:
        self._pending_frame = None
        timing = {}
        t0 = time.perf_counter()
        if self.frontend.begin_frame(event.t_s, event.textureless):
            self._drop_points()  # after a camera gap: the points it made stale
        self._predict(event)
        t1 = time.perf_counter()
        timing["prediction"] = t1 - t0
        image = event.image
        # a frame without texture (the reader marked it) is not searched, loses no point and starts none
        n_live = self.state.n_points
        n_tracked, t_track, t_update = (0, 0.0, 0.0) if event.textureless else self._track_and_update(image, event.t_s)
        self._note_tracking(event.textureless, n_live, n_tracked)
        timing["tracking"], timing["update"] = t_track, t_update
        t2 = time.perf_counter()
        self.history.append(event.t_s, self.state.T_world_body)
        if not event.textureless:
            live_uv = self._drop_points()
            self._add_points(image, event.t_s, live_uv)
        self.frontend.end_frame(event.t_s, image, event.textureless)
        timing["map"] = time.perf_counter() - t2
        timing["total"] = time.perf_counter() - t0
        record = FrameRecord(event.t_s, self.state.T_world_body.copy(), self.state.pose_covariance(), self.state.n_points, n_tracked, timing)
        self._frames.append(record)
        return record

    # --- prediction --------------------------------------------------------------------------
    def _predict(self, event: CameraFrame) -> None:
        """Odometry moves the filter's pose (and sets its velocity), refined across a camera gap by
        the images on either side (:class:`~dem_graph.frontend.gap_bridge.GapBridge`); without
        odometry, its velocity does."""
        dt, increment = self._motion.advance(event.t_s)
        t_a = event.t_s - dt
        samples = self._imu_span(t_a, event.t_s) if dt > 0 else None
        if samples is not None:
            spec = self.rig.imu
            R_gyro, _ = gyro_rotation(spec, samples, t_a, event.t_s, self.state.gyro_bias_rad_s)
            var_rot = spec.gyro_noise_density**2 * dt  # white noise only: the bias is in the state
        if increment is not None:
            U, Q = self.frontend.gap_bridge.refine(event.t_s, event.image, event.textureless, *increment)
            if samples is not None:
                U, Q = with_rotation(U, Q, R_gyro, np.eye(3) * var_rot)
            self.state.predict_increment(U, Q, dt)
        else:
            if dt > 0 and self._speed_unknown:
                self._measure_speed(event)
            if samples is not None:
                self.state.predict_constant_velocity_gyro(dt, self._motion.sigma_acc[3], R_gyro, var_rot)
            elif dt > 0:
                self.state.predict_constant_velocity(dt, self._motion.sigma_acc)
        if samples is not None:
            self.state.propagate_imu_biases(spec.T_body_imu, dt, spec.gyro_bias_random_walk, spec.accel_bias_random_walk)
            self._gravity_update(samples, t_a, event.t_s)

    def _measure_speed(self, event: CameraFrame) -> None:
        """Without odometry, at the start or after a frame that tracked nothing: the velocity taken from
        the ground's motion since the last image (the speed held was a guess), and the search cap for
        that speed."""
        measured = self._ground_velocity(self.frontend, event)
        if measured is not None:
            self.state.reset_linear_velocity(*measured)
            self._speed_from_ground = True

    # --- the IMU ---------------------------------------------------------------------------------
    def on_imu(self, event: ImuSample) -> None:
        """An IMU sample: kept until the frame whose interval it measures."""
        if self._imu is not None:
            self._imu.take(event)

    def _imu_span(self, t_a_s: float, t_b_s: float):
        """The samples measuring the frame's interval (:meth:`ImuBuffer.span`), None without an IMU
        or where they do not cover it (the prediction is then the odometry's or the model's, counted)."""
        if self._imu is None:
            return None
        samples = self._imu.span(t_a_s, t_b_s)
        self._imu.drop_before(t_b_s)
        if samples is None:
            self.frontend.counters["imu_frames_without_gyro"] += 1
        return samples

    def _gravity_update(self, samples, t_a_s: float, t_b_s: float) -> None:
        """The accelerometer's mean over the frame as gravity's direction (roll and pitch), the
        centripetal acceleration of the body's velocity at the gyroscope's rate taken off."""
        spec = self.rig.imu
        T = t_b_s - t_a_s
        v = self.state.v_body
        accel_body = np.cross(v[:3], v[3:])  # the body's acceleration at a steady speed on a turn
        var = spec.accel_noise_density**2 / T + self.config.imu_gravity_sigma_mps2**2
        ok = self.state.gravity_update(mean_specific_force(samples, t_a_s, t_b_s), accel_body, spec.T_body_imu, var, spec.gravity_mps2, GRAVITY_GATE_CHI2)
        self.frontend.counters["imu_tilt_updates" if ok else "imu_tilt_gated"] += 1

    # --- tracking and update -----------------------------------------------------------------
    def _camera_pose(self) -> np.ndarray:
        return self.state.T_world_body @ self.rig.T_body_cam

    def _track_and_update(self, image, t_s: float) -> tuple[int, float, float]:
        st = self.state
        self.last_search_sizes = []
        self.last_prior_search_sizes = []
        if st.n_points == 0:
            return 0, 0.0, 0.0
        t0 = time.perf_counter()
        fe = self.frontend
        idx = np.arange(st.n_points)
        uv, Hp, Hx, in_front, _ = st.observe(idx, self.rig.camera_model, self.rig.T_body_cam)
        T_wc = self._camera_pose()  # predicted; patches refreshed in this frame are tied to it
        warps = fe.template_warps(st.point_ids, st.points_xyz, T_wc)
        if self.config.variant == "gm":
            half = self.config.gm_search_half_size_px
            sel = idx[in_front]
            ids = st.point_ids[sel]
            templates = fe.templates(ids, None if warps is None else warps[sel])
            batch = fe.track_many(image, ids, templates, uv[sel], half_size_px=half, t_s=t_s, T_world_cam=T_wc)
            self.last_search_sizes = [(u, v) for u, v in batch.search_half_size_px.tolist()]
            # an injected match must fall inside the searched square
            ok, found_uv = self._false_matches.screen_batch(sel, batch, uv, lambda i, y: np.max(np.abs(y)) <= half)
            innov = found_uv - uv[ok]
            t1 = time.perf_counter()
            if len(ok):
                st.batch_update(ok, innov, Hp[ok], Hx[ok], self._R)
            return len(ok), t1 - t0, time.perf_counter() - t1

        # PTPM: most informative first (largest predicted innovation relative to the pixel noise)
        S_all = st.innovation_covariances(Hp, Hx, self._R)
        gains = np.where(in_front, np.linalg.slogdet(S_all / self._R)[1], -np.inf)
        order = [int(i) for i in np.argsort(-gains) if np.isfinite(gains[i])]
        half_prior = np.ceil(np.sqrt(self._gate * S_all[order][:, [0, 1], [0, 1]])).astype(int)
        self.last_prior_search_sizes = [(int(u), int(v)) for u, v in half_prior]
        t_track = time.perf_counter() - t0
        t_update = 0.0
        # every template at once (they do not depend on the order); then one search per point: a
        # point's region depends on the updates before it
        templates = fe.templates(st.point_ids[order], None if warps is None else warps[order]) if order else None
        st.begin_sequential(len(order))
        n_ok = 0
        try:
            for k, i in enumerate(order):
                ta = time.perf_counter()
                d_pose, d_point = st.correction(i)
                uv_i = uv[i] + Hp[i] @ d_pose + Hx[i] @ d_point
                S = st.sequential_innovation_covariance(i, Hp[i], Hx[i], self._R)
                res = fe.track(image, int(st.point_ids[i]), templates[k], uv_i, S_px2=S, t_s=t_s, T_world_cam=T_wc)
                self.last_search_sizes.append(res.search_half_size_px)
                # an injected match must pass the point's chi-square gate
                found = self._false_matches.screen(res.uv_px if res.ok else None, uv_i, lambda y, S=S: y @ np.linalg.solve(S, y) <= self._gate)
                tb = time.perf_counter()
                t_track += tb - ta
                if found is None:
                    continue
                y = found - uv_i
                st.sequential_update(i, y, Hp[i], Hx[i], S)
                n_ok += 1
                t_update += time.perf_counter() - tb
        finally:
            tc = time.perf_counter()
            st.end_sequential()
            t_update += time.perf_counter() - tc
        return n_ok, t_track, t_update

    # --- map management ----------------------------------------------------------------------
    def _drop_points(self) -> np.ndarray:
        """Archive the points that left the view or were lost (at their estimates now); returns the pixels of those kept (n,2)."""
        st = self.state
        keep, uv = self._archived.drop_points(st.point_ids, st.points_xyz, st.T_world_body, lambda i: (st.point_covariance(i), st.points_xyz[i]))
        st.remove_points(~keep)
        return uv

    def _speed_mps(self) -> float | None:
        """The speed the focus area and the search cap are made for: the filter's once it has seen
        two frames or measured the speed from the ground, None before (the focus area's nominal speed;
        inf on a first frame whose speed the ground will measure: :meth:`_speed_unknown_at_start`)."""
        if self._speed_unknown_at_start(self.frontend):
            return math.inf
        known = len(self.history) > 2 or self._speed_from_ground
        return float(np.linalg.norm(self.state.v_body[3:])) if known else None

    def _add_points(self, image, t_s: float, occupied_uv: np.ndarray) -> None:
        """New laser and camera points, away from the live points' pixels ``occupied_uv``."""
        st = self.state
        new = self.frontend.new_points(image, t_s, st.T_world_body, self._scans.take_until(t_s), self.history, st.points_xyz, occupied_uv, self._speed_mps())
        if new:
            st.add_points(np.array([p.point_id for p in new]), np.array([p.p_body for p in new]), np.array([p.Sigma_body for p in new]))

    # --- results -----------------------------------------------------------------------------
    def archived_points_since(self, start: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
        return self._archived.since(start)

    def live_points(self) -> tuple[np.ndarray, np.ndarray]:
        return np.asarray(self.state.point_ids, dtype=np.int64), np.asarray(self.state.points_xyz, dtype=float).reshape(-1, 3)

    def result(self) -> EstimatorResult:
        """Frames so far and every point: archived ones plus the live ones at their current estimate."""
        st = self.state
        return self._archived.result(self.name, self._frames, st.point_ids, lambda i: st.points_xyz[i], st.point_covariance)


__all__ = ["EkfConfig", "EkfOptions", "EkfSlam", "MotionConfig"]
