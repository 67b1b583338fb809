"""dem_graph: camera + single-line laser SLAM and dense Digital Elevation Maps.

Conventions (see README): world z-up; body x-forward, y-left, z-up; camera OpenCV
(x right, y down, z forward); ``T_a_b`` maps coordinates in frame b to frame a.
6-vectors and 6x6 covariances follow gtsam's Pose3 tangent order [rotation, translation].
"""

from dem_graph.errors import ConfigError, DatasetError, DemGraphError, MissingDependencyError

__version__ = "0.1.0"

__all__ = ["ConfigError", "DatasetError", "DemGraphError", "MissingDependencyError", "__version__"]
