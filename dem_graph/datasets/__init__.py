"""Event types, the Sequence interface, and the dataset readers and writers."""

from dem_graph.datasets.base import GroundTruth, Sequence
from dem_graph.datasets.events import CameraFrame, Event, ImuSample, LaserScan, Odometry
from dem_graph.datasets.folder import FolderSequence, open_folder_dataset, write_folder_dataset

__all__ = [
    "CameraFrame",
    "Event",
    "FolderSequence",
    "GroundTruth",
    "ImuSample",
    "LaserScan",
    "Odometry",
    "Sequence",
    "open_folder_dataset",
    "write_folder_dataset",
]
