"""The simulated world and the :class:`SimulatedSequence` that streams its sensor events."""

from __future__ import annotations

import heapq
import logging
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from dem_graph.datasets.base import GroundTruth, Sequence
from dem_graph.datasets.events import CameraFrame, Event, ImuSample, LaserScan, Odometry
from dem_graph.geometry.rig import SensorRig
from dem_graph.geometry.se3 import invert
from dem_graph.geometry.trajectory import Trajectory
from dem_graph.sim.config import ScenarioConfig
from dem_graph.sim.imu import ImuTrack, imu_sample_times, simulate_imu
from dem_graph.sim.laser import cast_scan
from dem_graph.sim.raycast import TerrainScene
from dem_graph.sim.render import CameraRenderer
from dem_graph.sim.terrain import Terrain, contact_surface, generate_terrain
from dem_graph.sim.texture import GroundTexture
from dem_graph.sim.vehicle import DrivenPath, SpeedProfile, VehicleMotion, generate_path

log = logging.getLogger(__name__)

# independent random streams, so that e.g. switching odometry off leaves the world unchanged (a
# stream added at the end leaves the others' numbers as they were)
_STREAMS = ("path", "terrain", "texture", "camera", "laser", "odometry", "speed", "imu")


def _rngs(seed: int) -> dict[str, np.random.Generator]:
    children = np.random.SeedSequence(seed).spawn(len(_STREAMS))
    return {name: np.random.default_rng(child) for name, child in zip(_STREAMS, children)}


@dataclass
class SimWorld:
    """Everything that does not change while the vehicle drives."""

    config: ScenarioConfig
    path: DrivenPath
    speed: SpeedProfile
    terrain: Terrain
    texture: GroundTexture
    motion: VehicleMotion
    t_end_s: float

    @classmethod
    def build(cls, config: ScenarioConfig) -> SimWorld:
        rngs = _rngs(config.seed)
        path = generate_path(config.path, config.length_m, rngs["path"], straight=config.straight_path)
        speed = SpeedProfile.generate(config.path, config.length_m, rngs["speed"])
        log.info("generating terrain")
        terrain = generate_terrain(config.terrain, path, rngs["terrain"])
        log.info("generating ground texture")
        texture = GroundTexture.generate(config.texture, terrain, rngs["texture"])
        motion = VehicleMotion(path, speed, contact_surface(terrain.elevation, config.path.tire_patch_m), config.path)
        return cls(config, path, speed, terrain, texture, motion, speed.time_at_distance(config.length_m))


class SimulatedSequence(Sequence):
    """A :class:`Sequence` rendered on the fly from a :class:`SimWorld`; deterministic for a given seed."""

    def __init__(self, world: SimWorld):
        self.world = world
        self.name = world.config.name
        self._scene: TerrainScene | None = None
        self._renderer: CameraRenderer | None = None
        self._imu: ImuTrack | None = None
        gt_t = np.arange(0.0, world.t_end_s, 1.0 / world.config.ground_truth_rate_hz)
        gt_t = np.append(gt_t, world.t_end_s) if world.t_end_s - gt_t[-1] > 1e-9 else gt_t
        self._ground_truth = GroundTruth(Trajectory.from_poses(gt_t, world.motion.T_world_body(gt_t)), world.terrain.elevation)

    @classmethod
    def from_config(cls, config: ScenarioConfig) -> SimulatedSequence:
        return cls(SimWorld.build(config))

    @property
    def config(self) -> ScenarioConfig:
        return self.world.config

    @property
    def rig(self) -> SensorRig:
        return self.world.config.rig

    @property
    def t_start_s(self) -> float:
        return 0.0

    @property
    def T_world_body_initial(self) -> np.ndarray:
        return self.world.motion.T_world_body(0.0)

    @property
    def ground_truth(self) -> GroundTruth:
        return self._ground_truth

    @property
    def has_odometry(self) -> bool:
        return self.world.config.with_odometry and self.rig.odometry is not None

    @property
    def has_imu(self) -> bool:
        return self.world.config.with_imu and self.rig.imu is not None

    def imu_track(self) -> ImuTrack:
        """Every IMU sample with the truth behind it (:mod:`dem_graph.sim.imu`), as :meth:`events` yields them."""
        if not self.has_imu:
            raise ValueError(f"scenario {self.name!r} has no IMU")
        if self._imu is None:
            spec = self.rig.imu
            self._imu = simulate_imu(self.world.motion.T_world_body, spec.T_body_imu, spec, self.world.t_end_s, _rngs(self.world.config.seed)["imu"])
        return self._imu

    @property
    def scene(self) -> TerrainScene:
        if self._scene is None:
            self._scene = TerrainScene(self.world.terrain.elevation)
        return self._scene

    @property
    def renderer(self) -> CameraRenderer:
        if self._renderer is None:
            cam = self.rig.camera
            self._renderer = CameraRenderer(self.scene, self.world.texture, cam.model, self.world.config.lighting, cam.noise_sigma_dn)
        return self._renderer

    # --- event times -------------------------------------------------------------------------
    def camera_times(self) -> np.ndarray:
        return np.arange(0.0, self.world.t_end_s + 1e-9, 1.0 / self.rig.camera.rate_hz)

    def laser_times(self) -> np.ndarray:
        return np.arange(self.world.config.laser_time_offset_s, self.world.t_end_s + 1e-9, 1.0 / self.rig.laser.rate_hz)

    def odometry_times(self) -> np.ndarray:
        if not self.has_odometry:
            return np.zeros(0)
        return np.arange(self.world.config.odometry_time_offset_s, self.world.t_end_s + 1e-9, 1.0 / self.rig.odometry.rate_hz)

    def imu_times(self) -> np.ndarray:
        return imu_sample_times(self.world.t_end_s, self.rig.imu.rate_hz) if self.has_imu else np.zeros(0)

    def event_count(self) -> int:
        return len(self.camera_times()) + len(self.laser_times()) + len(self.odometry_times()) + len(self.imu_times())

    # --- streams -----------------------------------------------------------------------------
    def _camera_events(self, rng) -> Iterator[tuple[float, int, Event]]:
        T_body_cam = self.rig.T_body_cam
        for k, t in enumerate(self.camera_times()):
            image = self.renderer.render(self.world.motion.T_world_body(t) @ T_body_cam, rng)
            yield (t, 2, CameraFrame(float(t), image, k))

    def _laser_events(self, rng) -> Iterator[tuple[float, int, Event]]:
        T_body_laser = self.rig.T_body_laser
        for k, t in enumerate(self.laser_times()):
            ranges = cast_scan(self.scene, self.world.motion.T_world_body(t) @ T_body_laser, self.rig.laser, rng)
            yield (t, 1, LaserScan(float(t), ranges, k))

    def _odometry_events(self, rng) -> Iterator[tuple[float, int, Event]]:
        times = self.odometry_times()
        if len(times) == 0:
            return
        spec = self.rig.odometry
        stamps = np.concatenate([[self.t_start_s], times])
        poses = self.world.motion.T_world_body(stamps)
        scale = 1.0 + spec.sigma_scale * rng.standard_normal()  # slip: one scale error for the run
        for k in range(len(times)):
            T_rel = invert(poses[k]) @ poses[k + 1]
            distance = float(np.linalg.norm(T_rel[:3, 3]))
            xi = rng.standard_normal(6) * np.sqrt(np.diag(spec.white_noise_covariance(distance)))
            T_meas = T_rel.copy()
            T_meas[:3, 3] *= scale
            T_meas[:3, :3] = T_rel[:3, :3] @ Rotation.from_rotvec(xi[:3]).as_matrix()
            T_meas[:3, 3] += T_rel[:3, :3] @ xi[3:]
            yield (float(times[k]), 0, Odometry(float(times[k]), float(stamps[k]), T_meas, spec.increment_covariance(distance), k))

    def _imu_events(self) -> Iterator[tuple[float, int, Event]]:
        if not self.has_imu:
            return
        track = self.imu_track()
        for k, t in enumerate(track.t_s):  # at equal times after the camera: sample k holds the motion from t_k on
            yield (float(t), 3, ImuSample(float(t), track.gyro_rad_s[k].copy(), track.accel_mps2[k].copy(), k))

    def laser_scans(self) -> tuple[np.ndarray, np.ndarray]:
        """The scans :meth:`events` yields (same noise), without rendering a single image."""
        scans = [scan for _, _, scan in self._laser_events(_rngs(self.world.config.seed)["laser"])]
        return np.array([s.t_s for s in scans]), np.array([s.ranges_m for s in scans], dtype=float).reshape(len(scans), -1)

    def noiseless_scans(self) -> Iterator[np.ndarray]:
        """The laser ranges of every scan without noise (for pictures and tests)."""
        for _, _, scan in self._laser_events(None):
            yield scan.ranges_m

    def events(self) -> Iterator[Event]:
        rngs = _rngs(self.world.config.seed)
        streams = [self._odometry_events(rngs["odometry"]), self._laser_events(rngs["laser"]), self._camera_events(rngs["camera"]), self._imu_events()]
        for _, _, event in heapq.merge(*streams, key=lambda item: (item[0], item[1])):
            yield event
