"""The options that say how to open a dataset (its format, KITTI's and ROS bags' own), shared by
``run``, ``compare`` and ``degrade``, and the dataset they open."""

from __future__ import annotations

from pathlib import Path

import click

from dem_graph.cli.options import option

KITTI = "KITTI"
ROS_BAG = "ROS bag"
FORMATS = ["folder", "kitti-odometry", "kitti-raw", "rosbag"]

FORMAT_OPTION = option(
    "--format", "fmt", type=click.Choice(FORMATS), metavar="FORMAT", default=None, group="Input", help=f"{', '.join(FORMATS)} [default: told from the path]."
)
_READER_OPTIONS = (
    option("--sequence", metavar="SEQ", default=None, group=KITTI, help="odometry: the sequence, if the folder holds several."),
    option("--ring", type=click.IntRange(0, 63), metavar="0-63", default=None, group=KITTI, help="The Velodyne ring used as the laser [default: ~10 m ahead]."),
    option("--camera", type=click.IntRange(0, 3), metavar="0-3", default=None, group=KITTI, help="raw: the camera (2, 3: colour) [default: the first]."),
    option(
        "--truth", type=click.Choice(["positions", "velocities"]), metavar="SOURCE", default=None, group=KITTI,
        help="raw: the truth from the GPS 'positions' or the OXTS 'velocities' integrated [default: positions].",
    ),
    option("--rig", type=click.Path(dir_okay=False, path_type=Path), default=None, group=ROS_BAG, help="A rig YAML over the bag's own, whole or in part."),
    option("--image-topic", metavar="TOPIC", default=None, group=ROS_BAG, help="Image or CompressedImage topic."),
    option("--scan-topic", metavar="TOPIC", default=None, group=ROS_BAG, help="LaserScan topic."),
    option("--odometry-topic", metavar="TOPIC", default=None, group=ROS_BAG, help="Odometry topic (optional)."),
    option("--imu-topic", metavar="TOPIC", default=None, group=ROS_BAG, help="Imu topic (optional; T_body_imu from tf)."),
    option("--camera-info-topic", metavar="TOPIC", default=None, group=ROS_BAG, help="CameraInfo topic [default: the image topic's]."),
    option("--body-frame", metavar="FRAME", default=None, group=ROS_BAG, help="The body's tf frame, on the ground, z up [default: base_footprint, else base_link]."),
    option("--camera-frame", metavar="FRAME", default=None, group=ROS_BAG, help="The camera's tf frame, over --rig [default: the images']."),
    option("--laser-frame", metavar="FRAME", default=None, group=ROS_BAG, help="The laser's tf frame, over --rig [default: the scans']."),
)
_DATASET_KEYS = (
    "sequence", "ring", "camera", "truth", "rig", "image_topic", "scan_topic", "odometry_topic", "imu_topic", "camera_info_topic", "body_frame", "camera_frame",
    "laser_frame",
)


def reader_options(fn):
    """Decorate a command with KITTI's and ROS bags' options (listed under their own headings)."""
    for decorator in reversed(_READER_OPTIONS):
        fn = decorator(fn)
    return fn


def dataset_options(fn):
    """Decorate a command with every dataset option: ``--format``, then :func:`reader_options`."""
    return FORMAT_OPTION(reader_options(fn))


def pop_reader_options(kwargs: dict) -> dict:
    """The reader's options (KITTI's, ROS bags') taken out of a command's ``kwargs``."""
    return {k: kwargs.pop(k) for k in _DATASET_KEYS}


def pop_dataset_options(kwargs: dict) -> dict:
    """The dataset options taken out of a command's ``kwargs``: ``fmt`` and the reader's options."""
    return {"fmt": kwargs.pop("fmt")} | pop_reader_options(kwargs)


def dataset_options_of(options: dict):
    """The reader's :class:`DatasetOptions` of the options given (None: not given)."""
    from dem_graph.datasets.open import DatasetOptions

    return DatasetOptions(**{k: v for k, v in options.items() if v is not None})


def open_dataset(path: Path, fmt: str | None = None, **options):
    """The dataset at ``path``: a dataset folder, KITTI (either layout) or a ROS bag (told from the path unless ``fmt``)."""
    from dem_graph.datasets.open import open_dataset as open_any

    return open_any(path, fmt, dataset_options_of(options))
