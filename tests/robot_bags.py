"""Bags as robots record them, for the tests (tests' helper, not a test module): the package's writer
(:mod:`dem_graph.datasets.bag_writer`), its options under the name the tests use for them."""

from __future__ import annotations

from dem_graph.datasets.bag_writer import (
    CAMERA_FRAME,
    EPOCH_S,
    IMAGE,
    IMU,
    INFO,
    LASER_FRAME,
    ODOM,
    SCAN,
    T_FOOTPRINT_LINK,
    f32_beams,
    robot_messages,
    write_robot_bag,
)
from dem_graph.datasets.bag_writer import BagOptions as BagEdits

__all__ = ["CAMERA_FRAME", "EPOCH_S", "IMAGE", "IMU", "INFO", "LASER_FRAME", "ODOM", "SCAN", "T_FOOTPRINT_LINK", "BagEdits", "f32_beams", "robot_messages", "write_robot_bag"]
