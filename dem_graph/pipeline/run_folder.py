"""The run folder (``dem-graph run DATASET --estimator NAME --out RUN``): writing it, and reading it back.

::

    RUN/
      trajectory.tum         the estimated T_world_body at camera times (TUM, readable by evo)
      trajectory_<name>.tum  another estimate of every frame's pose (isam2: ``smoothed``; isam2-batch: ``online``)
      points.ply             every map point ever estimated, with its variances and kind (binary PLY)
      poses.npz              the poses the DEM was made from, with their covariances
      metrics.json           accuracy and timing numbers (pretty, sorted keys, NaN and infinities as null)
      config.yaml            the configuration the run used
      rig.yaml               the rig the run used, whole (a bag's derived rig included): ``--rig`` reads it back
      dem.tif, dem.npz, dem.png, cloud.ply   the run's DEM (:func:`write_dem_outputs`)
      local_dem_error.csv    with ground truth: the Fig. 8 measure frame by frame, in hindsight
      live_map.tif           the map as it was built while the run went (GeoTIFF, layers as dem.tif's)
      live_maps.nc           every k-th frame's local map as the guidance had it (netCDF: time x y x x)
      live_maps.part         the same maps while the run goes, appended as saved; the run's end turns it
                             into live_maps.nc, and after a kill it is read in its place (:mod:`dem_graph.io.live_maps`)
      live_dem_error.csv     with ground truth: the Fig. 8 measure on the live map, frame by frame

Reading back: :func:`read_run_metrics`, :func:`run_folder_config`, :func:`load_run_poses`,
:func:`load_run_points`, and :func:`run_folder_dem` (the DEM made again from the saved poses).
"""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import yaml
from pydantic import ValidationError

from dem_graph.config_types import format_validation_error
from dem_graph.datasets.base import Sequence
from dem_graph.datasets.open import reopen_dataset
from dem_graph.dem.layers import Dem
from dem_graph.dem.returns import GroundReturns, PoseTrack, map_point_returns
from dem_graph.dem.views import to_local
from dem_graph.errors import ConfigError, DatasetError, DemGraphError
from dem_graph.evaluation.dem_metrics import LocalErrorSeries
from dem_graph.geometry.rig import SensorRig, rig_to_dict
from dem_graph.geometry.trajectory import Trajectory
from dem_graph.io.dem_files import write_cloud_ply, write_dem_geotiff, write_dem_npz
from dem_graph.io.live_maps import LIVE_MAPS_NC, live_map_at, live_maps_part_path
from dem_graph.io.npz import read_npz
from dem_graph.io.ply import read_points_ply, write_points_ply
from dem_graph.io.tum import write_tum
from dem_graph.pipeline.config import RunConfig, run_config
from dem_graph.pipeline.live_run import LiveRun
from dem_graph.pipeline.result import RunResult
from dem_graph.pipeline.run_dem import RunDem, focus_local_dem, ground_returns, make_run_dem, pose_track_from_result, require_time
from dem_graph.viz.dem_figure import write_dem_png

TRAJECTORY_TUM = "trajectory.tum"
METRICS_JSON = "metrics.json"
CONFIG_YAML = "config.yaml"
RIG_YAML = "rig.yaml"
POSES_NPZ = "poses.npz"
POINTS_PLY = "points.ply"
LOCAL_ERROR_CSV = "local_dem_error.csv"
LIVE_MAP_TIF = "live_map.tif"
LIVE_ERROR_CSV = "live_dem_error.csv"
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


RUN_FILES = (TRAJECTORY_TUM, METRICS_JSON, CONFIG_YAML, POSES_NPZ, POINTS_PLY)


def prepare_run_folder(out_dir: str | Path, overwrite: bool = False) -> Path:
    """Make ``out_dir`` ready for a run before any estimating: created if needed and checked
    writable. A folder holding an earlier run (any of :data:`RUN_FILES`) is refused unless
    ``overwrite``, which empties it first, so that no file of the earlier run can pass for this
    one's. A folder holding other files is never emptied. :class:`DatasetError` naming the folder."""
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise DatasetError(out, "is a file, not a folder: give --out a folder")
    if out.is_dir():
        entries = sorted(out.iterdir())
        earlier = [e.name for e in entries if e.name in RUN_FILES]
        if entries and not earlier:
            raise DatasetError(
                out, f"holds {len(entries)} files that are not a run's ({entries[0].name}, ...): give an empty or new folder"
            )
        if earlier and not overwrite:
            raise DatasetError(out, f"holds an earlier run ({', '.join(earlier)}): give --overwrite to replace it, or another --out")
        for entry in entries if earlier else ():
            try:
                shutil.rmtree(entry) if entry.is_dir() and not entry.is_symlink() else entry.unlink()
            except OSError as exc:
                raise DatasetError(entry, f"cannot remove the earlier run's file ({exc.strerror or exc})") from None
    try:
        out.mkdir(parents=True, exist_ok=True)
        probe = out / ".dem_graph_write_test"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as exc:
        raise DatasetError(out, f"cannot write the run folder here ({exc.strerror or exc})") from None
    return out


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
    config_text = _config_text(config)

    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise DatasetError(out_dir, f"cannot create the run folder ({exc.strerror or exc})") from None

    paths = {
        "trajectory": out_dir / TRAJECTORY_TUM,
        "points": out_dir / POINTS_PLY,
        "metrics": out_dir / METRICS_JSON,
        "config": out_dir / CONFIG_YAML,
    }
    write_tum(paths["trajectory"], trajectory)
    write_points_ply(paths["points"], points_xyz, point_attributes or {})
    _write_text(paths["metrics"], metrics_text)
    _write_text(paths["config"], config_text)
    for name, extra in extras.items():
        paths[name] = out_dir / f"{name}.tum"
        write_tum(paths[name], extra)
    return paths


def _config_text(config: dict) -> str:
    try:
        return yaml.safe_dump(_plain(config, nan_to_none=False), sort_keys=False)
    except yaml.YAMLError as exc:
        raise DemGraphError(f"config cannot be written as YAML: {exc}") from None


def write_run_config(out_dir: str | Path, config: RunConfig) -> Path:
    """The run's ``config.yaml`` alone, as the run starts: the folder says what run it holds."""
    path = Path(out_dir) / CONFIG_YAML
    _write_text(path, _config_text(config.model_dump(mode="json")))
    return path


def write_run_rig(out_dir: str | Path, rig: SensorRig) -> Path:
    """The run's ``rig.yaml``: the rig the run used, every field, as :func:`~dem_graph.geometry.rig.load_rig` reads it."""
    path = Path(out_dir) / RIG_YAML
    _write_text(path, yaml.safe_dump(rig_to_dict(rig), sort_keys=False, default_flow_style=None))
    return path


def write_dem_outputs(out_dir: str | Path, dem: Dem, returns: GroundReturns | None = None, trajectory_xy: np.ndarray | None = None) -> dict[str, Path]:
    """Write ``dem.tif``, ``dem.npz``, ``dem.png`` and (with ``returns``) ``cloud.ply`` into ``out_dir``."""
    out = Path(out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise DatasetError(out, f"cannot create the folder ({exc.strerror or exc})") from None
    paths = {
        "dem_tif": write_dem_geotiff(out / "dem.tif", dem),
        "dem_npz": write_dem_npz(out / "dem.npz", dem),
        "dem_png": write_dem_png(out / "dem.png", dem, trajectory_xy),
    }
    if returns is not None:
        row, col, inside = dem.geometry.cell_index(returns.xyz_m[:, 0], returns.xyz_m[:, 1])
        ok = inside & np.all(np.isfinite(returns.xyz_m), axis=1) & np.isfinite(returns.var_z_m2)
        paths["cloud_ply"] = write_cloud_ply(out / "cloud.ply", returns.select(ok))
    return paths


LOCAL_ERROR_COLUMNS = ("t_s", "mean_m", "std_m", "relative_mean_m", "relative_std_m", "covered_fraction")


def write_local_error_csv(path: str | Path, series: LocalErrorSeries) -> Path:
    """Write the Fig. 8 series as CSV (:data:`LOCAL_ERROR_COLUMNS`, a header line, NaN where a
    frame had no data); :class:`DatasetError` naming the file if it cannot."""
    path = Path(path)
    table = np.column_stack([getattr(series, name) for name in LOCAL_ERROR_COLUMNS])
    try:
        np.savetxt(path, table, delimiter=",", header=",".join(LOCAL_ERROR_COLUMNS), comments="", fmt="%.9g")
    except OSError as exc:
        raise DatasetError(path, f"cannot write ({exc.strerror or exc})") from None
    return path


def write_run_dem(run_dem: RunDem, out_dir: str | Path) -> dict[str, Path]:
    """The DEM's files (and, with the Fig. 8 series, ``local_dem_error.csv``); a local map's cloud
    and path are in its local frame."""
    p = run_dem.poses.T_world_body[:, :3, 3]
    returns = run_dem.returns
    if run_dem.dem.frame == "local":
        T = run_dem.dem.meta["T_world_local"]
        p = (p[run_dem.poses.t_s <= run_dem.dem.meta["t_s"]] - T[:3, 3]) @ T[:3, :3]
        returns = to_local(returns, T)
    paths = write_dem_outputs(out_dir, run_dem.dem, returns, p[:, :2])
    if run_dem.local_series is not None:
        paths["local_dem_error"] = write_local_error_csv(Path(out_dir) / LOCAL_ERROR_CSV, run_dem.local_series)
    return paths


def save_run_poses(path: str | Path, poses: PoseTrack) -> Path:
    path = Path(path)
    try:
        with path.open("wb") as fh:
            np.savez_compressed(fh, t_s=poses.t_s, T_world_body=poses.T_world_body, covariance=poses.covariance)
    except OSError as exc:
        raise DatasetError(path, f"cannot write ({exc.strerror or exc})") from None
    return path


def load_run_poses(run_dir: str | Path) -> PoseTrack:
    path = Path(run_dir) / POSES_NPZ
    data = read_npz(path, ("t_s", "T_world_body", "covariance"), missing_hint="is this a run folder written by `dem-graph run`?")
    try:
        t, T, P = (np.asarray(data[k], dtype=float) for k in ("t_s", "T_world_body", "covariance"))
    except (TypeError, ValueError) as exc:
        raise DatasetError(path, f"an array is not numeric ({exc})") from None
    try:
        return PoseTrack(t, T, P)
    except DemGraphError as exc:  # the track's own checks: shapes, NaN, times not increasing
        raise DatasetError(path, str(exc)) from None


def load_run_points(run_dir: str | Path) -> GroundReturns:
    """The map points of a run folder's ``points.ply`` (positions, height variances, creation times)."""
    path = Path(run_dir) / POINTS_PLY
    xyz, attributes = read_points_ply(path)
    if "var_z_m2" not in attributes:
        raise DatasetError(path, "no var_z_m2 attribute: cannot weigh the map points")
    cov = np.zeros((len(xyz), 3, 3))
    cov[:, 2, 2] = attributes["var_z_m2"]
    created = attributes.get("created_t_s", np.zeros(len(xyz)))
    return map_point_returns(xyz, cov, created)


def read_run_metrics(run_dir: str | Path) -> dict:
    """A run folder's ``metrics.json``; an empty dict when it is absent, :class:`DatasetError` when unreadable."""
    path = Path(run_dir) / METRICS_JSON
    if not path.is_file():
        return {}
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise DatasetError(path, f"not a readable JSON file ({str(exc).splitlines()[0]})") from None
    if not isinstance(data, dict):
        raise DatasetError(path, "must hold a mapping")
    return data


def run_folder_config(run_dir: str | Path) -> RunConfig:
    """The configuration a run folder was made with (its ``config.yaml``), the defaults if it has none.
    It already holds the dataset's run settings, so none are layered under it."""
    path = Path(run_dir) / CONFIG_YAML
    return run_config(config_file=path) if path.is_file() else RunConfig()


def run_folder_dem(run_dir: str | Path, sequence: Sequence, at_s: float | None = None, config: RunConfig | None = None, local_errors: bool = False) -> RunDem:
    """The DEM of a run folder made again from its saved poses and map points and the dataset's scans:
    the global map, or with ``at_s`` the local map at that time over the focus area the guidance
    needs at the vehicle's speed then. ``config``: the run's (:func:`run_folder_config`).
    ``local_errors``: the global map's metrics also get the Fig. 8 measure, as a run's do (it
    needs the truth's elevation)."""
    config = config or RunConfig()
    poses = load_run_poses(run_dir)
    points = load_run_points(run_dir) if config.dem.map_points else None
    returns = ground_returns(sequence, poses, points)
    if at_s is None:
        half_width_m = config.frontend.focus.corridor_width_m / 2.0
        return make_run_dem(returns, poses, sequence.ground_truth, config.dem, half_width_m, local_errors=local_errors, local_error=config.local_error)
    return focus_local_dem(returns, poses, at_s, sequence.rig, config.frontend.focus, config.dem)


def require_run_folder(run_dir: str | Path) -> Path:
    """``run_dir`` as a path, once it is seen to be a run folder (it holds ``poses.npz``); a
    :class:`DatasetError` naming it otherwise (a dataset folder given for a run, say)."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise DatasetError(run_dir, "run folder not found" if not run_dir.exists() else "not a folder")
    if not (run_dir / POSES_NPZ).exists():
        raise DatasetError(run_dir, f"not a run folder written by `dem-graph run` (no {POSES_NPZ})")
    return run_dir


def remake_dem(run_dir: str | Path, dataset: str | Path | None = None, at_s: float | None = None, resolution_m: float | None = None) -> RunDem:
    """What ``dem-graph dem RUN`` makes: the run folder's DEM again (see :func:`run_folder_dem`), from
    the dataset it names (or ``dataset``) opened as the run opened it, with its configuration (the
    cell size ``resolution_m`` if given)."""
    run_dir = require_run_folder(run_dir)
    config = run_folder_config(run_dir)
    recorded = read_run_metrics(run_dir)
    if dataset is None:
        dataset = recorded.get("dataset")
        if not dataset:
            raise DatasetError(run_dir / METRICS_JSON, "names no dataset: give --dataset")
    if resolution_m is not None:
        try:
            config.dem.fusion.resolution_m = resolution_m
        except ValidationError as exc:
            raise ConfigError(f"invalid DEM resolution: {format_validation_error(exc)}") from None
    sequence = reopen_dataset(Path(dataset), recorded.get("dataset_options"))  # the run's KITTI ring, ...
    return run_folder_dem(run_dir, sequence, at_s, config)


def live_map_of_run(run_dir: str | Path, t_s: float) -> Dem:
    """The live local map a run saved last at or before ``t_s`` (``RUN/live_maps.nc``). A run that
    did not end (killed, or still going) has no ``live_maps.nc`` and may have no ``poses.npz`` yet:
    its maps are read from ``RUN/live_maps.part`` with a warning, and ``t_s`` is checked against
    the run's poses only if they were written."""
    run_dir = Path(run_dir)
    path = run_dir / LIVE_MAPS_NC
    if path.is_file() or not live_maps_part_path(path).is_file():
        run_dir = require_run_folder(run_dir)
        if not path.is_file():
            raise DatasetError(path, "not found: the run saved no live map (an older run, or live_map.save_every_n_frames: 0); --hindsight makes one from its poses")
    if (run_dir / POSES_NPZ).exists():
        require_time(load_run_poses(run_dir), t_s)
    return live_map_at(path, t_s)


def write_run(run: RunResult, out_dir: str | Path) -> dict[str, Path]:
    """Write the whole run folder (see the module); returns the written paths by name."""
    res = run.estimator
    pts = res.points.arrays()
    cov = pts["covariance"]
    attributes = {
        "point_id": pts["point_id"],
        "kind": pts["kind"],
        "var_x_m2": cov[:, 0, 0].astype(np.float32),
        "var_y_m2": cov[:, 1, 1].astype(np.float32),
        "var_z_m2": cov[:, 2, 2].astype(np.float32),
        "n_tracked": pts["n_tracked"],
        "created_t_s": pts["created_t_s"],
    }
    if not res.frames:
        raise DemGraphError("the run produced no pose: nothing to write")
    paths = write_run_outputs(out_dir, res.trajectory(), pts["xyz"], attributes, run.metrics.to_json_dict(), run.config.model_dump(mode="json"), res.extra_trajectories())
    poses = run.dem.poses if run.dem is not None else pose_track_from_result(res)
    paths["poses"] = save_run_poses(Path(out_dir) / POSES_NPZ, poses)
    if run.dem is not None:
        paths.update(write_run_dem(run.dem, out_dir))
    if run.live is not None:
        paths.update(write_live_outputs(run.live, out_dir))
    return paths


def write_live_outputs(live: LiveRun, out_dir: str | Path) -> dict[str, Path]:
    """The live map's files: the map as built (``live_map.tif``), the saved local maps
    (``live_maps.nc``) and, with truth, its Fig. 8 measure frame by frame (``live_dem_error.csv``)."""
    out_dir = Path(out_dir)
    paths = {}
    if live.final_map is not None:
        paths["live_map"] = write_dem_geotiff(out_dir / LIVE_MAP_TIF, live.final_map)
    if live.recorder is not None:
        written = live.recorder.write(out_dir / LIVE_MAPS_NC)
        if written is not None:
            paths["live_maps"] = written
    if live.meter is not None and live.meter.times:
        paths["live_dem_error"] = write_local_error_csv(out_dir / LIVE_ERROR_CSV, live.meter.series())
    return paths


__all__ = [
    "CONFIG_YAML",
    "LIVE_MAPS_NC",
    "LOCAL_ERROR_COLUMNS",
    "METRICS_JSON",
    "POSES_NPZ",
    "TRAJECTORY_TUM",
    "json_text",
    "RUN_FILES",
    "live_map_of_run",
    "load_run_points",
    "load_run_poses",
    "prepare_run_folder",
    "read_run_metrics",
    "remake_dem",
    "require_run_folder",
    "run_folder_config",
    "run_folder_dem",
    "save_run_poses",
    "write_dem_outputs",
    "write_json",
    "write_live_outputs",
    "write_local_error_csv",
    "write_run",
    "write_run_dem",
    "write_run_config",
    "write_run_outputs",
]
