"""The headline numbers of a run, taken from its metrics (``metrics.json``): which estimator, how
accurate, how fast, as one row of a table.

Used by ``dem-graph evaluate`` (one run) and ``dem-graph compare`` (one row per estimator). Each
:class:`Column` says where its number sits in the metrics and in which unit it is shown; a number
the metrics do not hold (no ground truth, a run shorter than the RPE's distance, no DEM) is NaN,
shown as ``-``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class Column:
    key: str  # the number's name in summary.json (SI units, as the suffix says)
    label: str  # the table's header, with the unit shown
    path: tuple[str, ...]  # where the number sits in a run's metrics
    scale: float = 1.0  # shown value = value * scale
    digits: int = 3  # decimals shown


COLUMNS: tuple[Column, ...] = (
    Column("ate_anchored_rmse_m", "ATE (m)", ("trajectory", "ate_rmse_m")),
    Column("ate_aligned_rmse_m", "ATE aligned (m)", ("trajectory", "ate_aligned_rmse_m")),
    Column("drift_percent", "drift (%)", ("trajectory", "drift_percent"), digits=2),
    Column("rpe_10m_translation_rmse_m", "RPE 10 m (m)", ("trajectory", "rpe", "translation_rmse_m")),
    Column("rpe_10m_rotation_rmse_deg", "RPE 10 m (deg)", ("trajectory", "rpe", "rotation_rmse_deg"), digits=2),
    Column("dem_rmse_laser_cells_m", "DEM RMSE (cm)", ("dem", "height_error_laser_cells", "rmse_m"), scale=100.0, digits=2),
    Column("local_error_mean_m", "Fig. 8 mean (cm)", ("dem", "local_window", "mean_of_mean_m"), scale=100.0, digits=2),
    Column("local_error_std_m", "Fig. 8 std (cm)", ("dem", "local_window", "mean_of_std_m"), scale=100.0, digits=2),
    Column("time_per_frame_median_ms", "frame ms (median)", ("time_per_frame", "total", "median_ms"), digits=1),
    Column("time_per_frame_p95_ms", "frame ms (p95)", ("time_per_frame", "total", "p95_ms"), digits=1),
    Column("points_per_frame", "points/frame", ("points_per_frame", "live_median"), digits=0),
)


def metric_at(metrics: dict, path: tuple[str, ...]) -> float:
    """The number at ``path`` in ``metrics``, NaN when it is absent or null."""
    value = metrics
    for key in path:
        if not isinstance(value, dict) or key not in value:
            return math.nan
        value = value[key]
    return float(value) if isinstance(value, (int, float)) and not isinstance(value, bool) else math.nan


def headline(metrics: dict) -> dict[str, float]:
    """Every column's number from a run's metrics, by key, in SI units (NaN when absent)."""
    return {c.key: metric_at(metrics, c.path) for c in COLUMNS}


def format_value(column: Column, value: float) -> str:
    """The number as the table shows it: scaled, rounded, ``-`` for NaN."""
    if value is None or not math.isfinite(value):
        return "-"
    return f"{value * column.scale:.{column.digits}f}"


__all__ = ["COLUMNS", "Column", "format_value", "headline", "metric_at"]
