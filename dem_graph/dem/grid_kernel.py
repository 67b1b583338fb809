"""The incremental grid's per-measurement arithmetic (:class:`~dem_graph.dem.incremental.IncrementalDem`)
in compiled loops: a batch gated against its cells and added to their sums, or taken back out.

One pass over the measurements in place of a dozen array calls (the gate, five ``bincount`` sums
over the cells' span, ``maximum.at`` for the times, the emptied cells' reset). The cells' sums are
added to one measurement at a time, where the array version added each cell's batch total: the
same sums in another order of addition (tested to 1e-9 against the batch fusion).
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True, nogil=True)
def add_batch(
    sums: np.ndarray,
    counts: np.ndarray,
    flat: np.ndarray,
    w: np.ndarray,
    wz: np.ndarray,
    z: np.ndarray,
    var: np.ndarray,
    t_rel: np.ndarray,
    laser: np.ndarray,
    gate_min_count: float,
    gate_sigma2: float,
    gate_floor2_m2: float,
) -> np.ndarray:
    """Gate every measurement against its cell as it stood before the batch, then add the kept ones
    to their cells' sums and the rejected ones to their outlier counts; returns the kept mask.

    ``sums`` (2, cells): 1/var and z/var sums; ``counts`` (4, cells) float32: kept, kept laser,
    outliers, latest time (``t_rel``, float32, after the grid's origin); ``flat`` (N,) each
    measurement's cell; ``w``, ``wz``, ``z``, ``var`` (N,): 1/var, z/var, z and var."""
    n = len(flat)
    kept = np.empty(n, dtype=np.bool_)
    for i in range(n):
        c = flat[i]
        if counts[0, c] < gate_min_count:
            kept[i] = True
        else:
            W = sums[0, c]
            d = z[i] - sums[1, c] / W
            kept[i] = d * d <= gate_sigma2 * (var[i] + 1.0 / W + gate_floor2_m2)
    for i in range(n):
        c = flat[i]
        if kept[i]:
            sums[0, c] += w[i]
            sums[1, c] += wz[i]
            counts[0, c] += 1.0
            if laser[i]:
                counts[1, c] += 1.0
            if t_rel[i] > counts[3, c]:
                counts[3, c] = t_rel[i]
        else:
            counts[2, c] += 1.0
    return kept


@numba.njit(cache=True, nogil=True)
def remove_batch(sums: np.ndarray, counts: np.ndarray, flat: np.ndarray, w: np.ndarray, wz: np.ndarray, laser: np.ndarray, kept: np.ndarray) -> None:
    """Take a batch back out (exactly what :func:`add_batch` put in); a cell left without a kept
    measurement is reset to exact zeros (its outlier count and time stay)."""
    n = len(flat)
    for i in range(n):
        c = flat[i]
        if kept[i]:
            sums[0, c] -= w[i]
            sums[1, c] -= wz[i]
            counts[0, c] -= 1.0
            if laser[i]:
                counts[1, c] -= 1.0
        else:
            counts[2, c] -= 1.0
    for i in range(n):
        c = flat[i]
        if counts[0, c] <= 0.5:  # counts are whole numbers: no measurement left, whatever the rounding
            sums[0, c] = 0.0
            sums[1, c] = 0.0
            counts[0, c] = 0.0
            counts[1, c] = 0.0


def compile_kernels() -> None:
    """Run both loops once on one cell, so that numba compiles them (the first run after an install)
    or loads them from its cache before a live run's first measurement rather than in it."""
    sums, counts = np.zeros((2, 1)), np.zeros((4, 1), dtype=np.float32)
    flat, one = np.zeros(1, dtype=np.int64), np.ones(1)
    laser = np.ones(1, dtype=np.bool_)
    kept = add_batch(sums, counts, flat, one, one, one, one, np.ones(1, dtype=np.float32), laser, 3.0, 9.0, 0.0)
    remove_batch(sums, counts, flat, one, one, laser, kept)


__all__ = ["add_batch", "compile_kernels", "remove_batch"]
