"""Camera images by ray casting the terrain: filtered texture, sun shading, vignetting, sensor noise."""

from __future__ import annotations

import numpy as np

from dem_graph.geometry.camera import PinholeCamera
from dem_graph.sim.config import LightingSpec
from dem_graph.sim.raycast import TerrainScene
from dem_graph.sim.texture import GroundTexture


class CameraRenderer:
    """Renders grey images of a :class:`TerrainScene` seen by a :class:`PinholeCamera` (with its distortion)."""

    def __init__(
        self,
        scene: TerrainScene,
        texture: GroundTexture,
        camera: PinholeCamera,
        lighting: LightingSpec,
        noise_sigma_dn: float,
        filter_texture: bool = True,
    ):
        self.scene = scene
        self.texture = texture
        self.camera = camera
        self.lighting = lighting
        self.noise_sigma_dn = noise_sigma_dn
        self.filter_texture = filter_texture  # False: point-sample the finest level (aliases; for tests)
        self._bearings_cam = camera.pixel_bearings().astype(np.float32)
        # angular size of a pixel along its bearing: 1/f at the centre, scaled by the bearing's obliquity
        self._pixel_angle = (self._bearings_cam[:, 2] ** 2 / np.sqrt(camera.fx_px * camera.fy_px)).astype(np.float32)
        el, az = np.radians(lighting.sun_elevation_deg), np.radians(lighting.sun_azimuth_deg)
        self._sun_world = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], dtype=np.float32)
        u = (np.arange(camera.width_px) - camera.cx_px) / camera.width_px
        v = (np.arange(camera.height_px) - camera.cy_px) / camera.height_px
        r2 = (u[None, :] ** 2 + v[:, None] ** 2) / 0.5
        self._vignette = (1.0 - lighting.vignetting * r2).astype(np.float32).ravel()
        self._noise_bank: np.ndarray | None = None
        self._rays = np.empty((len(self._bearings_cam), 6), dtype=np.float32)  # reused every frame

    def render(self, T_world_cam: np.ndarray, rng: np.random.Generator | None = None) -> np.ndarray:
        """An (H,W) uint8 image from camera pose ``T_world_cam``; noise from ``rng`` (none if ``None``)."""
        light = self.lighting
        R = T_world_cam[:3, :3].astype(np.float32)
        origin = T_world_cam[:3, 3].astype(np.float32)
        rays = self._rays
        rays[:, :3] = origin
        np.matmul(self._bearings_cam, R.T, out=rays[:, 3:])
        dirs = rays[:, 3:]
        hits = self.scene.cast_packed(rays)
        hit = hits.object_id >= 0
        # work on every pixel (sky pixels get t = 0 and are overwritten): cheaper than gathering subsets
        t = np.where(hit, hits.t_hit_m, np.float32(0.0))
        n = hits.normals_world
        cos_view = np.abs(np.einsum("ij,ij->i", n, dirs))
        # footprint: geometric mean of the across (t*angle) and along (t*angle/cos) extents
        footprint = t * self._pixel_angle / np.sqrt(np.maximum(cos_view, 0.05))
        if not self.filter_texture:
            footprint[:] = 0.0
        x = origin[0] + t * dirs[:, 0]
        y = origin[1] + t * dirs[:, 1]
        albedo = self.texture.sample(x, y, footprint)
        for k, marker in enumerate(self.scene.markers, start=1):
            albedo[hits.object_id == k] = marker.albedo
        sun = np.maximum(n @ self._sun_world, 0.0)
        shading = light.ambient + (1.0 - light.ambient) / max(float(self._sun_world[2]), 1e-3) * sun
        dn = albedo * shading
        dn[~hit] = light.sky_dn / (255.0 * light.exposure)
        dn *= np.float32(255.0 * light.exposure) * self._vignette
        if rng is not None and self.noise_sigma_dn > 0:
            dn += self._noise(rng, len(dn))
        return np.clip(dn, 0.0, 255.0).round().astype(np.uint8).reshape(self.camera.height_px, self.camera.width_px)

    def _noise(self, rng: np.random.Generator, n: int) -> np.ndarray:
        # a bank of Gaussian noise read at a random offset each frame: same statistics, a fraction of the cost
        if self._noise_bank is None:
            self._noise_bank = (self.noise_sigma_dn * rng.standard_normal(4 * n)).astype(np.float32)
        start = int(rng.integers(0, len(self._noise_bank) - n))
        return self._noise_bank[start : start + n]
