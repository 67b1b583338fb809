"""Wrong matches injected in place of the tracker's, for robustness studies, and the screening of
the matches they pass through in every estimator.

:meth:`FalseMatches.apply` replaces a tracked pixel by one ``offset_px`` away, with probability
``fraction``; :meth:`FalseMatches.screen` puts one match through it and asks the estimator's own
test whether it accepts an injected one (counting what it decides); :meth:`FalseMatches.screen_batch`
does so for every match of a batched search, in order, so the random draws follow the points.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable

import numpy as np

from dem_graph.estimators.settings import FalseMatchConfig
from dem_graph.frontend.tracker import TrackBatch


class FalseMatches:
    """Replaces a tracked pixel by one ``offset_px`` away in a random direction, with probability
    ``fraction``; counts what the estimator then does with it."""

    def __init__(self, config: FalseMatchConfig, counters: Counter):
        self.config = config
        self.counters = counters
        self._rng = np.random.default_rng(config.seed)

    @property
    def enabled(self) -> bool:
        """False when :meth:`apply` returns every match unchanged (and draws nothing)."""
        return self.config.fraction > 0

    def apply(self, uv_found: np.ndarray | None, uv_predicted: np.ndarray) -> tuple[np.ndarray | None, bool]:
        """``(pixel, injected)``: the match, or a wrong one near it (near the prediction if the tracker found nothing)."""
        if self.config.fraction <= 0 or self._rng.random() >= self.config.fraction:
            return uv_found, False
        a = self._rng.uniform(0, 2 * np.pi)
        base = uv_found if uv_found is not None else uv_predicted
        return base + self.config.offset_px * np.array([np.cos(a), np.sin(a)]), True

    def record(self, accepted: bool) -> bool:
        """Count an injected match as accepted or rejected by the estimator; returns ``accepted``."""
        self.counters["injected"] += 1
        self.counters["injected_accepted" if accepted else "injected_rejected"] += 1
        return accepted

    def screen(self, uv_found: np.ndarray | None, uv_predicted: np.ndarray, accepts: Callable[[np.ndarray], bool]) -> np.ndarray | None:
        """One match (None: the tracker found nothing) through :meth:`apply`: the pixel to use, or
        None when there is none or an injected one fails ``accepts(pixel - uv_predicted)`` (the
        estimator's gate, which :meth:`record` counts)."""
        found, injected = self.apply(uv_found, uv_predicted)
        if found is None:
            return None
        if injected and not self.record(accepts(found - uv_predicted)):
            return None
        return found

    def screen_batch(
        self, sel: np.ndarray, batch: TrackBatch, uv_predicted: np.ndarray, accepts: Callable[[int, np.ndarray], bool]
    ) -> tuple[np.ndarray, np.ndarray]:
        """The matches of a batched search of points ``sel`` (indices into ``uv_predicted``), each
        through :meth:`screen` with ``accepts(i, innovation)``: the indices kept (m,) and their
        pixels (m,2). Without injection, the tracker's matches as they are."""
        if not self.enabled:
            return sel[batch.ok], batch.uv_px[batch.ok]
        idx, found_uv = [], []
        for i, ok, uv_found in zip(sel, batch.ok.tolist(), batch.uv_px):
            found = self.screen(uv_found if ok else None, uv_predicted[i], lambda y, i=i: accepts(i, y))
            if found is None:
                continue
            idx.append(i)
            found_uv.append(found)
        return np.array(idx, dtype=int), np.array(found_uv, dtype=float).reshape(-1, 2)


__all__ = ["FalseMatches"]
