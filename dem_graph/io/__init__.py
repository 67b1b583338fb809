"""File formats: TUM trajectories and elevation GeoTIFFs."""

from dem_graph.io.geotiff import read_elevation, read_elevation_geotiff, write_elevation, write_elevation_geotiff
from dem_graph.io.tum import read_tum, write_tum

__all__ = [
    "read_elevation",
    "read_elevation_geotiff",
    "read_tum",
    "write_elevation",
    "write_elevation_geotiff",
    "write_tum",
]
