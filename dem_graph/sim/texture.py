"""Ground reflectance: soil and grass patches with multi-scale detail, sampled with mip-map filtering.

The texture is generated once per world on a regular grid (``texel_m``) and reduced into a
Gaussian pyramid. A pixel samples the pyramid level matching its footprint on the ground and
blends two neighbouring levels (trilinear filtering), so fine detail fades out smoothly with
distance instead of aliasing into shimmer from frame to frame.
"""

from __future__ import annotations

import cv2
import numpy as np

from dem_graph.geometry.grid import GridGeometry
from dem_graph.sim.config import TextureSpec
from dem_graph.sim.noise import fractal_noise, smooth_noise, smoothstep
from dem_graph.sim.terrain import Terrain

_SCALE = 65535.0


class GroundTexture:
    """Reflectance in [0, 1] of the ground at world (x, y), filtered over a footprint."""

    def __init__(self, levels: list[np.ndarray], geometry: GridGeometry):
        self.levels = levels  # level k has texel size geometry.resolution_m * 2**k
        self.geometry = geometry

    @classmethod
    def generate(cls, spec: TextureSpec, terrain: Terrain, rng: np.random.Generator) -> GroundTexture:
        g = terrain.geometry
        geometry = GridGeometry(g.x_min_m, g.y_max_m, spec.texel_m, int(np.ceil(g.n_rows * g.resolution_m / spec.texel_m)), int(np.ceil(g.n_cols * g.resolution_m / spec.texel_m)))
        shape, r = geometry.shape, spec.texel_m
        # where grass grows: large irregular patches with ragged borders
        patches = fractal_noise(shape, r, [spec.patch_size_m, spec.patch_size_m / 3], rng) + 0.35 * smooth_noise(shape, r, 0.15, rng)
        threshold = float(np.quantile(patches[:: max(1, shape[0] // 256), :: max(1, shape[1] // 256)], 1.0 - spec.grass_fraction))
        grass = smoothstep(threshold - 0.12, threshold + 0.12, patches)
        del patches
        c = spec.contrast
        soil = spec.soil_albedo + c * (0.07 * fractal_noise(shape, r, [0.03, 0.08, 0.25, 0.8], rng, exponent=0.6) + 0.05 * smooth_noise(shape, r, 0.02, rng))
        pebbles = smoothstep(1.6, 2.2, smooth_noise(shape, r, 0.025, rng))
        soil += c * 0.18 * pebbles
        del pebbles
        blades = fractal_noise(shape, r, [0.015, 0.03, 0.06], rng, exponent=0.3)
        tufts = smooth_noise(shape, r, 0.4, rng)
        grass_albedo = spec.grass_albedo + c * (0.10 * blades + 0.05 * tufts)
        del blades, tufts
        albedo = soil + grass * (grass_albedo - soil)
        del soil, grass_albedo, grass
        # stones: lighter, mottled
        cover = cv2.resize(terrain.stone_cover, (shape[1], shape[0]), interpolation=cv2.INTER_LINEAR)
        stone = 0.55 + c * 0.08 * smooth_noise(shape, r, 0.03, rng)
        albedo += cover * (stone - albedo)
        np.clip(albedo, 0.03, 0.97, out=albedo)
        levels = [albedo]
        while min(levels[-1].shape) > 8:
            levels.append(cv2.pyrDown(levels[-1]))
        # stored as 16-bit fixed point: half the memory traffic of float32, far finer than 8-bit grey levels
        return cls([np.rint(level * _SCALE).astype(np.uint16) for level in levels], geometry)

    def sample(self, x_m: np.ndarray, y_m: np.ndarray, footprint_m: np.ndarray) -> np.ndarray:
        """Reflectance at world points, averaged over a ground footprint of ``footprint_m`` (1-D arrays)."""
        g = self.geometry
        lod = np.log2(np.maximum(footprint_m, 1e-9) / g.resolution_m)
        lod = np.clip(lod, 0.0, len(self.levels) - 1.0)
        base = np.minimum(np.floor(lod).astype(np.int32), len(self.levels) - 2)
        frac = (lod - base).astype(np.float32)
        # continuous index in level-0 texels (centres at integers); pyrDown keeps texel j of level k at 2**k * j
        col0 = ((np.asarray(x_m) - g.x_min_m) / g.resolution_m - 0.5).astype(np.float32)
        row0 = ((g.y_max_m - np.asarray(y_m)) / g.resolution_m - 0.5).astype(np.float32)
        out = np.empty(len(col0), dtype=np.float32)
        for k in range(int(base.min()), int(base.max()) + 1) if len(base) else ():
            sel = np.flatnonzero(base == k)
            if len(sel) == 0:
                continue
            c, r = col0[sel], row0[sel]
            lo = self._lookup(k, c, r)
            hi = self._lookup(k + 1, c, r)
            out[sel] = lo + frac[sel] * (hi - lo)
        return out

    def _lookup(self, level: int, col0: np.ndarray, row0: np.ndarray) -> np.ndarray:
        # cv2.remap wants maps smaller than 32767 in each dimension: fold the points into rows of 1024
        n = len(col0)
        width = 1024
        rows = max(1, -(-n // width))
        scale = np.float32(2.0**-level)
        map_x = np.zeros(rows * width, dtype=np.float32)
        map_y = np.zeros(rows * width, dtype=np.float32)
        map_x[:n] = col0 * scale
        map_y[:n] = row0 * scale
        out = cv2.remap(self.levels[level], map_x.reshape(rows, width), map_y.reshape(rows, width), cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        return out.ravel()[:n].astype(np.float32) * np.float32(1.0 / _SCALE)
