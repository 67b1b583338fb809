"""What the node publishes, as ROS 2 messages made from the live pipeline's results (pure functions:
arrays in, rosbags messages out), and the GridMap read back (:func:`dem_from_grid_map`).

**GridMap** (``grid_map_msgs/GridMap``), as grid_map lays a map out: the map is axis-aligned with
its header's frame, ``info.pose`` its centre; the data of each layer is a column-major matrix
(``layout.dim[0]`` labelled ``column_index``, ``dim[1]`` ``row_index``) whose row index runs against
the frame's x and column index against its y, cell (0, 0) at the corner of largest x and y;
``outer_start_index`` and ``inner_start_index`` are the circular buffer's start (0 here: the maps
are written whole). A :class:`~dem_graph.dem.layers.Dem`'s rows run against y and its columns
along x, so a layer ``L`` goes out as ``L[:, ::-1]`` transposed.

**OccupancyGrid** (``nav_msgs/OccupancyGrid``): row-major from ``info.origin`` (the cell corner of
smallest x and y, its orientation the grid's), 0 free to 100 lethal, -1 unknown: the cost is the
largest of slope, step and roughness each over its limit (:class:`CostLimits`), 100 at or past one.

**Odometry** and **tf**: poses of the body in the map frame; the covariance goes out in ROS's
order (x, y, z, then rotations about x, y, z) in the map frame's axes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dem_graph.dem.layers import Dem
from dem_graph.errors import DemGraphError
from dem_graph.geometry.grid import GridGeometry
from dem_graph.geometry.se3 import make_pose, matrix_from_quat_xyzw, quat_xyzw_from_matrix
from dem_graph.ros2.messages import Codec

GRID_MAP_LAYERS = ("elevation", "variance", "count", "age_s", "slope_deg", "step_height_m", "roughness_m")
"""The layers of the GridMaps published, by grid_map's names (the live maps' own, ``live_maps.nc``'s)."""
GLOBAL_MAP_LAYERS = ("elevation", "variance", "count", "last_update_s", "slope_deg", "step_height_m", "roughness_m")
"""The global map's layers: its cells' last update (the source's clock, seconds) in place of their age."""
COLUMN_INDEX, ROW_INDEX = "column_index", "row_index"  # grid_map's storage index labels

# diagnostic_msgs/DiagnosticStatus levels
OK, WARN, ERROR, STALE = 0, 1, 2, 3


@dataclass(frozen=True)
class CostLimits:
    """The traversability at which a cell is lethal (cost 100); below, the cost rises with the largest ratio."""

    max_slope_deg: float = 20.0
    max_step_height_m: float = 0.15
    max_roughness_m: float = 0.05


@dataclass(frozen=True)
class Frames:
    """The tf frames the node names (REP 105)."""

    map: str = "map"  # the world the map and the poses are in
    odom: str = "odom"  # the robot's odometry frame
    body: str = "base_footprint"  # the body (the rig's body frame)
    heading: str = "dem_graph_heading"  # the local map's: at the body, x along its heading, z up


def stamp(codec: Codec, t_s: float, exact: dict | None = None):
    """A ``builtin_interfaces/Time`` of ``t_s`` seconds: the stamp ``exact`` maps ``t_s`` to (the
    input message's own: a float of epoch seconds is only good to a few hundred nanoseconds), else
    the whole seconds and the nanoseconds of the fraction, rounded."""
    if exact is not None and t_s in exact:
        sec, nanosec = exact[t_s]
    else:
        sec = int(np.floor(float(t_s)))
        nanosec = int(round((float(t_s) - sec) * 1e9))
        if nanosec >= 10**9:
            sec, nanosec = sec + 1, nanosec - 10**9
    return codec.message_class("builtin_interfaces/msg/Time")(sec=sec, nanosec=nanosec)


def header(codec: Codec, t_s: float, frame_id: str, exact: dict | None = None):
    return codec.message_class("std_msgs/msg/Header")(stamp=stamp(codec, t_s, exact), frame_id=frame_id)


def pose_message(codec: Codec, T: np.ndarray):
    """A ``geometry_msgs/Pose`` of a 4x4 pose."""
    m = codec.message_class
    q = quat_xyzw_from_matrix(np.asarray(T)[:3, :3])
    return m("geometry_msgs/msg/Pose")(
        position=m("geometry_msgs/msg/Point")(x=float(T[0, 3]), y=float(T[1, 3]), z=float(T[2, 3])),
        orientation=m("geometry_msgs/msg/Quaternion")(x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])),
    )


def transform_message(codec: Codec, t_s: float, parent: str, child: str, T_parent_child: np.ndarray, exact: dict | None = None):
    """A ``geometry_msgs/TransformStamped``."""
    m = codec.message_class
    T = np.asarray(T_parent_child, dtype=float)
    q = quat_xyzw_from_matrix(T[:3, :3])
    return m("geometry_msgs/msg/TransformStamped")(
        header=header(codec, t_s, parent, exact),
        child_frame_id=child,
        transform=m("geometry_msgs/msg/Transform")(
            translation=m("geometry_msgs/msg/Vector3")(x=float(T[0, 3]), y=float(T[1, 3]), z=float(T[2, 3])),
            rotation=m("geometry_msgs/msg/Quaternion")(x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])),
        ),
    )


def tf_message(codec: Codec, transforms: list):
    return codec.message_class("tf2_msgs/msg/TFMessage")(transforms=list(transforms))


# --- GridMap -------------------------------------------------------------------------------------


def grid_map_message(codec: Codec, dem: Dem, t_s: float, frame_id: str, layers: tuple[str, ...] = GRID_MAP_LAYERS, z_offset_m: float = 0.0, exact: dict | None = None):
    """``dem`` (in ``frame_id``'s axes: a local map in the heading frame, a global one in the map
    frame) as a ``grid_map_msgs/GridMap`` at ``t_s`` (see the module; ``exact``: :func:`stamp`'s). ``z_offset_m``: the height of
    the frame's z = 0 in the elevation's datum (0: the elevation is in the frame's z)."""
    m = codec.message_class
    g = dem.geometry
    missing = [name for name in layers if name not in dem.layers]
    if missing:
        raise DemGraphError(f"the map has no layer {', '.join(missing)} (it has {', '.join(dem.layers)})")
    centre = make_pose(np.eye(3), [g.x_min_m + 0.5 * g.n_cols * g.resolution_m, g.y_max_m - 0.5 * g.n_rows * g.resolution_m, float(z_offset_m)])
    info = m("grid_map_msgs/msg/GridMapInfo")(resolution=float(g.resolution_m), length_x=float(g.n_cols * g.resolution_m), length_y=float(g.n_rows * g.resolution_m), pose=pose_message(codec, centre))
    Dim = m("std_msgs/msg/MultiArrayDimension")
    layout = m("std_msgs/msg/MultiArrayLayout")(
        dim=[Dim(label=COLUMN_INDEX, size=g.n_rows, stride=g.n_rows * g.n_cols), Dim(label=ROW_INDEX, size=g.n_cols, stride=g.n_cols)],
        data_offset=0,
    )
    Array = m("std_msgs/msg/Float32MultiArray")
    data = [Array(layout=layout, data=np.ascontiguousarray(np.asarray(dem.layers[name], dtype=np.float32)[:, ::-1]).ravel()) for name in layers]
    return m("grid_map_msgs/msg/GridMap")(
        header=header(codec, t_s, frame_id, exact), info=info, layers=list(layers), basic_layers=["elevation"], data=data, outer_start_index=0, inner_start_index=0,
    )


def dem_from_grid_map(msg) -> Dem:
    """A ``grid_map_msgs/GridMap`` read back as a :class:`Dem` in its frame's axes (rows against y,
    columns along x), whichever storage order its layers declare and wherever its circular buffer
    starts; ``meta`` holds its time, frame and centre. A map that is not one is a :class:`DemGraphError`."""
    info = msg.info
    r = float(info.resolution)
    if not r > 0 or len(msg.layers) != len(msg.data):
        raise DemGraphError(f"not a grid map: resolution {r}, {len(msg.layers)} layer names for {len(msg.data)} layers")
    n_x, n_y = int(round(info.length_x / r)), int(round(info.length_y / r))  # grid_map's rows (along x) and columns (along y)
    start = (int(msg.outer_start_index), int(msg.inner_start_index))
    layers = {}
    for name, array in zip(msg.layers, msg.data):
        dims = array.layout.dim
        values = np.asarray(array.data, dtype=np.float32)[int(array.layout.data_offset):]
        if len(dims) != 2 or values.size != n_x * n_y:
            raise DemGraphError(f"grid map layer {name!r}: {values.size} values in {len(dims)} dimensions, not {n_x} x {n_y}")
        if dims[0].label == ROW_INDEX:  # row-major
            M = values.reshape(n_x, n_y)
        else:  # column-major, grid_map's default
            M = values.reshape(n_y, n_x).T
        M = np.roll(M, (-start[0], -start[1]), axis=(0, 1))  # the circular buffer unrolled: cell (0, 0) first
        layers[str(name)] = np.ascontiguousarray(M.T[:, ::-1])
    x_c, y_c = float(info.pose.position.x), float(info.pose.position.y)
    geometry = GridGeometry(x_c - 0.5 * n_x * r, y_c + 0.5 * n_y * r, r, n_y, n_x)
    t_s = float(msg.header.stamp.sec) + 1e-9 * float(msg.header.stamp.nanosec)
    return Dem(geometry, layers, frame=str(msg.header.frame_id), meta={"t_s": t_s, "frame_id": str(msg.header.frame_id), "z_m": float(info.pose.position.z)})


# --- OccupancyGrid -------------------------------------------------------------------------------


def cost_of(dem: Dem, limits: CostLimits) -> np.ndarray:
    """The cells' cost, int8 (rows, cols) of ``dem``: -1 unknown (no height or no traversability), else
    0-100 (see the module)."""
    ratios = [np.asarray(dem.layers[name], dtype=float) / limit for name, limit in (("slope_deg", limits.max_slope_deg), ("step_height_m", limits.max_step_height_m), ("roughness_m", limits.max_roughness_m))]
    stacked = np.stack(ratios)
    known = np.isfinite(np.asarray(dem.layers["elevation"], dtype=float)) & np.any(np.isfinite(stacked), axis=0)
    worst = np.nanmax(np.where(np.isfinite(stacked), stacked, -np.inf), axis=0)
    cost = np.clip(np.round(100.0 * np.where(known, worst, 0.0)), 0, 100).astype(np.int8)
    cost[~known] = -1
    return cost


def occupancy_grid_message(codec: Codec, dem: Dem, t_s: float, frame_id: str, T_frame_grid: np.ndarray, limits: CostLimits, exact: dict | None = None):
    """The cost of ``dem`` (its axes those of the frame ``T_frame_grid`` places in ``frame_id``: the
    heading frame in the map frame, for a local map) as a ``nav_msgs/OccupancyGrid``."""
    m = codec.message_class
    g = dem.geometry
    T_grid_origin = make_pose(np.eye(3), [g.x_min_m, g.y_min_m, 0.0])  # the corner of smallest x and y
    info = m("nav_msgs/msg/MapMetaData")(
        map_load_time=stamp(codec, t_s, exact), resolution=float(g.resolution_m), width=g.n_cols, height=g.n_rows,
        origin=pose_message(codec, np.asarray(T_frame_grid, dtype=float) @ T_grid_origin),
    )
    cost = cost_of(dem, limits)[::-1]  # OccupancyGrid rows run along +y
    return m("nav_msgs/msg/OccupancyGrid")(header=header(codec, t_s, frame_id, exact), info=info, data=np.ascontiguousarray(cost).ravel())


# --- Odometry ------------------------------------------------------------------------------------


def ros_pose_covariance(T_world_body: np.ndarray, covariance_rot_trans: np.ndarray) -> np.ndarray:
    """A 6x6 covariance of ``[rotation, translation]`` perturbed on the right (the body's axes) as
    ROS's 36 values: ``[x, y, z, rot x, rot y, rot z]`` in the world's axes (first order)."""
    R = np.asarray(T_world_body, dtype=float)[:3, :3]
    A = np.zeros((6, 6))
    A[:3, 3:] = R  # translation (world) from the body's translation perturbation
    A[3:, :3] = R  # rotation (world axes) from the body's rotation perturbation
    return (A @ np.asarray(covariance_rot_trans, dtype=float) @ A.T).ravel()


def odometry_message(
    codec: Codec, t_s: float, frames: Frames, T_map_body: np.ndarray, covariance_rot_trans: np.ndarray, velocity_body_mps: np.ndarray, yaw_rate_rad_s: float, exact: dict | None = None,
):
    """``nav_msgs/Odometry`` of the body in the map frame; the twist in the body's axes (its
    covariance unknown: zeros, ROS's convention)."""
    m = codec.message_class
    V3 = m("geometry_msgs/msg/Vector3")
    v = np.asarray(velocity_body_mps, dtype=float)
    twist = m("geometry_msgs/msg/Twist")(linear=V3(x=float(v[0]), y=float(v[1]), z=float(v[2])), angular=V3(x=0.0, y=0.0, z=float(yaw_rate_rad_s)))
    return m("nav_msgs/msg/Odometry")(
        header=header(codec, t_s, frames.map, exact),
        child_frame_id=frames.body,
        pose=m("geometry_msgs/msg/PoseWithCovariance")(pose=pose_message(codec, T_map_body), covariance=ros_pose_covariance(T_map_body, covariance_rot_trans)),
        twist=m("geometry_msgs/msg/TwistWithCovariance")(twist=twist, covariance=np.zeros(36)),
    )


def pose_of(msg_pose) -> np.ndarray:
    """A 4x4 pose of a ``geometry_msgs/Pose`` (for tests and listeners)."""
    q = np.array([msg_pose.orientation.x, msg_pose.orientation.y, msg_pose.orientation.z, msg_pose.orientation.w], dtype=float)
    return make_pose(matrix_from_quat_xyzw(q / np.linalg.norm(q)), [msg_pose.position.x, msg_pose.position.y, msg_pose.position.z])


# --- diagnostics ---------------------------------------------------------------------------------


def diagnostic_status(codec: Codec, name: str, level: int, message: str, values: dict[str, object], hardware_id: str = "dem_graph"):
    m = codec.message_class
    KeyValue = m("diagnostic_msgs/msg/KeyValue")
    return m("diagnostic_msgs/msg/DiagnosticStatus")(
        level=np.uint8(level), name=name, message=message, hardware_id=hardware_id,
        values=[KeyValue(key=str(k), value=_text(v)) for k, v in values.items()],
    )


def diagnostic_array(codec: Codec, t_s: float, statuses: list):
    return codec.message_class("diagnostic_msgs/msg/DiagnosticArray")(header=header(codec, t_s, ""), status=list(statuses))


def _text(value) -> str:
    if isinstance(value, float):
        return "nan" if not np.isfinite(value) else f"{value:.6g}"
    return str(value)


__all__ = [
    "ERROR",
    "GLOBAL_MAP_LAYERS",
    "GRID_MAP_LAYERS",
    "OK",
    "STALE",
    "WARN",
    "CostLimits",
    "Frames",
    "cost_of",
    "dem_from_grid_map",
    "diagnostic_array",
    "diagnostic_status",
    "grid_map_message",
    "header",
    "occupancy_grid_message",
    "odometry_message",
    "pose_message",
    "pose_of",
    "ros_pose_covariance",
    "stamp",
    "tf_message",
    "transform_message",
]
