"""What the node puts on the robot's ROS 2 graph after each frame, and between frames.

:class:`MapPublisher` is a listener of the live pipeline: after each frame it publishes, in this
order, tf, the local map ahead (``elevation_map``, a GridMap over the live map's save window, the
window ``live_maps.nc`` keeps) and the pose (``odometry``). Between frames the node asks it for the
cost map around the vehicle (``cost_map``, on a grid aligned with the map frame, as Nav2 reads one),
the global map (latched, at a lower rate) and the diagnostics.

tf (REP 105): the node's poses are of the body in the map frame, so it owns ``map -> odom``, the
correction that puts the robot's own odometry frame in the map, as a localisation node (AMCL,
slam_toolbox) does; ``odom -> body`` stays the robot odometry's (a frame has one parent in tf).
Where tf carries no odometry of the robot, the node's estimate is the odometry too: it publishes
``odom -> body`` and an identity ``map -> odom`` (on ``/tf_static``). The local GridMap is in the
heading frame (at the body, x along its heading, z up: grid_map maps are axis-aligned with their
frame), which the node publishes as ``map -> dem_graph_heading``.
"""

from __future__ import annotations

import logging
import time
from collections import deque
from dataclasses import dataclass

import numpy as np

from dem_graph.datasets.rosbag import TransformTree, _transform_from_msg, stamp_s
from dem_graph.geometry.lie import so3_log_many
from dem_graph.geometry.se3 import invert, make_pose
from dem_graph.pipeline.live import LivePipeline, LiveUpdate, PoseWindow
from dem_graph.ros2 import outputs
from dem_graph.ros2.dds import Participant
from dem_graph.ros2.outputs import CostLimits, Frames
from dem_graph.ros2.qos import DEFAULT, LATCHED, TF, TF_STATIC

log = logging.getLogger(__name__)

GRID_MAP, OCCUPANCY_GRID, ODOMETRY_MSG = "grid_map_msgs/msg/GridMap", "nav_msgs/msg/OccupancyGrid", "nav_msgs/msg/Odometry"
TF_MSG, DIAGNOSTICS_MSG = "tf2_msgs/msg/TFMessage", "diagnostic_msgs/msg/DiagnosticArray"


@dataclass(frozen=True)
class OutputTopics:
    """The topics the node publishes on (each name configurable; relative names go under ``namespace``)."""

    namespace: str = "/dem_graph"
    elevation_map: str = "elevation_map"
    global_map: str = "global_map"
    cost_map: str = "cost_map"
    odometry: str = "odometry"
    diagnostics: str = "/diagnostics"  # where ROS 2's diagnostic aggregators and rqt_robot_monitor look

    def resolve(self, name: str) -> str:
        return name if name.startswith("/") else f"{self.namespace.rstrip('/')}/{name}"


class RobotOdometry:
    """The robot's own ``odom -> body`` from ``/tf`` (its moving transforms with the odometry frame as
    parent, carried to the body by the fixed ones), kept for a few seconds to be read at a frame's time."""

    def __init__(self, frames: Frames, keep_s: float = 5.0):
        self.frames = frames
        self.keep_s = keep_s
        self._samples: deque[tuple[float, np.ndarray]] = deque()

    @property
    def present(self) -> bool:
        return bool(self._samples)

    def add(self, msg, fixed: TransformTree) -> None:
        """A ``/tf`` message: its ``odom -> X`` transforms, with X linked to the body by fixed ones, kept."""
        for tr in msg.transforms:
            if str(tr.header.frame_id).lstrip("/") != self.frames.odom:
                continue
            child = str(tr.child_frame_id).lstrip("/")
            T_child_body = fixed.lookup(child, self.frames.body)
            q = tr.transform.rotation
            if T_child_body is None or not np.isfinite([q.x, q.y, q.z, q.w]).all() or abs(q.x * q.x + q.y * q.y + q.z * q.z + q.w * q.w) < 1e-12:
                continue
            t_s = stamp_s(tr.header)
            if self._samples and t_s <= self._samples[-1][0]:
                continue
            self._samples.append((t_s, _transform_from_msg(tr.transform) @ T_child_body))
        while self._samples and self._samples[-1][0] - self._samples[0][0] > self.keep_s:
            self._samples.popleft()

    def at(self, t_s: float, tolerance_s: float = 0.25) -> np.ndarray | None:
        """``T_odom_body`` at ``t_s`` (interpolated; None when tf has none within ``tolerance_s``)."""
        if not self._samples:
            return None
        t = np.array([s[0] for s in self._samples])
        if t_s < t[0] - tolerance_s or t_s > t[-1] + tolerance_s:
            return None
        if len(t) == 1:
            return self._samples[0][1]
        T = np.array([s[1] for s in self._samples])
        return PoseWindow(t, T, np.zeros((len(t), 6, 6))).at(np.array([min(t_s, t[-1])]))[0][0]


class MapPublisher:
    """A live-pipeline listener publishing each frame's tf, GridMap, cost map and odometry (see the module)."""

    def __init__(
        self, participant: Participant, pipeline: LivePipeline, topics: OutputTopics, frames: Frames, limits: CostLimits, robot_odometry: RobotOdometry,
        exact_stamps: dict[float, tuple[int, int]] | None = None,
    ):
        self.participant, self.pipeline, self.topics, self.frames, self.limits = participant, pipeline, topics, frames, limits
        self.codec = participant.codec
        self.robot_odometry = robot_odometry
        self.elevation = participant.writer(topics.resolve(topics.elevation_map), GRID_MAP, DEFAULT)
        self.global_map = participant.writer(topics.resolve(topics.global_map), GRID_MAP, LATCHED)
        self.cost = participant.writer(topics.resolve(topics.cost_map), OCCUPANCY_GRID, LATCHED)
        self.odometry = participant.writer(topics.resolve(topics.odometry), ODOMETRY_MSG, DEFAULT)
        self.diagnostics = participant.writer(topics.resolve(topics.diagnostics), DIAGNOSTICS_MSG, DEFAULT)
        self.tf = participant.writer("/tf", TF_MSG, TF)
        self.tf_static = participant.writer("/tf_static", TF_MSG, TF_STATIC)
        self._owns_odom_body: bool | None = None  # decided at the first frame
        self._previous: LiveUpdate | None = None
        self.frames_published = 0
        self.publish_s: list[float] = []  # each frame: the local map over the save window, the messages made, encoded and written
        # the frames' times: their images' own stamps (sec, nanosec), which the outputs carry (a float of epoch seconds is not exact)
        self.exact_stamps = exact_stamps if exact_stamps is not None else {}

    def __call__(self, update: LiveUpdate) -> None:
        t0 = time.perf_counter()
        c = self.pipeline.config
        lm = c.live_map
        dem = self.pipeline.map.local(update.T_world_body, tuple(lm.save_x_range_m), lm.save_width_m / 2.0, update.t_s, c.dem.traversability_window)
        T_map_heading = dem.meta["T_world_local"]
        exact = self.exact_stamps
        self.tf.publish(outputs.tf_message(self.codec, self._transforms(update, T_map_heading)))
        self.elevation.publish(outputs.grid_map_message(self.codec, dem, update.t_s, self.frames.heading, exact=exact))
        velocity, yaw_rate = self._velocity(update)
        self.odometry.publish(outputs.odometry_message(self.codec, update.t_s, self.frames, update.T_world_body, update.covariance, velocity, yaw_rate, exact))
        self._previous = update
        for t in [t for t in exact if t < update.t_s]:  # (the frames done; this one's kept for its cost map)
            del exact[t]
        self.frames_published += 1
        self.publish_s.append(time.perf_counter() - t0)

    @property
    def transport_s(self) -> float:
        """Time spent encoding and writing every message published so far, seconds."""
        return sum(w.seconds for w in self.participant.writers)

    def publish_global(self, t_s: float) -> None:
        """The whole map so far, in the map frame (latched: a subscriber that comes later gets the last one)."""
        c = self.pipeline.config
        if not self.pipeline.map.grid.n_kept:
            return
        dem = self.pipeline.map.global_dem(c.dem.traversability_window)
        self.global_map.publish(outputs.grid_map_message(self.codec, dem, t_s, self.frames.map, outputs.GLOBAL_MAP_LAYERS))

    def publish_cost(self, half_size_m: float) -> None:
        """The cost of the cells within ``half_size_m`` of the body, on a grid aligned with the map
        frame (Nav2's costmap layers take an OccupancyGrid's origin without its rotation), at the latest frame."""
        update = self._previous
        if update is None:
            return
        T_axes = make_pose(np.eye(3), update.T_world_body[:3, 3])  # at the body, the map frame's axes
        c = self.pipeline.config
        dem = self.pipeline.map.local(T_axes, (-half_size_m, half_size_m), half_size_m, update.t_s, c.dem.traversability_window)
        self.cost.publish(outputs.occupancy_grid_message(self.codec, dem, update.t_s, self.frames.map, dem.meta["T_world_local"], self.limits, self.exact_stamps))

    def publish_diagnostics(self, t_s: float, statuses: list) -> None:
        self.diagnostics.publish(outputs.diagnostic_array(self.codec, t_s, statuses))

    # --------------------------------------------------------------------------------------------
    def _transforms(self, update: LiveUpdate, T_map_heading: np.ndarray) -> list:
        f, t, exact = self.frames, update.t_s, self.exact_stamps
        out = [outputs.transform_message(self.codec, t, f.map, f.heading, T_map_heading, exact)]
        T_odom_body = self.robot_odometry.at(t)
        if self._owns_odom_body is None:
            self._owns_odom_body = T_odom_body is None and not self.robot_odometry.present
            if self._owns_odom_body:
                log.warning("tf carries no %s -> %s of the robot: publishing it from the estimate, and %s -> %s as identity (REP 105)", f.odom, f.body, f.map, f.odom)
                self.tf_static.publish(outputs.tf_message(self.codec, [outputs.transform_message(self.codec, t, f.map, f.odom, np.eye(4))]))
            else:
                log.info("publishing %s -> %s (the robot's odometry owns %s -> %s)", f.map, f.odom, f.odom, f.body)
        if self._owns_odom_body:
            out.append(outputs.transform_message(self.codec, t, f.odom, f.body, update.T_world_body, exact))
        elif T_odom_body is not None:
            out.append(outputs.transform_message(self.codec, t, f.map, f.odom, update.T_world_body @ invert(T_odom_body), exact))
        return out

    def _velocity(self, update: LiveUpdate) -> tuple[np.ndarray, float]:
        """The body's velocity in its own axes and its yaw rate since the previous frame."""
        prev = self._previous
        if prev is None or not update.t_s > prev.t_s:
            return np.zeros(3), 0.0
        dt = update.t_s - prev.t_s
        T_rel = invert(prev.T_world_body) @ update.T_world_body
        return T_rel[:3, 3] / dt, float(so3_log_many(T_rel[None, :3, :3])[0, 2] / dt)


__all__ = ["MapPublisher", "OutputTopics", "RobotOdometry"]
