"""Open any dataset the package reads, from its path: a dataset folder, KITTI (either layout) or a ROS bag."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from dem_graph.datasets.base import Sequence
from dem_graph.datasets.checks import InputChecks
from dem_graph.errors import DatasetError

FORMATS = ("folder", "kitti-odometry", "kitti-raw", "rosbag")


@dataclass
class DatasetOptions:
    """What a format needs beyond its path (each used only by the formats it concerns)."""

    sequence: str | None = None  # KITTI odometry: the sequence number when ROOT holds several
    ring: int | None = None  # KITTI: the Velodyne ring used as the line laser (default: the one hitting the road ~10 m ahead)
    camera: int | None = None  # KITTI raw: the camera, 0-3 (default: the first the drive holds)
    truth: str | None = None  # KITTI raw: the true trajectory from the OXTS "positions" (default) or "velocities"
    rig: Path | None = None  # rosbag: a rig YAML over the rig the bag holds, field by field (default: the bag's own)
    image_topic: str | None = None  # rosbag
    scan_topic: str | None = None  # rosbag
    odometry_topic: str | None = None  # rosbag
    imu_topic: str | None = None  # rosbag: sensor_msgs/Imu (the rig needs an imu section)
    body_frame: str | None = None  # rosbag: the body's tf frame (default: base_footprint, else base_link)
    camera_frame: str | None = None  # rosbag: the camera's tf frame (default: the images' frame_id; given: tf wins over --rig)
    laser_frame: str | None = None  # rosbag: the laser's tf frame (default: the scans' frame_id; given: tf wins over --rig)
    camera_info_topic: str | None = None  # rosbag: sensor_msgs/CameraInfo (default: the image topic's sibling camera_info)
    input_checks: InputChecks | None = None  # folder, rosbag: the limits bad input is held to (None: the defaults)


_ROSBAG_ONLY = ("rig", "image_topic", "scan_topic", "odometry_topic", "imu_topic", "body_frame", "camera_frame", "laser_frame", "camera_info_topic")
USED_OPTIONS: dict[str, tuple[str, ...]] = {  # the DatasetOptions each format reads
    "folder": ("input_checks",),
    "kitti-odometry": ("sequence", "ring"),
    "kitti-raw": ("ring", "camera", "truth"),
    "rosbag": (*_ROSBAG_ONLY, "input_checks"),
}


def check_options_used(path: str | Path, fmt: str, options: DatasetOptions, told: bool = False) -> None:
    """Refuse options ``fmt`` does not read (a :class:`DatasetError` naming them as the command line
    does, e.g. ``--rig`` for a dataset folder, which has its own rig.yaml): a user who gives one
    expects it to count. ``told``: the format was told from the path, not given."""
    unused = [name for name in DatasetOptions.__dataclass_fields__ if getattr(options, name) is not None and name not in USED_OPTIONS.get(fmt, ())]
    if not unused:
        return
    flags = ", ".join(name if name == "input_checks" else "--" + name.replace("_", "-") for name in unused)
    users = sorted({f for f, names in USED_OPTIONS.items() for name in unused if name in names})
    how = " (the format told from the path; give --format to choose another)" if told else ""
    raise DatasetError(path, f"{flags}: not used by the {fmt} format{how}, only by {', '.join(users)}: leave {'it' if len(unused) == 1 else 'them'} out")


def detect_format(path: str | Path) -> str:
    """The format of the dataset at ``path``, from its layout; ``"folder"`` when nothing else fits."""
    from dem_graph.datasets.folder import DATASET_YAML
    from dem_graph.datasets.kitti import kitti_layout

    path = Path(path)
    if not path.exists() or (path.is_dir() and (path / DATASET_YAML).exists()):
        return "folder"  # a missing path: the folder reader's own error names it
    if path.is_dir():
        layout = kitti_layout(path)
        if layout is not None:
            return layout
        if (path / "metadata.yaml").exists():
            return "rosbag"
    if path.is_file() and path.suffix in (".bag", ".mcap", ".db3"):
        return "rosbag"
    return "folder"  # the folder reader says what is missing


def open_dataset(path: str | Path, format: str | None = None, options: DatasetOptions | None = None) -> Sequence:
    """The :class:`Sequence` at ``path``; ``format`` None: told from the path (:func:`detect_format`)."""
    options = options or DatasetOptions()
    fmt = format or detect_format(path)
    if fmt in USED_OPTIONS and (format is not None or Path(path).exists()):  # a missing path: the reader's error says so first
        check_options_used(path, fmt, options, told=format is None)
    if fmt == "folder":
        from dem_graph.datasets.folder import FolderSequence

        return FolderSequence(path, checks=options.input_checks)
    if fmt in ("kitti-odometry", "kitti-raw"):
        from dem_graph.datasets.kitti import open_kitti

        return open_kitti(path, fmt, options.sequence, options.ring, camera=options.camera, truth=options.truth)
    if fmt == "rosbag":
        return _open_bag(path, options)
    raise DatasetError(path, f"unknown dataset format {fmt!r}: choose from {', '.join(FORMATS)}")


def _open_bag(path: str | Path, options: DatasetOptions) -> Sequence:
    """A ROS bag with the rig it holds (:mod:`~dem_graph.datasets.bag_rig`), ``options.rig`` over it field by field."""
    from dem_graph.datasets.bag_rig import BagTopics, rig_of_bag
    from dem_graph.datasets.rosbag import RosbagSequence, open_bag

    missing = [n for n, v in (("--image-topic", options.image_topic), ("--scan-topic", options.scan_topic)) if v is None]
    if missing:
        raise DatasetError(path, f"a ROS bag needs {' and '.join(missing)} (`dem-graph bag-info {path}` lists its topics and proposes them)")
    topics = BagTopics(
        options.image_topic, options.scan_topic, options.odometry_topic, options.imu_topic, options.camera_info_topic,
        options.body_frame, options.camera_frame, options.laser_frame,
    )
    checks = options.input_checks or InputChecks()
    if Path(path).exists():
        with open_bag(path, quiet=True) as reader:
            rig, derived = rig_of_bag(reader, path, topics, options.rig, checks.max_skipped_fraction)
        body = options.body_frame or (derived.body_frame if derived.from_tf else None)
    else:  # the reader's own error names the path
        from dem_graph.geometry.rig import default_rig

        rig, body = default_rig(), options.body_frame
    return RosbagSequence(
        path,
        rig,
        options.image_topic,
        options.scan_topic,
        options.odometry_topic,
        body_frame=body,
        camera_frame=options.camera_frame,
        laser_frame=options.laser_frame,
        checks=options.input_checks,
        imu_topic=options.imu_topic,
    )


def reopen_dataset(path: str | Path, recorded: dict | None) -> Sequence:
    """The dataset at ``path`` opened as a run recorded it (:meth:`Sequence.open_options`, in the run's
    ``metrics.json``): its options (a KITTI ring, ...) applied, the format told from the path."""
    fields = DatasetOptions.__dataclass_fields__
    options = {k: v for k, v in (recorded or {}).items() if k in fields and v is not None}
    return open_dataset(path, None, DatasetOptions(**options))


def open_sequence(sequence: Sequence | str | Path, recorded: dict | None = None) -> Sequence:
    """``sequence`` itself, or the dataset at that path opened as a run recorded it (:func:`reopen_dataset`;
    None: the defaults)."""
    if isinstance(sequence, (str, Path)):
        return reopen_dataset(sequence, recorded)
    return sequence


__all__ = ["FORMATS", "USED_OPTIONS", "DatasetOptions", "check_options_used", "detect_format", "open_dataset", "open_sequence", "reopen_dataset"]
