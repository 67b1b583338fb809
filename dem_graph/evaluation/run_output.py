"""The run folder every estimator writes (``dem-graph run DATASET --estimator NAME --out RUN``).

::

    RUN/
      trajectory.tum     the estimated T_world_body (TUM, readable by evo)
      points.ply         the estimated 3-D points and their per-point attributes (binary PLY)
      metrics.json       accuracy and timing numbers (pretty, sorted keys, NaN and infinities as null)
      config.yaml        the configuration the run used
      <name>.tum         any extra trajectory (e.g. ``odometry.tum``, ``ground_truth.tum``)
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import yaml

from dem_graph.errors import DatasetError, DemGraphError
from dem_graph.evaluation.timing import TimingStats
from dem_graph.geometry.trajectory import Trajectory
from dem_graph.io.ply import write_points_ply
from dem_graph.io.tum import write_tum

_RESERVED = ("trajectory", "points", "metrics", "config")


def _plain(value, *, nan_to_none: bool):
    """``value`` with numpy scalars and arrays, tuples and paths turned into plain Python data."""
    if isinstance(value, dict):
        return {str(k): _plain(v, nan_to_none=nan_to_none) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v, nan_to_none=nan_to_none) for v in value]
    if isinstance(value, np.ndarray):
        return _plain(value.tolist(), nan_to_none=nan_to_none)
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, float) and nan_to_none and not math.isfinite(value):
        return None
    return value


def _write_text(path: Path, text: str) -> None:
    try:
        path.write_text(text, encoding="utf-8")
    except OSError as exc:
        raise DatasetError(path, f"cannot write ({exc.strerror or exc})") from None


def json_text(data: dict, what: str = "data") -> str:
    """``data`` as the run folder writes JSON: pretty, sorted keys, numpy values as plain numbers and
    lists, NaN and infinities as ``null``. Raises :class:`DemGraphError` naming ``what`` if it cannot."""
    try:
        return json.dumps(_plain(data, nan_to_none=True), indent=2, sort_keys=True, allow_nan=False) + "\n"
    except (TypeError, ValueError) as exc:
        raise DemGraphError(f"{what} cannot be written as JSON: {exc}") from None


def write_json(path: str | Path, data: dict, what: str = "data") -> Path:
    """Write ``data`` to ``path`` as :func:`json_text`; :class:`DatasetError` naming the file if it cannot."""
    path = Path(path)
    _write_text(path, json_text(data, what))
    return path


def write_run_outputs(
    out_dir: str | Path,
    trajectory: Trajectory,
    points_xyz,
    point_attributes: dict | None,
    metrics: dict,
    config: dict,
    extra_trajectories: dict[str, Trajectory] | None = None,
) -> dict[str, Path]:
    """Write a run folder (created if needed; existing files are overwritten).

    Returns the written paths by name: ``trajectory``, ``points``, ``metrics``, ``config`` and each
    extra trajectory's name. ``metrics`` and ``config`` may hold numpy scalars and arrays, tuples and
    paths (written as plain numbers, lists and strings); in ``metrics.json`` NaN and infinities are
    written as ``null``. Extra trajectory names must be plain file stems, other than the four above.

    Raises :class:`DemGraphError` for bad arguments, :class:`DatasetError` when a file cannot be written.
    """
    out_dir = Path(out_dir)
    extras = {} if extra_trajectories is None else dict(extra_trajectories)
    for name in extras:
        if not isinstance(name, str) or not name or name in _RESERVED or name.startswith(".") or any(c in name for c in "/\\"):
            raise DemGraphError(f"extra trajectory name {name!r} is not a plain file stem other than {', '.join(_RESERVED)}")

    metrics_text = json_text(metrics, "metrics")
    try:
        config_text = yaml.safe_dump(_plain(config, nan_to_none=False), sort_keys=False)
    except yaml.YAMLError as exc:
        raise DemGraphError(f"config cannot be written as YAML: {exc}") from None

    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise DatasetError(out_dir, f"cannot create the run folder ({exc.strerror or exc})") from None

    paths = {
        "trajectory": out_dir / "trajectory.tum",
        "points": out_dir / "points.ply",
        "metrics": out_dir / "metrics.json",
        "config": out_dir / "config.yaml",
    }
    write_tum(paths["trajectory"], trajectory)
    write_points_ply(paths["points"], points_xyz, point_attributes or {})
    _write_text(paths["metrics"], metrics_text)
    _write_text(paths["config"], config_text)
    for name, extra in extras.items():
        paths[name] = out_dir / f"{name}.tum"
        write_tum(paths[name], extra)
    return paths


def frame_timing_summary(per_frame: dict[str, list[float]]) -> dict[str, dict[str, float]]:
    """Per-phase timing of a run: ``{phase: {"median_ms", "p95_ms", "mean_ms"}}``.

    ``per_frame`` maps a phase ("total", "prediction", "tracking", "update", ...) to its duration in
    seconds at each frame. A phase with no sample gets NaN (null in ``metrics.json``).
    """
    summary = {}
    for phase, samples in per_frame.items():
        stats = TimingStats.from_seconds(samples)
        summary[phase] = {"median_ms": stats.median_ms, "p95_ms": stats.p95_ms, "mean_ms": stats.mean_ms}
    return summary
