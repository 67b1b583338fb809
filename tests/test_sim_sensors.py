"""The simulator's sensors against analytic truth: laser ranges on planes, projection of a marker."""

from __future__ import annotations

import numpy as np
import pytest

from dem_graph.geometry.grid import ElevationGrid, GridGeometry
from dem_graph.geometry.rig import default_rig
from dem_graph.geometry.se3 import invert, make_pose, rotation_from_rpy, transform_points
from dem_graph.sim.config import LightingSpec, TextureSpec
from dem_graph.sim.laser import cast_scan
from dem_graph.sim.raycast import TerrainScene, sphere_marker
from dem_graph.sim.render import CameraRenderer
from dem_graph.sim.terrain import Terrain
from dem_graph.sim.texture import GroundTexture


def _plane_grid(slope_x: float = 0.0, slope_y: float = 0.0, z0: float = 0.0, size_m: float = 40.0, res: float = 0.05) -> ElevationGrid:
    geometry = GridGeometry.covering(-size_m / 2, -size_m / 2, size_m / 2, size_m / 2, res)
    X, Y = geometry.cell_centers_xy()
    return ElevationGrid(geometry, (z0 + slope_x * X + slope_y * Y).astype(np.float32))


def _analytic_plane_ranges(T_world_laser, directions_laser, slope_x, slope_y, z0):
    # plane: z = z0 + sx x + sy y  <=>  n . p = z0 with n = (-sx, -sy, 1)
    n = np.array([-slope_x, -slope_y, 1.0])
    o = T_world_laser[:3, 3]
    d = directions_laser @ T_world_laser[:3, :3].T
    denom = d @ n
    with np.errstate(divide="ignore", invalid="ignore"):
        r = (z0 - o @ n) / denom
    r[(denom >= 0) | (r <= 0)] = np.inf
    return r


@pytest.mark.parametrize("slope", [(0.0, 0.0), (0.08, -0.05), (-0.15, 0.0)], ids=["flat", "slope-xy", "downhill"])
def test_laser_ranges_on_plane_match_analytic(slope):
    rig = default_rig()
    sx, sy = slope
    grid = _plane_grid(sx, sy, z0=0.1)
    scene = TerrainScene(grid)
    T_world_body = make_pose(rotation_from_rpy(0.02, -0.03, 0.4), [1.0, -0.5, 0.1])
    T_world_laser = T_world_body @ rig.T_body_laser
    truth = _analytic_plane_ranges(T_world_laser, rig.laser.beam_directions(), sx, sy, 0.1)
    inside = truth < 15.0  # rays that land on the 40 m grid
    expect_valid = inside & (truth >= rig.laser.range_min_m) & (truth <= rig.laser.range_max_m)

    noiseless = cast_scan(scene, T_world_laser, rig.laser, rng=None)
    assert np.array_equal(np.isfinite(noiseless[inside]), expect_valid[inside])
    # float32 mesh and ranges: agreement to 0.5 mm
    np.testing.assert_allclose(noiseless[expect_valid], truth[expect_valid], atol=5e-4)

    noisy = cast_scan(scene, T_world_laser, rig.laser, rng=np.random.default_rng(3))
    err = noisy[expect_valid] - truth[expect_valid]
    sigma = rig.laser.range_sigma_m
    assert abs(err.mean()) < 4 * sigma / np.sqrt(len(err))
    assert 0.85 * sigma < err.std() < 1.15 * sigma


def test_laser_no_return_beyond_max_range_and_into_sky():
    rig = default_rig()
    scene = TerrainScene(_plane_grid())
    T_world_laser = rig.T_body_laser
    ranges = cast_scan(scene, T_world_laser, rig.laser, rng=None)
    angles = rig.laser.beams.angle_min_rad + rig.laser.beams.angle_increment_rad * np.arange(rig.laser.beams.count)
    truth = _analytic_plane_ranges(T_world_laser, rig.laser.beam_directions(), 0, 0, 0)
    # beams near +-90 degrees run almost parallel to the ground: beyond 30 m or off the grid -> NaN
    assert np.all(np.isnan(ranges[truth > rig.laser.range_max_m]))
    assert np.isnan(ranges[np.argmax(np.abs(angles))])
    # the central beam hits flat ground 3 m ahead of the laser (the paper's set-up)
    centre = ranges[np.argmin(np.abs(angles))]
    hit = transform_points(T_world_laser, [[centre, 0.0, 0.0]])[0]
    assert hit[2] == pytest.approx(0.0, abs=1e-3)
    assert hit[0] - T_world_laser[0, 3] == pytest.approx(3.0, abs=0.01)


def _flat_renderer(rig, marker):
    grid = _plane_grid(size_m=30.0)
    terrain = Terrain(grid, np.zeros(grid.geometry.shape, dtype=np.float32))
    texture = GroundTexture.generate(TextureSpec(texel_m=0.02), terrain, np.random.default_rng(0))
    scene = TerrainScene(grid, markers=(marker,))
    return CameraRenderer(scene, texture, rig.camera_model, LightingSpec(), noise_sigma_dn=0.0), scene


@pytest.mark.parametrize("marker_world", [(4.0, 0.3, 0.4), (6.0, -1.5, 0.25), (3.0, 1.2, 0.8)])
def test_marker_appears_at_its_projection(marker_world):
    rig = default_rig()
    T_world_body = make_pose(rotation_from_rpy(0.0, 0.0, 0.0), [0.0, 0.0, 0.0])
    T_world_cam = T_world_body @ rig.T_body_cam
    marker = sphere_marker(marker_world, radius_m=0.03, albedo=1.0, resolution=40)
    renderer, scene = _flat_renderer(rig, marker)
    cam = rig.camera_model
    # object ids per pixel, from the same rays the renderer casts
    dirs = cam.pixel_bearings() @ T_world_cam[:3, :3].T
    hits = scene.cast(T_world_cam[:3, 3], dirs)
    mask = (hits.object_id == 1).reshape(cam.height_px, cam.width_px)
    assert mask.sum() > 20
    v, u = np.nonzero(mask)
    uv_expected, in_front = cam.project(transform_points(invert(T_world_cam), [marker_world]))
    assert in_front[0]
    assert np.hypot(u.mean() - uv_expected[0, 0], v.mean() - uv_expected[0, 1]) < 1.0
    # and the rendered image shows it: the marker is brighter than the ground around it
    image = renderer.render(T_world_cam).astype(float)
    ring = np.zeros_like(mask)
    r0, c0 = int(round(uv_expected[0, 1])), int(round(uv_expected[0, 0]))
    ring[r0 - 25 : r0 + 26, c0 - 25 : c0 + 26] = True
    ring &= ~mask
    assert image[mask].mean() > image[ring].mean() + 20


def test_filtered_texture_does_not_shimmer():
    """A camera moving by a fraction of a pixel footprint sees far ground change little when the
    texture is filtered, and a lot when it is point-sampled (aliasing)."""
    rig = default_rig()
    grid = _plane_grid(size_m=60.0, res=0.1)
    terrain = Terrain(grid, np.zeros(grid.geometry.shape, dtype=np.float32))
    texture = GroundTexture.generate(TextureSpec(), terrain, np.random.default_rng(1))
    scene = TerrainScene(grid)
    cam = rig.camera_model
    T0 = rig.T_body_cam.copy()
    T1 = T0.copy()
    T1[:3, 3] += [0.004, 0.003, 0.0]  # 5 mm: a small part of a far pixel's footprint (several cm)
    # far ground: rows whose ground distance exceeds 12 m (footprint > 2 cm, i.e. > 2 texels)
    dirs = cam.pixel_bearings() @ T0[:3, :3].T
    t = scene.cast(T0[:3, 3], dirs).t_hit_m.reshape(cam.height_px, cam.width_px)
    far = np.isfinite(t) & (t > 12.0) & (t < 25.0)
    changes = {}
    for filtered in (True, False):
        r = CameraRenderer(scene, texture, cam, LightingSpec(), noise_sigma_dn=0.0, filter_texture=filtered)
        a, b = r.render(T0).astype(float), r.render(T1).astype(float)
        changes[filtered] = np.abs(a - b)[far].mean()
    assert far.sum() > 5000
    assert changes[True] < 0.35 * changes[False]
    assert changes[True] < 1.5  # grey levels (measured 0.5)
