"""Seeded multi-scale random fields on regular grids (the building block of terrain and texture)."""

from __future__ import annotations

import cv2
import numpy as np


def smooth_noise(shape: tuple[int, int], cell_size: float, wavelength: float, rng: np.random.Generator) -> np.ndarray:
    """A smooth zero-mean, unit-variance random field on a grid of ``shape`` with cells of ``cell_size``.

    Its features have the size ``wavelength`` (same unit as ``cell_size``): white noise on a lattice of
    spacing ``wavelength`` is upsampled bicubically to the grid. Never periodic.
    """
    n_rows, n_cols = shape
    step = max(wavelength / cell_size, 1.0)
    coarse_rows = int(np.ceil(n_rows / step)) + 4
    coarse_cols = int(np.ceil(n_cols / step)) + 4
    coarse = rng.standard_normal((coarse_rows, coarse_cols)).astype(np.float32)
    if step <= 1.0:
        return coarse[:n_rows, :n_cols].copy()
    # upsample the lattice so that one lattice step spans `step` output cells, then crop
    up = cv2.resize(
        coarse,
        (int(round(coarse_cols * step)), int(round(coarse_rows * step))),
        interpolation=cv2.INTER_CUBIC,
    )
    offset = int(round(1.5 * step))
    field = up[offset : offset + n_rows, offset : offset + n_cols]
    return _standardize(field)


def _standardize(field: np.ndarray) -> np.ndarray:
    """Zero mean, unit variance, in place; statistics from a subsample (the field is smooth and large)."""
    stride = max(1, int(np.sqrt(field.size / 1e6)))
    sample = field[::stride, ::stride]
    mean, std = float(sample.mean()), float(sample.std())
    field -= np.float32(mean)
    field *= np.float32(1.0 / std if std > 0 else 1.0)
    return field


def fractal_noise(
    shape: tuple[int, int],
    cell_size: float,
    wavelengths: list[float],
    rng: np.random.Generator,
    exponent: float = 1.0,
) -> np.ndarray:
    """Sum of :func:`smooth_noise` octaves with amplitude ``wavelength ** exponent``, normalised to unit variance."""
    total = np.zeros(shape, dtype=np.float32)
    for w in wavelengths:
        octave = smooth_noise(shape, cell_size, w, rng)
        octave *= np.float32(w**exponent)
        total += octave
    return _standardize(total)


def smoothstep(edge0: float, edge1: float, x: np.ndarray) -> np.ndarray:
    """0 below ``edge0``, 1 above ``edge1``, a cubic in between (float32, computed in place on a copy)."""
    t = np.asarray(x, dtype=np.float32) - np.float32(edge0)
    t *= np.float32(1.0 / (edge1 - edge0))
    np.clip(t, 0.0, 1.0, out=t)
    out = np.float32(3.0) - np.float32(2.0) * t
    out *= t
    out *= t
    return out
