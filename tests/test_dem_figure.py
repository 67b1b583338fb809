"""dem.png's colours span the ground near the path, not the walls beside it."""

from __future__ import annotations

import numpy as np
import pytest

from dem_graph.dem.layers import Dem
from dem_graph.geometry.grid import GridGeometry
from dem_graph.viz.dem_figure import COLOUR_PERCENTILES, NEAR_PATH_M, colour_range


def _street() -> tuple[Dem, np.ndarray]:
    """A 40 x 30 m map at 0.1 m: a street along y = 0 (heights uniform in [-0.05, 0.05] m, seeded),
    walls 13 m high from 8 m either side, and the path down the middle of the street."""
    g = GridGeometry.covering(0.0, -15.0, 40.0, 15.0, 0.1)
    X, Y = g.cell_centers_xy()
    z = np.random.default_rng(3).uniform(-0.05, 0.05, g.shape)
    z[np.abs(Y) > 8.0] = 13.0
    dem = Dem.empty(g)
    dem.layers["elevation"] = z.astype(np.float32)
    path = np.stack([np.linspace(1.0, 39.0, 200), np.zeros(200)], axis=1)
    return dem, path


def test_the_colours_span_the_ground_near_the_path():
    """Known truth: the cells within 5 m of the path are the street's alone, so the span is their own
    2nd and 98th percentiles (to float32), inside [-0.05, 0.05] m; the walls (13 m, 47 % of the map)
    do not move it. Without the path the span is every cell's, which the walls take over."""
    dem, path = _street()
    low, high, what = colour_range(dem, path)
    X, Y = dem.geometry.cell_centers_xy()
    near = (X >= 1.0 - NEAR_PATH_M) & (X <= 39.0 + NEAR_PATH_M) & (np.hypot(np.clip(X, 1.0, 39.0) - X, Y) <= NEAR_PATH_M)
    expected = np.percentile(dem.elevation[near], COLOUR_PERCENTILES)
    assert (low, high) == pytest.approx(tuple(expected), abs=2e-4)  # the path is sampled every 0.19 m: the 5 m disc's edge moves by < 1 mm
    assert -0.05 <= low < high <= 0.05
    assert what == "the ground within 5 m of the path, 2-98 %"
    low_all, high_all, what_all = colour_range(dem, None)
    assert high_all == pytest.approx(13.0) and what_all == "every covered cell, 2-98 %"


def test_a_path_that_passes_by_too_few_cells_falls_back_to_every_cell():
    dem, _ = _street()
    far = np.array([[500.0, 500.0], [501.0, 500.0]])
    assert colour_range(dem, far)[2] == "every covered cell, 2-98 %"

