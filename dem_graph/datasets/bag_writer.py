"""A dataset folder (a simulated log) written as a ROS bag the way a robot records one, so that the
ROS 2 node and player can be tried, tested and benchmarked without a robot
(``dem-graph simulate --bag``, :func:`write_robot_bag`).

A folder's images, scans and odometry become ``sensor_msgs/Image`` (mono8, or a Bayer mosaic), one
``sensor_msgs/CameraInfo`` per image (ROS 1's ``D, K, R, P``, ROS 2's ``d, k, r, p``),
``sensor_msgs/LaserScan`` (float32 angles and ranges, the rig's range limits), ``nav_msgs/Odometry``
(absolute poses of ``base_link`` in ``odom``, all-zero covariances) and tf: ``/tf_static`` holds
base_footprint -> base_link -> the camera's optical frame and the laser; ``/tf`` holds the moving
odom -> base_footprint (tf2_msgs/TFMessage) and, in a ROS 1 bag, a fixed wheel frame sent as the
older tf/tfMessage on the same topic; with :attr:`BagOptions.imu`, its IMU as ``sensor_msgs/Imu``.
The folder's rig is the truth the bag's rig is read against. :class:`BagOptions` also takes parts
out or spoils them (the tests' bags that must be refused or repaired).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dem_graph.datasets.events import CameraFrame, ImuSample, LaserScan, Odometry
from dem_graph.datasets.folder import FolderSequence
from dem_graph.errors import DatasetError
from dem_graph.geometry.rig import PlanarBeams
from dem_graph.geometry.se3 import invert, make_pose, quat_xyzw_from_matrix

IMAGE, INFO, SCAN, ODOM, IMU = "/camera/image_raw", "/camera/camera_info", "/scan", "/odom", "/imu/data"
CAMERA_FRAME, LASER_FRAME = "camera_optical_frame", "laser"
T_FOOTPRINT_LINK = make_pose(np.eye(3), [0.0, 0.0, 0.3])  # base_link 0.3 m above the ground
EPOCH_S = 1_700_000_000  # stamps as a robot's clock gives them


def f32_beams(beams: PlanarBeams) -> PlanarBeams:
    """``beams`` with the angles a LaserScan carries exactly (float32)."""
    return PlanarBeams(angle_min_rad=float(np.float32(beams.angle_min_rad)), angle_increment_rad=float(np.float32(beams.angle_increment_rad)), count=beams.count)


@dataclass
class BagOptions:
    """What the bag holds beyond the camera, the laser, the odometry and tf, and what is left out or
    changed in it (the ways a bag is refused or repaired)."""

    no_camera_info: bool = False
    no_laser_tf: bool = False
    beams_change_at: int | None = None  # scans from this one on have 10 beams fewer
    rectified: bool = False  # the image topic is image_rect, its CameraInfo's P the rig's intrinsics
    distortion_model: str = "plumb_bob"
    extra: list = field(default_factory=list)
    imu: bool = False  # the folder's IMU as sensor_msgs/Imu on /imu/data (frame imu_link, its mount on /tf_static)
    image_encoding: str = "mono8"  # or a Bayer pattern (bayer_gbrg8, ...): the grey scene as a colour camera of equal channel gains records it
    blemishes: bool = False  # one bad message in a stream each, 1 ms after a good one halfway: a scan 10 beams short, an IMU sample and an odometry pose not finite


def _stamp(t_s: float) -> tuple[int, int]:
    ns = int(round(t_s * 1e9))
    return EPOCH_S + ns // 10**9, ns % 10**9


def _types(store):
    from rosbags.typesys import get_types_from_msg

    for name in ("tf2_msgs/msg/TFMessage", "tf/msg/tfMessage"):
        if name not in store.types:
            store.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms", name))
    return store.types


def robot_messages(folder, edits: BagOptions | None = None):
    """``(store, ros1) -> [(topic, msgtype, bag time ns, message)]`` of the folder's log, in time order."""
    edits = edits or BagOptions()
    seq = FolderSequence(folder)
    rig = seq.rig
    events = list(seq.events())

    def messages(store, ros1: bool):
        T = _types(store)
        G = "geometry_msgs/msg/"
        extra = {"seq": 0} if ros1 else {}

        def header(t_s, frame):
            sec, ns = _stamp(t_s)
            return T["std_msgs/msg/Header"](**extra, stamp=T["builtin_interfaces/msg/Time"](sec=sec, nanosec=ns), frame_id=frame)

        def ns_of(t_s):
            sec, ns = _stamp(t_s)
            return sec * 10**9 + ns

        def transform(parent, child, P, t_s):
            q = quat_xyzw_from_matrix(P[:3, :3])
            return T[G + "TransformStamped"](
                header=header(t_s, parent), child_frame_id=child,
                transform=T[G + "Transform"](translation=T[G + "Vector3"](x=P[0, 3], y=P[1, 3], z=P[2, 3]), rotation=T[G + "Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3])),
            )

        cam = rig.camera
        K = np.array([[cam.fx_px, 0.0, cam.cx_px], [0.0, cam.fy_px, cam.cy_px], [0.0, 0.0, 1.0]])
        P = np.hstack([K, np.zeros((3, 1))])
        D = np.array(cam.distortion, dtype=float) if edits.distortion_model == "plumb_bob" else np.r_[cam.distortion, 0.0, 0.0, 0.0]
        if edits.rectified:
            D = np.zeros(5)
        mats = {"d": D, "k": K.ravel(), "r": np.eye(3).ravel(), "p": P.ravel()}
        if ros1:
            mats = {k.upper(): v for k, v in mats.items()}
        image_topic = IMAGE.replace("image_raw", "image_rect") if edits.rectified else IMAGE
        beams = rig.laser.beams
        out = []
        t0 = events[0].t_s
        odometry_pose = None
        n_scan = 0
        for e in events:
            if isinstance(e, CameraFrame):
                img = e.image if e.image.ndim == 2 else e.image[:, :, 0]
                h, w = img.shape
                msg = T["sensor_msgs/msg/Image"](header=header(e.t_s, CAMERA_FRAME), height=h, width=w, encoding=edits.image_encoding, is_bigendian=0, step=w, data=np.ascontiguousarray(img).ravel())
                out.append((image_topic, "sensor_msgs/msg/Image", ns_of(e.t_s), msg))
                if not edits.no_camera_info:
                    roi = T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
                    info = T["sensor_msgs/msg/CameraInfo"](
                        header=header(e.t_s, CAMERA_FRAME), height=h, width=w, distortion_model=edits.distortion_model, **mats, binning_x=0, binning_y=0, roi=roi,
                    )
                    out.append((INFO, "sensor_msgs/msg/CameraInfo", ns_of(e.t_s), info))
            elif isinstance(e, LaserScan):
                r = np.asarray(e.ranges_m, dtype=np.float32)
                if edits.beams_change_at is not None and n_scan >= edits.beams_change_at:
                    r = r[:-10]
                n_scan += 1
                msg = T["sensor_msgs/msg/LaserScan"](
                    header=header(e.t_s, LASER_FRAME), angle_min=beams.angle_min_rad, angle_max=beams.angle_min_rad + (len(r) - 1) * beams.angle_increment_rad,
                    angle_increment=beams.angle_increment_rad, time_increment=0.0, scan_time=1.0 / rig.laser.rate_hz,
                    range_min=rig.laser.range_min_m, range_max=rig.laser.range_max_m, ranges=r, intensities=np.zeros(0, dtype=np.float32),
                )
                out.append((SCAN, "sensor_msgs/msg/LaserScan", ns_of(e.t_s), msg))
            elif isinstance(e, ImuSample) and edits.imu:
                V, Q = T[G + "Vector3"], T[G + "Quaternion"]
                no_orientation = np.zeros(9)
                no_orientation[0] = -1.0  # ROS: "no orientation estimate"
                msg = T["sensor_msgs/msg/Imu"](
                    header=header(e.t_s, "imu_link"), orientation=Q(x=0.0, y=0.0, z=0.0, w=1.0), orientation_covariance=no_orientation,
                    angular_velocity=V(x=e.gyro_rad_s[0], y=e.gyro_rad_s[1], z=e.gyro_rad_s[2]), angular_velocity_covariance=np.zeros(9),
                    linear_acceleration=V(x=e.accel_mps2[0], y=e.accel_mps2[1], z=e.accel_mps2[2]), linear_acceleration_covariance=np.zeros(9),
                )
                out.append((IMU, "sensor_msgs/msg/Imu", ns_of(e.t_s), msg))
            elif isinstance(e, Odometry):
                poses = []
                if odometry_pose is None:
                    odometry_pose = np.eye(4)
                    poses.append((e.t_prev_s, odometry_pose))
                odometry_pose = odometry_pose @ e.T_prev_curr
                poses.append((e.t_s, odometry_pose))
                for t_s, P_odom_body in poses:
                    P_link = P_odom_body @ T_FOOTPRINT_LINK
                    q = quat_xyzw_from_matrix(P_link[:3, :3])
                    pose = T[G + "Pose"](position=T[G + "Point"](x=P_link[0, 3], y=P_link[1, 3], z=P_link[2, 3]), orientation=T[G + "Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]))
                    twist = T[G + "Twist"](linear=T[G + "Vector3"](x=0.0, y=0.0, z=0.0), angular=T[G + "Vector3"](x=0.0, y=0.0, z=0.0))
                    msg = T["nav_msgs/msg/Odometry"](
                        header=header(t_s, "odom"), child_frame_id="base_link",
                        pose=T[G + "PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
                        twist=T[G + "TwistWithCovariance"](twist=twist, covariance=np.zeros(36)),
                    )
                    out.append((ODOM, "nav_msgs/msg/Odometry", ns_of(t_s), msg))
                    tf = T["tf2_msgs/msg/TFMessage"](transforms=[transform("odom", "base_footprint", P_odom_body, t_s)])
                    out.append(("/tf", "tf2_msgs/msg/TFMessage", ns_of(t_s), tf))
        statics = [
            transform("base_footprint", "base_link", T_FOOTPRINT_LINK, t0),
            transform("base_link", CAMERA_FRAME, invert(T_FOOTPRINT_LINK) @ rig.T_body_cam, t0),
        ]
        if not edits.no_laser_tf:
            statics.append(transform("base_link", LASER_FRAME, invert(T_FOOTPRINT_LINK) @ rig.T_body_laser, t0))
        if edits.imu and rig.imu is not None:
            statics.append(transform("base_link", "imu_link", invert(T_FOOTPRINT_LINK) @ rig.T_body_imu, t0))
        out.append(("/tf_static", "tf2_msgs/msg/TFMessage", ns_of(t0) - 1, T["tf2_msgs/msg/TFMessage"](transforms=statics)))
        if edits.blemishes:
            out += _blemishes(out, header, ns_of)
        if ros1:  # a fixed wheel frame sent by an older node as tf/tfMessage, on /tf beside the TFMessage ones
            wheel = make_pose(np.eye(3), [0.0, 0.25, 0.0])
            for k in range(3):
                t_s = t0 + 0.5 * k
                out.append(("/tf", "tf/msg/tfMessage", ns_of(t_s) + 1, T["tf/msg/tfMessage"](transforms=[transform("base_link", "wheel_left", wheel, t_s)])))
        return sorted(out, key=lambda m: m[2])

    return messages


def _blemishes(out, header, ns_of):
    """The bad messages of :attr:`BagEdits.blemishes`, each 1 ms after the good message of its stream halfway through."""
    import dataclasses

    bad = []
    for topic, change in ((SCAN, lambda m: {"ranges": m.ranges[:-10]}), (IMU, lambda m: {"angular_velocity": dataclasses.replace(m.angular_velocity, y=np.nan)}), (ODOM, None)):
        msgs = [(t, m) for tp, _, t, m in out if tp == topic]
        if not msgs:
            continue
        t_ns, msg = msgs[len(msgs) // 2]
        stamp = msg.header.stamp
        t_s = (stamp.sec - EPOCH_S) + stamp.nanosec * 1e-9 + 0.001
        if topic == ODOM:
            pose = dataclasses.replace(msg.pose.pose, position=dataclasses.replace(msg.pose.pose.position, x=np.nan))
            fields = {"pose": dataclasses.replace(msg.pose, pose=pose)}
        else:
            fields = change(msg)
        msgtype = {SCAN: "sensor_msgs/msg/LaserScan", IMU: "sensor_msgs/msg/Imu", ODOM: "nav_msgs/msg/Odometry"}[topic]
        bad.append((topic, msgtype, ns_of(t_s), dataclasses.replace(msg, header=header(t_s, msg.header.frame_id), **fields)))
    return bad


def write_robot_bag(path, folder, fmt: str, edits: BagOptions | None = None):
    """The folder's log as a bag at ``path``: ``fmt`` "ros1" (a ``.bag`` file), "ros2" (a ROS 2 bag
    folder, SQLite) or "mcap" (a ROS 2 bag folder, MCAP storage); returns ``path``."""
    from rosbags.typesys import Stores, get_typestore

    if fmt not in ("ros1", "ros2", "mcap"):
        raise DatasetError(path, f"unknown bag format {fmt!r}: ros1, ros2 or mcap")
    path = Path(path)
    if path.exists():
        raise DatasetError(path, "exists: a bag is not written over (remove it first)")
    ros1 = fmt == "ros1"
    if ros1:
        from rosbags.rosbag1 import Writer

        store = get_typestore(Stores.ROS1_NOETIC)
        writer, serialize = Writer(path), store.serialize_ros1
    else:
        from rosbags.rosbag2 import StoragePlugin, Writer

        store = get_typestore(Stores.ROS2_HUMBLE)
        writer = Writer(path, version=9, storage_plugin=StoragePlugin.MCAP if fmt == "mcap" else StoragePlugin.SQLITE3)
        serialize = store.serialize_cdr
    with writer:
        connections = {}
        for topic, msgtype, t_ns, msg in robot_messages(folder, edits)(store, ros1):
            if (topic, msgtype) not in connections:  # a topic may carry two types (ROS 1's /tf: TFMessage and tf/tfMessage)
                connections[topic, msgtype] = writer.add_connection(topic, msgtype, typestore=store)
            writer.write(connections[topic, msgtype], t_ns, serialize(msg, msgtype))
    return path


__all__ = ["BagOptions", "CAMERA_FRAME", "IMAGE", "IMU", "INFO", "LASER_FRAME", "ODOM", "SCAN", "f32_beams", "robot_messages", "write_robot_bag"]
