"""Imports of heavy or optional dependencies, with an error that says what to install."""

from __future__ import annotations

import importlib

from dem_graph.errors import MissingDependencyError


def _import(module: str, hint: str):
    try:
        return importlib.import_module(module)
    except ImportError as exc:
        if "libusb" in str(exc):
            raise MissingDependencyError(module, "the system library libusb-1.0 is missing: apt-get install -y libusb-1.0-0") from None
        raise MissingDependencyError(module, hint) from None


def import_open3d():
    return _import("open3d", "pip install open3d-cpu (or open3d)")


def import_rasterio():
    return _import("rasterio", "pip install rasterio")


def import_rosbags_typesys():
    """``rosbags.typesys`` (message definitions, CDR, type hashes), for the ROS 2 node and player."""
    return _import("rosbags.typesys", "pip install 'dem-graph[ros2]'")


def import_cyclonedds():
    """The ``cyclonedds`` package (Eclipse Cyclone DDS, one of ROS 2's middlewares), for the ROS 2 node and player."""
    return _import("cyclonedds", "pip install 'dem-graph[ros2]' (the cyclonedds wheel bundles its C library)")


def import_rosbags_highlevel():
    """``rosbags.highlevel`` (AnyReader), for reading ROS 1 and ROS 2 bags."""
    return _import("rosbags.highlevel", "pip install rosbags (or pip install 'dem-graph[ros]')")
