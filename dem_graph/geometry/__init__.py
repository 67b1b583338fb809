"""Poses, interpolation, the camera model and the sensor rig."""

from dem_graph.geometry.camera import PinholeCamera
from dem_graph.geometry.se3 import (
    invert,
    make_pose,
    matrix_from_quat_xyzw,
    quat_xyzw_from_matrix,
    rotation_from_rpy,
    transform_points,
)
from dem_graph.geometry.trajectory import Trajectory

__all__ = [
    "PinholeCamera",
    "Trajectory",
    "invert",
    "make_pose",
    "matrix_from_quat_xyzw",
    "quat_xyzw_from_matrix",
    "rotation_from_rpy",
    "transform_points",
]
