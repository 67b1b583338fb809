"""The sensor rig a ROS bag holds, read from its own messages (no rig file needed).

- the camera's intrinsics and distortion from its ``sensor_msgs/CameraInfo`` (ROS 1's ``D, K, R, P``
  and ROS 2's ``d, k, r, p``; ``plumb_bob``, and ``rational_polynomial`` whose k4..k6 are 0); for a
  rectified image topic (``image_rect*``) the projection ``P`` and no distortion;
- the laser's beams and range limits from its ``sensor_msgs/LaserScan`` messages (the first one's;
  a layout that changes and holds is refused naming the message where it changes);
- ``T_body_cam``, ``T_body_laser`` (and ``T_body_imu``) from ``/tf_static`` and the transforms of
  ``/tf`` that never change, between the body frame and the messages' own ``frame_id``. The body frame
  is ``base_footprint`` where tf has it (REP 105 puts it on the ground under the robot, the body
  convention here: origin on the ground, z up), else ``base_link``, unless given;
- the rates from the messages' times; the odometry's noise (its messages' covariances are of the
  absolute pose, and mostly placeholders), the image noise and the range noise from the defaults of
  :mod:`~dem_graph.geometry.rig` for a wheeled vehicle, stated in one warning.

A rig file, when given, overrides the derived rig field by field (:func:`rig_of_bag`). Anything
neither gives is a :class:`DatasetError` naming the topic, the frame or the message.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

from dem_graph.datasets.rosbag import (
    IMAGE_TYPES,
    IMU_TYPE,
    SCAN_TYPE,
    TransformTree,
    _transform_from_msg,
    check_topic,
    open_bag,
    topic_messages,
    topic_where,
)
from dem_graph.errors import ConfigError, DatasetError
from dem_graph.geometry.rig import CameraSpec, ImuSpec, LaserSpec, OdometrySpec, SensorRig, rig_from_dict

log = logging.getLogger(__name__)

CAMERA_INFO_TYPE = "sensor_msgs/msg/CameraInfo"
BODY_FRAMES = ("base_footprint", "base_link")
"""The body frames looked for in tf, in this order (REP 105)."""
STATIC_TOLERANCE = 1e-9
"""A ``/tf`` transform whose every message agrees with the first to this (metres, quaternion units) is taken as fixed."""


@dataclass
class BagTopics:
    """What a user names to read a bag: the topics, and the frames when they are not the messages' own."""

    image_topic: str
    scan_topic: str
    odometry_topic: str | None = None
    imu_topic: str | None = None
    camera_info_topic: str | None = None  # default: the image topic's sibling camera_info
    body_frame: str | None = None  # default: base_footprint, else base_link
    camera_frame: str | None = None  # default: the image messages' frame_id
    laser_frame: str | None = None  # default: the scans' frame_id


@dataclass
class DerivedRig:
    """A rig read from a bag: the values found (a nested mapping as a rig file holds), the problems
    of those not found (each with the fields it leaves unset), and what was told about how."""

    values: dict
    missing: list[tuple[tuple[str, ...], DatasetError]] = field(default_factory=list)
    body_frame: str | None = None
    notes: list[str] = field(default_factory=list)
    from_tf: bool = False  # some extrinsic came from tf (then the body frame matters to the odometry)


def _set(values: dict, path: str, value) -> None:
    keys = path.split(".")
    for key in keys[:-1]:
        values = values.setdefault(key, {})
    values[keys[-1]] = value


def _has(values: dict, path: str) -> bool:
    for key in path.split("."):
        if not isinstance(values, dict) or key not in values:
            return False
        values = values[key]
    return True


def _merge(base: dict, over: dict) -> dict:
    out = dict(base)
    for key, value in over.items():
        out[key] = _merge(out[key], value) if isinstance(value, dict) and isinstance(out.get(key), dict) else value
    return out


def camera_info_candidates(image_topic: str) -> list[str]:
    """Where a camera driver publishes an image topic's CameraInfo: beside it (``/cam/image_raw`` ->
    ``/cam/camera_info``; ``/cam/image_raw/compressed`` -> the same)."""
    parts = image_topic.rstrip("/").split("/")
    if parts and parts[-1] in ("compressed", "theora", "compressedDepth"):
        parts = parts[:-1]
    stem = "/".join(parts[:-1])
    out = [f"{stem}/camera_info"]
    if len(parts) > 2:
        out.append("/".join(parts[:-2]) + "/camera_info")
    return out


def is_rectified(image_topic: str) -> bool:
    """Whether an image topic is named as image_proc names a rectified image (``image_rect``, ``image_rect_color``)."""
    return any(part.startswith("image_rect") for part in image_topic.split("/"))


def _info_field(msg, name: str) -> np.ndarray:
    """A CameraInfo matrix by its ROS 2 name (``k``), or its ROS 1 name (``K``)."""
    value = getattr(msg, name, None)
    if value is None:
        value = getattr(msg, name.upper())
    return np.asarray(value, dtype=float).ravel()


def intrinsics_from_camera_info(msg, rectified: bool, where: str) -> dict:
    """The camera fields of a rig (size, focal lengths, principal point, distortion) from one CameraInfo
    message; ``rectified``: the image is rectified, so its projection ``P`` and no distortion apply."""
    width, height = int(msg.width), int(msg.height)
    K, P, D = _info_field(msg, "k"), _info_field(msg, "p"), _info_field(msg, "d")
    if int(getattr(msg, "binning_x", 0)) > 1 or int(getattr(msg, "binning_y", 0)) > 1 or int(msg.roi.width) > 0:
        raise DatasetError(where, f"binning {msg.binning_x}x{msg.binning_y} or a region of interest ({msg.roi.width}x{msg.roi.height} px): not read; record the full image")
    if rectified:
        if len(P) != 12 or P[0] <= 0 or P[5] <= 0:
            raise DatasetError(where, f"the image topic is rectified but P is {P.tolist()}: not a projection")
        fx, fy, cx, cy, distortion = P[0], P[5], P[2], P[6], [0.0] * 5
    else:
        if len(K) != 9 or K[0] <= 0 or K[4] <= 0:
            raise DatasetError(where, f"K is {K.tolist()}: the camera is not calibrated (run camera_calibration, or give --rig with the intrinsics)")
        fx, fy, cx, cy = K[0], K[4], K[2], K[5]
        model = str(msg.distortion_model)
        if len(D) == 0:
            distortion = [0.0] * 5
        elif model == "plumb_bob" and len(D) == 5:
            distortion = D.tolist()
        elif model == "rational_polynomial" and len(D) == 8:
            if np.any(D[5:] != 0.0):
                raise DatasetError(
                    where,
                    f"rational_polynomial distortion with k4, k5, k6 = {D[5:].tolist()}: the camera model has k1, k2, p1, p2, k3 only; "
                    "record the rectified image (image_rect) or calibrate with plumb_bob",
                )
            distortion = D[:5].tolist()
        else:
            raise DatasetError(where, f"distortion model {model!r} with {len(D)} coefficients: read are plumb_bob (5) and rational_polynomial (8)")
    if width <= 0 or height <= 0:
        raise DatasetError(where, f"image size {width}x{height} px: not an image")
    return {"width_px": width, "height_px": height, "fx_px": float(fx), "fy_px": float(fy), "cx_px": float(cx), "cy_px": float(cy), "distortion": [float(x) for x in distortion]}


def fixed_transforms(reader) -> tuple[TransformTree, set[str]]:
    """The transforms of ``/tf_static``, and those of ``/tf`` that never change (robot_state_publisher's
    fixed joints in an older bag), as a tree; and the frames of the ``/tf`` transforms that move
    (odom -> base_link), left out. Every message type on the topics is read (tf2_msgs/TFMessage and
    the older tf/tfMessage alike)."""
    tree = TransformTree()
    for topic in ("/tf_static",):
        for _, msg in topic_messages(reader, topic):
            for tr in msg.transforms:
                T = _finite_transform(tr)
                if T is not None:
                    tree.add(str(tr.header.frame_id), str(tr.child_frame_id), T)
    first: dict[tuple[str, str], np.ndarray] = {}
    moving: set[tuple[str, str]] = set()
    for _, msg in topic_messages(reader, "/tf"):
        for tr in msg.transforms:
            T = _finite_transform(tr)
            if T is None:
                continue
            key = (str(tr.header.frame_id).lstrip("/"), str(tr.child_frame_id).lstrip("/"))
            if key not in first:
                first[key] = T
            elif np.max(np.abs(first[key] - T)) > STATIC_TOLERANCE:
                moving.add(key)
    for key, T in first.items():
        if key not in moving:
            tree.add(key[0], key[1], T)
    return tree, {f for key in moving for f in key}


def _finite_transform(tr) -> np.ndarray | None:
    q, p = tr.transform.rotation, tr.transform.translation
    values = np.array([q.x, q.y, q.z, q.w, p.x, p.y, p.z], dtype=float)
    if not np.all(np.isfinite(values)) or np.linalg.norm(values[:4]) < 1e-6:
        return None
    return _transform_from_msg(tr.transform)


def rate_hz(t_ns: np.ndarray) -> float | None:
    """A stream's rate from its messages' times (ns): one over the median period, to 1 mHz; None with fewer than two."""
    t_ns = np.sort(np.asarray(t_ns, dtype=np.int64))
    dt = np.diff(t_ns)
    dt = dt[dt > 0]
    if not len(dt):
        return None
    return round(1e9 / float(np.median(dt)), 3)


def topic_times_ns(reader, topic: str) -> np.ndarray:
    """The bag's record times (ns) of ``topic``'s messages, without deserialising them."""
    connections = [c for c in reader.connections if c.topic == topic]
    if not connections:  # rosbags reads every topic when given none
        return np.zeros(0, dtype=np.int64)
    return np.array([t for _, t, _ in reader.messages(connections=connections)], dtype=np.int64)


def _first(reader, topic: str):
    for _, msg in topic_messages(reader, topic):
        return msg
    return None


def scan_layout(reader, path, topic: str, max_changed_fraction: float = 0.2) -> tuple[dict, str]:
    """The laser's beams and range limits (a rig's ``laser`` fields) from ``topic``'s scans, and their
    frame_id. The first scan's layout is the laser's; scans of another layout are the reader's to skip
    (a blemish), but a layout that changes and holds (more than ``max_changed_fraction`` of the scans)
    is a :class:`DatasetError` naming the message where it changes."""
    where = topic_where(path, topic)
    layout, frame, changed, n = None, "", [], 0
    for i, (_, msg) in enumerate(topic_messages(reader, topic)):
        n += 1
        this = (float(msg.angle_min), float(msg.angle_increment), len(msg.ranges))
        if layout is None:
            layout, frame = this, str(msg.header.frame_id).lstrip("/")
            limits = (float(msg.range_min), float(msg.range_max))
            if not (np.isfinite(this[0]) and np.isfinite(this[1]) and this[1] > 0 and this[2] >= 2):
                raise DatasetError(f"{where} message 0", f"{this[2]} beams from {this[0]} rad every {this[1]} rad: not a scan")
        elif this[2] != layout[2] or abs(this[0] - layout[0]) > 1e-5 or abs(this[1] - layout[1]) > 1e-5 * layout[1]:
            changed.append((i, this))
    if layout is None:
        raise DatasetError(where, "holds no message: the laser's beams cannot be read")
    if len(changed) > max_changed_fraction * n:
        i, other = changed[0]
        raise DatasetError(
            f"{where} message {i}",
            f"the beams change from {layout[2]} from {layout[0]:.6f} rad every {layout[1]:.6f} rad (message 0) to {other[2]} from "
            f"{other[0]:.6f} rad every {other[1]:.6f} rad, in {len(changed)} of {n} scans: one laser, one layout; cut the bag where it changes "
            "or record the scanner with fixed settings",
        )
    range_min, range_max = limits
    if not (np.isfinite(range_min) and np.isfinite(range_max)) or range_max <= max(range_min, 0.0):
        raise DatasetError(f"{where} message 0", f"range limits {range_min} to {range_max} m: not limits")
    beams = {"kind": "planar", "angle_min_rad": layout[0], "angle_increment_rad": layout[1], "count": layout[2]}
    return {"beams": beams, "range_min_m": max(range_min, 0.0), "range_max_m": range_max}, frame


def choose_body_frame(tree: TransformTree, given: str | None) -> tuple[str | None, str]:
    """The body frame (``given``, else base_footprint, else base_link where tf has them) and a sentence on where the ground is taken to be."""
    if given is not None:
        return given.lstrip("/"), f"body frame {given!r} (given): the ground taken at its z = 0, z up"
    for frame in BODY_FRAMES:
        if tree.has(frame):
            if frame == "base_footprint":
                return frame, "body frame 'base_footprint' (REP 105: on the ground under the robot): the ground taken at its z = 0, z up"
            return frame, (
                "body frame 'base_link' (tf has no base_footprint): the ground taken at its z = 0, z up; if base_link is above the ground "
                "(at the axles, as REP 105 allows), the flat-ground seeding is wrong: publish base_footprint or give --body-frame"
            )
    return None, ""


def derive_rig(reader, path: str | Path, topics: BagTopics, max_changed_fraction: float = 0.2) -> DerivedRig:
    """Everything the bag says of its rig (:class:`DerivedRig`); nothing is raised for what it lacks
    until :func:`rig_of_bag` knows whether a rig file gives it."""
    path = Path(path)
    values: dict = {}
    derived = DerivedRig(values)
    names = {c.topic: c.msgtype for c in reader.connections}
    tree, moving = fixed_transforms(reader)

    # the camera
    image_type = check_topic(reader, path, topics.image_topic, IMAGE_TYPES)
    first_image = _first(reader, topics.image_topic)
    camera_frame = topics.camera_frame or (str(first_image.header.frame_id).lstrip("/") if first_image is not None else "")
    info_topic = topics.camera_info_topic
    if info_topic is None:
        info_topic = next((t for t in camera_info_candidates(topics.image_topic) if names.get(t) == CAMERA_INFO_TYPE), None)
    intrinsics = ("camera.width_px", "camera.height_px", "camera.fx_px", "camera.fy_px", "camera.cx_px", "camera.cy_px", "camera.distortion")
    if info_topic is None:
        infos = sorted(t for t, m in names.items() if m == CAMERA_INFO_TYPE)
        derived.missing.append((intrinsics, DatasetError(
            topic_where(path, topics.image_topic),
            f"no sensor_msgs/CameraInfo beside it (looked for {' and '.join(camera_info_candidates(topics.image_topic))}; its CameraInfo topics: "
            f"{', '.join(infos) or 'none'}): record the camera's camera_info, or give --camera-info-topic, or --rig with the camera's intrinsics",
        )))
    else:
        check_topic(reader, path, info_topic, (CAMERA_INFO_TYPE,))
        info = _first(reader, info_topic)
        if info is None:
            derived.missing.append((intrinsics, DatasetError(topic_where(path, info_topic), "holds no message: the camera's intrinsics cannot be read")))
        else:
            rectified = is_rectified(topics.image_topic)
            for key, value in intrinsics_from_camera_info(info, rectified, topic_where(path, info_topic)).items():
                _set(values, f"camera.{key}", value)
            derived.notes.append(f"camera intrinsics from {info_topic} ({'P: the image is rectified' if rectified else str(info.distortion_model) or 'no distortion'})")
            camera_frame = camera_frame or str(info.header.frame_id).lstrip("/")
    camera_rate = rate_hz(topic_times_ns(reader, topics.image_topic))
    if camera_rate is not None:
        _set(values, "camera.rate_hz", camera_rate)
    del image_type

    # the laser
    check_topic(reader, path, topics.scan_topic, (SCAN_TYPE,))
    laser, scan_frame = scan_layout(reader, path, topics.scan_topic, max_changed_fraction)
    values["laser"] = laser
    laser_frame = topics.laser_frame or scan_frame
    laser_rate = rate_hz(topic_times_ns(reader, topics.scan_topic))
    if laser_rate is not None:
        laser["rate_hz"] = laser_rate

    # the extrinsics
    body, ground = choose_body_frame(tree, topics.body_frame)
    derived.body_frame = body
    if ground:
        derived.notes.append(ground)
    mounts = [("camera.T_body_cam", camera_frame, topics.image_topic), ("laser.T_body_laser", laser_frame, topics.scan_topic)]
    imu_frame = None
    if topics.imu_topic is not None:
        check_topic(reader, path, topics.imu_topic, (IMU_TYPE,))
        first_imu = _first(reader, topics.imu_topic)
        imu_frame = str(first_imu.header.frame_id).lstrip("/") if first_imu is not None else ""
        mounts.append(("imu.T_body_imu", imu_frame, topics.imu_topic))
    for field_path, frame, topic in mounts:
        problem = _mount_problem(tree, moving, body, frame, topic)
        if problem is None:
            _set(values, field_path, tree.lookup(body, frame).tolist())
            derived.from_tf = True
        else:
            derived.missing.append(((field_path,), DatasetError(path, f"{problem}: give --rig with {field_path}")))

    # the odometry and the IMU: noise from the defaults
    defaults = []
    if topics.odometry_topic is not None:
        odometry = OdometrySpec().model_dump()
        odometry_rate = rate_hz(topic_times_ns(reader, topics.odometry_topic))
        if odometry_rate is not None:
            odometry["rate_hz"] = odometry_rate
        values["odometry"] = odometry
        spec = OdometrySpec()
        defaults.append(
            f"odometry noise {spec.sigma_forward_m_per_sqrt_m:g} m/sqrt(m) forward and lateral, {np.degrees(spec.sigma_yaw_rad_per_sqrt_m):g} deg/sqrt(m) in yaw, "
            f"slip {spec.sigma_scale:.0%} (a wheeled vehicle's defaults; the messages' covariances are not used)"
        )
    if topics.imu_topic is not None:
        imu = {k: v for k, v in ImuSpec().model_dump(mode="json").items() if k != "T_body_imu"}
        imu_rate = rate_hz(topic_times_ns(reader, topics.imu_topic))
        if imu_rate is not None:
            imu["rate_hz"] = imu_rate
        values["imu"] = _merge(imu, values.get("imu", {}))
        defaults.append(f"IMU noise of the {ImuSpec().part}'s datasheet")
    camera_default, laser_default = CameraSpec.model_fields["noise_sigma_dn"].default, LaserSpec.model_fields["range_sigma_m"].default
    _set(values, "camera.noise_sigma_dn", camera_default)
    laser["range_sigma_m"] = laser_default
    defaults.append(f"image noise {camera_default:g} grey levels, range noise {laser_default:g} m")
    derived.notes.append("from the defaults (give --rig to set them): " + "; ".join(defaults))
    return derived


def _mount_problem(tree: TransformTree, moving: set[str], body: str | None, frame: str, topic: str) -> str | None:
    """Why tf gives no fixed ``T_body_frame`` for ``topic``'s sensor, None when it does."""
    known = sorted(tree.frames())
    if not frame:
        return f"the messages of {topic} name no frame_id: T_body of its sensor cannot be read from tf"
    if body is None:
        return f"tf has neither {' nor '.join(BODY_FRAMES)} (its fixed frames: {', '.join(known) or 'none'}): give --body-frame"
    if not tree.has(frame):
        why = " (it moves in /tf)" if frame in moving else ""
        return f"frame {frame!r} (the frame_id of {topic}) is not in tf's fixed transforms{why} (its frames: {', '.join(known) or 'none'})"
    if tree.lookup(body, frame) is None:
        return f"tf links no chain of fixed transforms from the body frame {body!r} to {frame!r} (the frame_id of {topic})"
    return None


def read_rig_overrides(path: str | Path) -> dict:
    """A rig file's mapping, as written (whole or in part: it overrides the bag's rig field by field)."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError("rig file not found", path)
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except (yaml.YAMLError, OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"cannot read the rig file ({str(exc).splitlines()[0]})", path) from None
    if not isinstance(data, dict):
        raise ConfigError("a rig file must hold a mapping (camera, laser, odometry, imu)", path)
    return data


def rig_of_bag(reader, path: str | Path, topics: BagTopics, rig_file: str | Path | None = None, max_changed_fraction: float = 0.2) -> tuple[SensorRig, DerivedRig]:
    """The rig of the bag at ``path``: :func:`derive_rig`, then ``rig_file``'s fields over it. What
    neither gives is the first missing value's :class:`DatasetError`; one warning says how the rig was made."""
    derived = derive_rig(reader, path, topics, max_changed_fraction)
    over = read_rig_overrides(rig_file) if rig_file is not None else {}
    values = _merge(derived.values, over)
    for fields, error in derived.missing:
        if not all(_has(over, f) for f in fields):
            raise error
    if topics.odometry_topic is None and "odometry" not in over:
        values.pop("odometry", None)
    source = f"{path} (the rig from the bag{', ' + str(rig_file) + ' over it' if rig_file is not None else ''})"
    rig = rig_from_dict(values, source)
    given = f"; {rig_file} over it: {', '.join(sorted(over))}" if over else ""
    log.warning("%s: the rig from the bag: %s%s", path, "; ".join(derived.notes), given)
    return rig, derived


def bag_rig(path: str | Path, topics: BagTopics, rig_file: str | Path | None = None) -> tuple[SensorRig, DerivedRig]:
    """:func:`rig_of_bag` on the bag at ``path``, opened and closed here."""
    with open_bag(path, quiet=True) as reader:
        return rig_of_bag(reader, path, topics, rig_file)


__all__ = ["BagTopics", "DerivedRig", "bag_rig", "camera_info_candidates", "derive_rig", "fixed_transforms", "intrinsics_from_camera_info", "is_rectified", "rate_hz", "rig_of_bag", "scan_layout"]
