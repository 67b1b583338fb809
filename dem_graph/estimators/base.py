"""What every estimator returns, and the interface the run loop drives."""

from __future__ import annotations

import abc
import math
from collections import Counter
from dataclasses import dataclass, field

import numpy as np

from dem_graph.datasets.events import CameraFrame, ImuSample, LaserScan, Odometry
from dem_graph.errors import EventOrderError
from dem_graph.estimators.motion import FrameMotion
from dem_graph.estimators.settings import MotionConfig
from dem_graph.geometry.trajectory import Trajectory

# other estimates of every frame's pose an estimator may give (EstimatorResult.extra_poses), by name:
# each is written as <name>.tum and measured under its name
SMOOTHED_TRAJECTORY = "trajectory_smoothed"  # isam2: every frame as smoothed at the end of the run
ONLINE_TRAJECTORY = "trajectory_online"  # isam2-batch: its online pass
EXTRA_TRAJECTORIES = (SMOOTHED_TRAJECTORY, ONLINE_TRAJECTORY)


@dataclass
class MapPoints:
    """Every point ever estimated, with its last estimate and covariance (world frame)."""

    point_id: list[int] = field(default_factory=list)
    kind: list[int] = field(default_factory=list)  # PointKind
    xyz: list[np.ndarray] = field(default_factory=list)
    covariance: list[np.ndarray] = field(default_factory=list)
    n_tracked: list[int] = field(default_factory=list)
    created_t_s: list[float] = field(default_factory=list)

    def add(self, point_id: int, kind: int, xyz: np.ndarray, covariance: np.ndarray, n_tracked: int, created_t_s: float) -> None:
        self.point_id.append(int(point_id))
        self.kind.append(int(kind))
        self.xyz.append(np.array(xyz, dtype=float))
        self.covariance.append(np.array(covariance, dtype=float))
        self.n_tracked.append(int(n_tracked))
        self.created_t_s.append(float(created_t_s))

    def __len__(self) -> int:
        return len(self.point_id)

    def arrays(self) -> dict[str, np.ndarray]:
        n = len(self)
        return {
            "point_id": np.asarray(self.point_id, dtype=np.int32),
            "kind": np.asarray(self.kind, dtype=np.uint8),
            "xyz": np.asarray(self.xyz, dtype=float).reshape(n, 3),
            "covariance": np.asarray(self.covariance, dtype=float).reshape(n, 3, 3),
            "n_tracked": np.asarray(self.n_tracked, dtype=np.int32),
            "created_t_s": np.asarray(self.created_t_s, dtype=float),
        }


@dataclass
class FrameRecord:
    t_s: float
    T_world_body: np.ndarray
    pose_covariance: np.ndarray  # 6x6 [rotation, translation], right perturbation
    n_live: int
    n_tracked: int
    timing_s: dict[str, float]


@dataclass
class EstimatorResult:
    name: str
    frames: list[FrameRecord] = field(default_factory=list)
    points: MapPoints = field(default_factory=MapPoints)
    counters: Counter = field(default_factory=Counter)
    # other estimates of every frame's pose, by name (a file stem): for the graph estimator, the
    # trajectory as smoothed at the end of the run, next to the per-frame one
    extra_poses: dict[str, np.ndarray] = field(default_factory=dict)
    # the graph estimator: each graph update's time by phase (its key: "total", "solve", "cut", ...), seconds
    graph_update_s: dict[str, list[float]] = field(default_factory=dict)

    def trajectory(self) -> Trajectory:
        return Trajectory.from_poses(np.array([f.t_s for f in self.frames]), np.array([f.T_world_body for f in self.frames]))

    def extra_trajectories(self) -> dict[str, Trajectory]:
        t = np.array([f.t_s for f in self.frames])
        return {name: Trajectory.from_poses(t, poses) for name, poses in self.extra_poses.items()}

    def pose_covariances(self) -> np.ndarray:
        return np.array([f.pose_covariance for f in self.frames])


class Estimator(abc.ABC):
    """Consumes a sequence's events in time order; :meth:`result` may be called at any time."""

    name: str = "estimator"
    # set by a live pipeline at the camera's rate: a frame's work that need not come before its pose
    # and the map may wait for :meth:`idle` (an estimator without such work ignores it)
    defer_keyframe_work: bool = False

    @abc.abstractmethod
    def on_odometry(self, event: Odometry) -> None: ...

    @abc.abstractmethod
    def on_scan(self, event: LaserScan) -> None: ...

    @abc.abstractmethod
    def on_frame(self, event: CameraFrame) -> FrameRecord | None:
        """Process a frame (or hold it briefly, e.g. until the odometry covering it arrives)."""

    def on_imu(self, event: ImuSample) -> None:  # noqa: B027 - an estimator without IMU use ignores it
        """An IMU sample (the rig's ``imu`` frame). The default ignores it: a run with or without the
        stream is then the same run."""

    def idle(self) -> bool:
        """Work that need not wait for the next event, done while the sensors are quiet (a run at the
        camera's rate calls it between events when there is time): True if anything was done. The
        default has nothing to do."""
        return False

    def finish(self) -> None:  # noqa: B027 - a hook with nothing to do by default
        """The log has ended: process anything held back."""

    @property
    def holding_frame(self) -> bool:
        """Whether a frame was taken but waits for its odometry (its work comes at that odometry)."""
        return False

    @property
    def graph_lag_keyframes(self) -> int | None:
        """How many keyframes after its own the graph's latest result came (a smoother whose results
        come when ready); None for an estimator without one, or before its first result."""
        return None

    @abc.abstractmethod
    def result(self) -> EstimatorResult:
        """Everything estimated so far (live points included with their current estimates)."""


class ScanQueue:
    """Laser scans waiting for the next frame that takes new points, in arrival order."""

    def __init__(self):
        self._scans: list[LaserScan] = []

    def __len__(self) -> int:
        return len(self._scans)

    def append(self, scan: LaserScan) -> None:
        self._scans.append(scan)

    def take_until(self, t_s: float) -> list[LaserScan]:
        """The scans at or before ``t_s`` (in arrival order), which leave the queue; later ones stay."""
        taken, self._scans = [s for s in self._scans if s.t_s <= t_s], [s for s in self._scans if s.t_s > t_s]
        return taken


class FrameDrivenEstimator(Estimator):
    """The event handling GM, PTPM and the graph share: scans are queued for the next frame, and with
    odometry a frame is held until the odometry covering its time has arrived (at most one odometry
    period later), so its motion is measured, not extrapolated. Subclasses call this constructor
    and implement :meth:`_process`, which must clear ``_pending_frame`` and take its motion from
    ``_motion`` (:meth:`FrameMotion.advance`) and its scans from ``_scans``. A frame not after the
    frame before it (or before the start time) is an :class:`EventOrderError`."""

    _last_frame_t_s: float | None = None  # the latest frame processed
    _speed_unknown: bool = False  # no speed but a guess: the estimators without odometry measure it from the ground (frontend.ground_motion)

    def __init__(self, motion: MotionConfig, has_odometry: bool, t_start_s: float):
        self._motion = FrameMotion(motion, has_odometry, t_start_s)
        self._scans = ScanQueue()
        self._pending_frame: CameraFrame | None = None
        self._frames: list[FrameRecord] = []

    # --- what the live map reads after each frame --------------------------------------------
    @property
    def frames_done(self) -> int:
        """Frames processed so far (a frame held for its odometry is not yet one)."""
        return len(self._frames)

    @property
    def last_frame(self) -> FrameRecord | None:
        return self._frames[-1] if self._frames else None

    @property
    def holding_frame(self) -> bool:
        return self._pending_frame is not None

    def recent_poses(self, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The last ``n`` frames' times (n,), best poses known now (n,4,4) and covariances (n,6,6):
        here the per-frame estimates; a smoother gives its revised ones."""
        frames = self._frames[-n:] if n > 0 else []
        return (
            np.array([f.t_s for f in frames]),
            np.array([f.T_world_body for f in frames]).reshape(-1, 4, 4),
            np.array([f.pose_covariance for f in frames]).reshape(-1, 6, 6),
        )

    def live_points(self) -> tuple[np.ndarray, np.ndarray]:
        """The points tracked now: ids (n,) and world positions (n,3) (a viewer's)."""
        return np.zeros(0, dtype=np.int64), np.zeros((0, 3))

    def archived_points_since(self, start: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
        """The map points that left the estimator since the ``start``-th one did: world positions
        (m,3), 3x3 covariances (m,3,3) and creation times (m,), and the count to ask from next
        time. Points whose estimate is not known yet are left out."""
        return np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros(0), start

    # --- the speed without odometry (frontend.ground_motion) ----------------------------------
    def _start_speed(self, motion: MotionConfig, frontend) -> None:
        """The speed at the start: a guess the ground's motion replaces (``initial_speed_mps`` 0), or
        the speed given or measured by the dataset, the search cap then set for it."""
        self._speed_unknown = not motion.speed_known_at_start
        if motion.speed_known_at_start:
            frontend.follow_speed(abs(motion.initial_speed_mps))

    def _note_tracking(self, textureless: bool, n_live: int, n_tracked: int) -> None:
        """A frame that had live points and tracked none lost the track: the next frame measures the
        speed from the ground again."""
        if not textureless and n_live > 0 and n_tracked == 0:
            self._speed_unknown = True

    def _ground_velocity(self, frontend, event: CameraFrame) -> tuple[np.ndarray, np.ndarray] | None:
        """The body's linear velocity (3,) m/s and its covariance (3x3) from the ground's motion
        since the last image (:meth:`FrontEnd.ground_shift`), the search cap set for that speed and
        the speed known from then on; None when nothing was measured."""
        shift = frontend.ground_shift(event.t_s, event.image)
        if shift is None:
            return None
        v, R = shift.velocity()
        frontend.follow_speed(float(np.linalg.norm(v)))
        self._speed_unknown = False
        return v, R

    def _speed_unknown_at_start(self, frontend, frame: int | None = None) -> bool:
        """On the first frame, with no odometry and no speed but a guess that the ground's motion will
        replace at the next frame (``frontend.ground_motion``): the points seeded now are spread over
        the whole depth the focus area may take (the speed ``math.inf`` to
        :meth:`~dem_graph.frontend.focus.FocusArea.for_speed`), not over the guessed speed's (for a car
        at 12 m/s, the nearest ground, gone within two frames). ``frame``: the frame's number, when its
        work comes after it was recorded (default: the frame being processed)."""
        first = (self.frames_done if frame is None else frame) == 0
        return first and self._speed_unknown and not self._motion.uses_odometry and frontend.measures_ground_motion

    @property
    def t_s(self) -> float:
        """The time the estimate is at, seconds."""
        return self._motion.t_s

    @abc.abstractmethod
    def _process(self, event: CameraFrame) -> FrameRecord: ...

    def _process_in_order(self, event: CameraFrame) -> FrameRecord:
        t_s, last = event.t_s, self._last_frame_t_s
        if not math.isfinite(t_s) or (last is not None and t_s <= last) or t_s < self.t_s:
            self._pending_frame = None
            after = f"the frame before, at {last:.6f} s" if last is not None else f"the start, at {self.t_s:.6f} s"
            raise EventOrderError(f"camera frame {event.index} at {t_s:.6f} s is not after {after}: frames must come in time order")
        self._last_frame_t_s = t_s
        return self._process(event)

    def on_odometry(self, event: Odometry) -> None:
        self._motion.add_odometry(event)
        if self._pending_frame is not None and event.t_s >= self._pending_frame.t_s:
            self._process_in_order(self._pending_frame)

    def on_scan(self, event: LaserScan) -> None:
        self._scans.append(event)

    def on_frame(self, event: CameraFrame) -> FrameRecord | None:
        if self._pending_frame is not None:
            self._process_in_order(self._pending_frame)
        if self._motion.holds(event.t_s):
            self._pending_frame = event
            return None
        return self._process_in_order(event)

    def finish(self) -> None:
        if self._pending_frame is not None:
            self._process_in_order(self._pending_frame)
