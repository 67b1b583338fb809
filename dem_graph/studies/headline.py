"""The headline numbers of a run, taken from its metrics (:class:`~dem_graph.pipeline.metrics.RunMetrics`):
which estimator, how accurate, how fast, as one row of a table.

Used by ``dem-graph evaluate`` (one run) and ``dem-graph compare`` (one row per estimator). Each
:class:`Column` names the fields its number sits under and the unit it is shown in; a number the
run did not measure (no ground truth, a run shorter than the RPE's distance, no DEM) is NaN, shown
as ``-``. A path that names no field is an error (and a test checks every column against the
metrics' types), so a renamed field cannot turn a column into ``-`` unnoticed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from pydantic import BaseModel

from dem_graph.pipeline.metrics import RunMetrics
from dem_graph.pipeline.run_dem import DemFailure


@dataclass(frozen=True)
class Column:
    key: str  # the number's name in summary.json (SI units, as the suffix says)
    label: str  # the table's header, with the unit shown
    path: tuple[str, ...]  # the fields of RunMetrics the number sits under (a dict's key for a dict)
    scale: float = 1.0  # shown value = value * scale
    digits: int = 3  # decimals shown


COLUMNS: tuple[Column, ...] = (
    Column("ate_anchored_rmse_m", "ATE (m)", ("trajectory", "ate_rmse_m")),
    Column("ate_aligned_rmse_m", "ATE aligned (m)", ("trajectory", "ate_aligned_rmse_m")),
    Column("drift_percent", "drift (%)", ("trajectory", "drift_percent"), digits=2),
    Column("final_height_error_m", "end height error (m)", ("trajectory", "final_height_error_m")),
    Column("rpe_10m_translation_rmse_m", "RPE 10 m (m)", ("trajectory", "rpe", "translation_rmse_m")),
    Column("rpe_10m_rotation_rmse_deg", "RPE 10 m (deg)", ("trajectory", "rpe", "rotation_rmse_deg"), digits=2),
    Column("dem_rmse_laser_cells_m", "DEM RMSE (cm)", ("dem", "height_error_laser_cells", "rmse_m"), scale=100.0, digits=2),
    Column("local_error_mean_m", "Fig. 8 mean (cm)", ("dem", "local_window", "mean_of_mean_m"), scale=100.0, digits=2),
    Column("local_error_std_m", "Fig. 8 std (cm)", ("dem", "local_window", "mean_of_std_m"), scale=100.0, digits=2),
    Column("live_local_error_mean_m", "live Fig. 8 mean (cm)", ("live_map", "local_window", "mean_of_mean_m"), scale=100.0, digits=2),
    Column("live_local_error_std_m", "live Fig. 8 std (cm)", ("live_map", "local_window", "mean_of_std_m"), scale=100.0, digits=2),
    Column("time_per_frame_median_ms", "frame ms (median)", ("time_per_frame", "total", "median_ms"), digits=1),
    Column("time_per_frame_p95_ms", "frame ms (p95)", ("time_per_frame", "total", "p95_ms"), digits=1),
    Column("points_per_frame", "points/frame", ("points_per_frame", "live_median"), digits=0),
    Column("live_map_update_median_ms", "map ms (median)", ("live_map", "update_median_ms"), digits=2),
)

# the forms a section takes when it was not measured: it holds no number
_NOT_MEASURED = (DemFailure,)


def metric_at(metrics: RunMetrics, path: tuple[str, ...]) -> float:
    """The number at ``path`` in ``metrics``; NaN when a section on the way was not measured.
    :class:`AttributeError` when ``path`` names no field."""
    value = metrics
    for key in path:
        if value is None or isinstance(value, _NOT_MEASURED):
            return math.nan
        if isinstance(value, dict):
            value = value.get(key)
        elif isinstance(value, BaseModel) and key in type(value).model_fields:
            value = getattr(value, key)
        else:
            raise AttributeError(f"{type(value).__name__} has no field {key!r} (column path {'.'.join(path)})")
    return float(value) if isinstance(value, (int, float)) and not isinstance(value, bool) else math.nan


def headline(metrics: RunMetrics | None) -> dict[str, float]:
    """Every column's number from a run's metrics, by key, in SI units (NaN when not measured; all NaN without metrics)."""
    return {c.key: math.nan if metrics is None else metric_at(metrics, c.path) for c in COLUMNS}


def format_value(column: Column, value: float) -> str:
    """The number as the table shows it: scaled, rounded, ``-`` for NaN."""
    if value is None or not math.isfinite(value):
        return "-"
    return f"{value * column.scale:.{column.digits}f}"


__all__ = ["COLUMNS", "Column", "format_value", "headline", "metric_at"]
