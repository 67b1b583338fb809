"""Where the laser's line meets the flat ground against the ground the camera sees, from the rig
alone (geometry.ground_view), checked against the mounts' own trigonometry."""

from __future__ import annotations

import numpy as np
import pytest

from dem_graph.geometry.ground_view import laser_view, nearest_visible_ground_m
from dem_graph.geometry.rig import car_rig, default_rig, laser_mount


def test_the_paper_rig_sees_its_laser_line():
    """The paper's laser: 1.0 m ahead of the body origin, 1.2 m up, pitched to meet the ground 3 m
    ahead of itself: its straight-ahead beam lands at 4.0 m. The camera (0.9 m ahead, 1.6 m up, 20
    degrees down, 600 rows, fy 560, cy 299.5) sees from 0.9 + 1.6 / tan(20 deg + atan(299.5 / 560)),
    distortion aside (k1 = -0.05 moves the bottom row's ray by under 0.3 degrees)."""
    view = laser_view(default_rig())
    assert view.laser_ahead_m == pytest.approx(4.0, abs=1e-9)
    assert view.camera_nearest_m == pytest.approx(0.9 + 1.6 / np.tan(np.radians(20.0) + np.arctan(299.5 / 560.0)), abs=0.05)
    assert view.in_view and view.in_image > 0.2 * view.on_ground
    assert view.line().endswith("% of the laser's ground is in the image")


def test_a_bumper_laser_below_the_camera_view_is_said_in_one_line():
    """The car's rig: the laser 0.8 m ahead, 0.33 m up, meeting the road 1.7 m ahead of itself (2.5 m
    from the body origin); the camera 1.4 m up, 2 degrees down, undistorted, fy 750, its bottom row
    (479) 239.5 px under the centre: it sees from 1.4 / tan(2 deg + atan(239.5 / 750)) = 3.908 m. Of the
    541 beams (-135 to +135 degrees by 0.5), those meeting the road within 50 m have
    cos(angle) >= 0.33 / (50 sin(pitch)): |angle| <= 88.0 degrees, 353 beams; none falls in the image."""
    rig = car_rig()
    view = laser_view(rig)
    pitch = np.arctan2(0.33, 1.7)
    assert view.laser_ahead_m == pytest.approx(2.5, abs=1e-9)
    assert view.camera_nearest_m == pytest.approx(1.4 / np.tan(np.radians(2.0) + np.arctan(239.5 / 750.0)), abs=1e-9)
    assert nearest_visible_ground_m(rig) == view.camera_nearest_m
    angles = np.radians(-135.0 + 0.5 * np.arange(541))
    expected = int(np.count_nonzero(np.cos(angles) >= 0.33 / (50.0 * np.sin(pitch))))
    assert view.on_ground == expected == 353 and view.in_image == 0 and not view.in_view
    line = view.line()
    assert "\n" not in line and line.startswith("laser: its line meets the flat ground 2.50 m ahead (353 of 541 beams); the camera sees the ground from 3.91 m ahead")
    assert "nearer than the camera's view (0 % of it in the image)" in line


def test_a_laser_looking_up_meets_no_ground():
    rig = default_rig()
    rig = rig.model_copy(update={"laser": rig.laser.model_copy(update={"T_body_laser": laser_mount([1.0, 0.0, 1.2], -np.radians(10.0))})})
    view = laser_view(rig)
    assert view.on_ground == 0 and not view.in_view
    assert view.line().startswith("laser: none of its 361 beams meets the flat ground ahead")
