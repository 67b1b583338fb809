"""The focus area against its definition: stopping distance, cells, back-projection."""

from __future__ import annotations

import numpy as np
import pytest

from dem_graph.frontend.focus import FocusArea, FocusConfig
from dem_graph.geometry.ground_view import nearest_visible_ground_m
from dem_graph.geometry.rig import default_rig


def test_far_edge_is_the_stopping_distance_plus_margin():
    rig, cfg = default_rig(), FocusConfig()
    for v in (1.5, 2.0, 5.0):
        area = FocusArea.for_speed(cfg, rig, v)
        stopping = cfg.front_offset_m + v * cfg.reaction_time_s + v * v / (2 * cfg.braking_decel_mps2) + cfg.margin_m
        assert area.x_far_m == pytest.approx(max(min(stopping, cfg.max_distance_m), area.x_near_m + cfg.min_depth_m))
    # faster -> looks further ahead
    assert FocusArea.for_speed(cfg, rig, 5.0).x_far_m > FocusArea.for_speed(cfg, rig, 1.5).x_far_m


def test_near_edge_is_the_nearest_ground_the_camera_sees():
    rig = default_rig()
    # default camera: 1.6 m high, 0.9 m ahead, pitched 20 deg, vertical half field of view atan(300.5/560)
    half_fov = np.arctan2(rig.camera.height_px - 1 - rig.camera.cy_px, rig.camera.fy_px)
    # the distortion bends the bottom ray a little: allow 5 cm
    assert nearest_visible_ground_m(rig) == pytest.approx(0.9 + 1.6 / np.tan(np.radians(20.0) + half_fov), abs=0.05)


def test_cells_and_back_projection():
    rig = default_rig()
    area = FocusArea.for_speed(FocusConfig(), rig, 1.5)
    cells = area.cell_centers_body()
    nx, ny = area.shape
    assert len(cells) == nx * ny
    np.testing.assert_array_equal(area.cell_of(cells), np.arange(len(cells)))
    assert area.cell_of(np.array([[area.x_near_m - 0.01, 0.0, 0.0]]))[0] == -1
    # the outline projects into the lower part of the image (flat ground ahead)
    uv = area.image_polygon(rig)
    cam = rig.camera_model
    assert np.all(cam.in_image(uv))
    assert np.all(uv[:, 1] > cam.cy_px)
