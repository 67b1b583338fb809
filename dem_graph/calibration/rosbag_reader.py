"""Calibration recordings from ROS 1 (``.bag``) and ROS 2 (folder) bags, read with ``rosbags`` through the
helpers of :mod:`dem_graph.datasets.rosbag`.

The user names the topics:

- ``image_topic``: ``sensor_msgs/Image`` or ``sensor_msgs/CompressedImage`` (the encodings
  :func:`~dem_graph.datasets.rosbag.image_from_message` decodes);
- ``scan_topic``: ``sensor_msgs/LaserScan``; every scan must have the first one's ``angle_min``,
  ``angle_increment`` and beam count. A range that is not finite or lies outside
  ``[range_min, range_max]`` is no return (NaN);
- ``camera_info_topic``: ``sensor_msgs/CameraInfo``, the first message's ``K``, ``D`` (``plumb_bob``:
  k1, k2, p1, p2, k3) and image size; or, instead, ``intrinsics_path``: OpenCV's calibration output
  (:func:`~dem_graph.calibration.readers.read_opencv_intrinsics`), which may also give the board.

A bag does not say which board it shows: give it to :func:`~dem_graph.calibration.pipeline.calibrate_recording`
(``--board`` and ``--square-m`` on the command line) unless the intrinsics file does. Times are the header
stamps, seconds, and must increase on each topic. Scans are read when the bag is opened; images are only
listed then (stamp and place in the bag) and each is read from the bag again when the calibration asks for
it, so a bag of thousands of frames costs memory for one image at a time.
"""

from __future__ import annotations

from functools import partial
from pathlib import Path

import numpy as np

from dem_graph.calibration.readers import CalibrationRecording, Intrinsics, ScanSet, read_opencv_intrinsics
from dem_graph.datasets.rosbag import (
    IMAGE_TYPES,
    SCAN_TYPE,
    check_increasing,
    check_topic,
    image_from_message,
    open_bag,
    read_scan_topic,
    stamp_s,
    topic_messages,
    topic_where,
)
from dem_graph.errors import DatasetError

CAMERA_INFO_TYPE = "sensor_msgs/msg/CameraInfo"


def read_rosbag_recording(
    path: str | Path,
    image_topic: str,
    scan_topic: str,
    camera_info_topic: str | None = None,
    intrinsics_path: str | Path | None = None,
) -> CalibrationRecording:
    """A calibration recording from a bag (see the module). ``intrinsics_path``, when given, is used and
    ``camera_info_topic`` is not read; one of the two is needed."""
    path = Path(path)
    if intrinsics_path is None and camera_info_topic is None:
        raise DatasetError(path, "no intrinsics: give a sensor_msgs/CameraInfo topic or an OpenCV intrinsics file")
    intrinsics, board = read_opencv_intrinsics(intrinsics_path) if intrinsics_path is not None else (None, None)
    with open_bag(path) as reader:
        image_type = check_topic(reader, path, image_topic, IMAGE_TYPES)
        check_topic(reader, path, scan_topic, (SCAN_TYPE,))
        if intrinsics is None:
            check_topic(reader, path, camera_info_topic, (CAMERA_INFO_TYPE,))
            intrinsics = _read_camera_info(reader, topic_where(path, camera_info_topic), camera_info_topic)
        scans = _read_scans(reader, topic_where(path, scan_topic), scan_topic)
        times_s, keys = _list_images(reader, topic_where(path, image_topic), image_topic, intrinsics)
    names = [f"image {i} ({t:.3f} s)" for i, t in enumerate(times_s)]
    return CalibrationRecording(names, times_s, scans, intrinsics, board, keys, partial(_read_image, path, image_topic, image_type))


def _field(msg, name: str):
    """A CameraInfo field: ROS 2 spells the matrices in lower case (``k``, ``d``), ROS 1 in upper case."""
    return getattr(msg, name) if hasattr(msg, name) else getattr(msg, name.upper())


def _read_camera_info(reader, where: str, topic: str) -> Intrinsics:
    msg = next((m for _, m in topic_messages(reader, topic)), None)
    if msg is None:
        raise DatasetError(where, "no CameraInfo message")
    K = np.asarray(_field(msg, "k"), dtype=float).reshape(3, 3)
    coeffs = np.asarray(_field(msg, "d"), dtype=float).ravel()
    model = str(msg.distortion_model)
    if model not in ("plumb_bob", "rational_polynomial", "") or (model == "" and coeffs.size):
        raise DatasetError(where, f"distortion model {model!r} is not supported (plumb_bob: k1, k2, p1, p2, k3)")
    if coeffs.size > 5 and np.any(coeffs[5:] != 0):
        raise DatasetError(where, f"{model} with {coeffs.size} coefficients, some beyond k3 non-zero: only k1, k2, p1, p2, k3 are supported")
    if not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0 or K[2, 2] != 1.0:
        raise DatasetError(where, f"K is not a valid camera matrix ({K.ravel().tolist()})")
    width, height = int(msg.width), int(msg.height)
    if width <= 0 or height <= 0:
        raise DatasetError(where, f"image size {width}x{height} is not valid")
    return Intrinsics(K, np.pad(coeffs[:5], (0, 5 - min(coeffs.size, 5))), width, height)


def _read_scans(reader, where: str, topic: str) -> ScanSet:
    t_s, ranges, layout = read_scan_topic(reader, topic, where)
    if layout is None:
        raise DatasetError(where, "no LaserScan message")
    return ScanSet(t_s, layout[0], layout[1], ranges.astype(float))


def _list_images(reader, where: str, topic: str, intrinsics: Intrinsics) -> tuple[np.ndarray, list[tuple[int, int, float]]]:
    """Image stamps and keys ``(bag time ns, rank among the topic's messages at that bag time, stamp)``; the images are not kept."""
    times, keys, previous_ns, rank = [], [], None, 0
    for t_ns, msg in topic_messages(reader, topic):
        rank = rank + 1 if t_ns == previous_ns else 0
        previous_ns = t_ns
        if not keys and hasattr(msg, "width") and (int(msg.width), int(msg.height)) != (intrinsics.width_px, intrinsics.height_px):
            raise DatasetError(where, f"images are {msg.width}x{msg.height}, the intrinsics are for {intrinsics.width_px}x{intrinsics.height_px}")
        t_s = stamp_s(msg.header)
        times.append(t_s)
        keys.append((t_ns, rank, t_s))
    if not keys:
        raise DatasetError(where, "no image message")
    t_s = np.array(times)
    check_increasing(t_s, where)
    return t_s, keys


def _read_image(path: Path, topic: str, msgtype: str, key: tuple[int, int, float], color: bool = False) -> np.ndarray:
    """The image of ``key`` (see :func:`_list_images`), read from the bag again; grey or BGR as encoded."""
    t_ns, rank, t_s = key
    where = topic_where(path, topic)
    with open_bag(path) as reader:
        for i, (_, msg) in enumerate(topic_messages(reader, topic, t_ns, t_ns + 1)):
            if i == rank and stamp_s(msg.header) == t_s:
                return image_from_message(msg, msgtype, where)
    raise DatasetError(where, f"the image stamped {t_s!r} s is no longer in the bag")
