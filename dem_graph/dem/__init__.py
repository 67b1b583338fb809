"""The dense DEM (the paper's III-F, Eq. 4): every laser return placed with the estimated poses,
fused per cell with its own uncertainty, in a global and a local view, with traversability layers.

- :mod:`~dem_graph.dem.returns`: laser returns and map points as world measurements with height variances;
- :mod:`~dem_graph.dem.fusion`: the vectorised per-cell fusion with a Mahalanobis gate;
- :mod:`~dem_graph.dem.layers`: the :class:`Dem` and its ``.npz`` file;
- :mod:`~dem_graph.dem.traversability`: slope, step height, roughness;
- :mod:`~dem_graph.dem.views`: the global map and the local map at a time.

Arrays in, maps out: a run's DEM is made by :mod:`dem_graph.pipeline.run_dem`, its files written by
:mod:`dem_graph.io.dem_files`.
"""

from dem_graph.dem.fusion import FusionConfig, covering_geometry, fuse
from dem_graph.dem.layers import Dem
from dem_graph.dem.returns import GroundReturns, PoseTrack, laser_returns_world, map_point_returns
from dem_graph.dem.views import global_dem, local_dem

__all__ = [
    "Dem",
    "FusionConfig",
    "GroundReturns",
    "PoseTrack",
    "covering_geometry",
    "fuse",
    "global_dem",
    "laser_returns_world",
    "local_dem",
    "map_point_returns",
]
