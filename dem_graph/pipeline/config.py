"""The run's configuration and its layering, in one place.

A run's settings come from four layers, each over the one before (:func:`run_config`):

1. the defaults of :class:`RunConfig`;
2. the dataset's own run settings (:meth:`Sequence.run_settings`: KITTI brings a car's);
3. the user's YAML file (``--config``; a run folder's ``config.yaml`` is one; ``dem-graph config``
   writes the defaults as one). A value in it that restates a default where the dataset brings its
   own setting leaves the dataset's in place (:func:`without_restated_defaults`): only a value that
   differs from the default wins over a dataset's setting;
4. explicit overrides (:class:`RunOverrides`: the command line's flags).

Then, with a dataset, the settings the vehicle's speed and the camera's frame rate decide
(``frontend.tracker.max_search_half_size_px``, ``frontend.focus.nominal_speed_mps``) are derived
from ``vehicle.speed_mps`` and the rig where they still hold their default value
(:mod:`dem_graph.pipeline.derived`): a value given in any layer wins.

``dem-graph run`` and :func:`dem_graph.pipeline.run.run_dataset` both build their configuration
here, so a notebook and the command line run the same thing.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import yaml
from pydantic import Field, ValidationError

from dem_graph.config_types import StrictModel, format_validation_error
from dem_graph.datasets.base import Sequence
from dem_graph.dem.fusion import FusionConfig
from dem_graph.errors import ConfigError
from dem_graph.estimators.ekf import EkfOptions
from dem_graph.estimators.isam2 import Isam2Options
from dem_graph.estimators.settings import SharedSettings
from dem_graph.evaluation.dem_metrics import LocalErrorConfig
from dem_graph.pipeline.derived import derive_from_vehicle

log = logging.getLogger(__name__)

EstimatorName = Literal["gm", "ptpm", "isam2", "isam2-batch", "odometry"]
ESTIMATORS: tuple[str, ...] = ("gm", "ptpm", "isam2", "isam2-batch")
"""The estimators proper; ``odometry`` (the odometry integrated alone) is the baseline beside them."""


class DemConfig(StrictModel):
    """The dense DEM a run makes from its poses."""

    fusion: FusionConfig = Field(default_factory=FusionConfig, description="per-cell fusion and the grid")
    map_points: bool = Field(True, description="fuse the estimator's map points along with every laser return")
    traversability_window: int = Field(3, ge=3, description="cells on a side of the slope / step / roughness window (odd)")
    local_history_s: float = Field(10.0, gt=0, description="a local DEM fuses the measurements of this many seconds before its time")


class LiveMapConfig(StrictModel):
    """The map built while the run goes (:class:`~dem_graph.pipeline.live.LivePipeline`); its cells
    and gate are ``dem.fusion``'s."""

    revision_window_s: float = Field(
        2.0, gt=0, description="scans this recent are moved when their poses are revised; older ones are frozen (bounds the cost of a revision)"
    )
    tolerance_m: float = Field(1e-3, ge=0, description="a scan is moved when its pose moved more than this, metres ...")
    tolerance_rad: float = Field(1e-4, ge=0, description="... or turned more than this, radians")
    tile_cells: int = Field(32, ge=1, description="cells on a side of one tile of the map (tiles are made where measurements land)")
    gate_min_count: int = Field(3, ge=1, description="a cell gates new measurements once it holds this many")
    save_every_n_frames: int = Field(10, ge=0, description="the run folder's live_maps.nc keeps every this many frames' local map (0: none)")
    save_x_range_m: tuple[float, float] = Field((0.0, 8.0), description="the saved local maps' window ahead of the body origin, metres (from, to)")
    save_width_m: float = Field(6.0, gt=0, description="the saved local maps' width, metres")
    camera_silent_s: float = Field(1.0, gt=0, description="warn when no camera frame has come for this long (the map goes on with extrapolated poses)")
    laser_silent_s: float = Field(2.0, gt=0, description="warn when no laser scan with a return has come for this long (no laser return reaches the map; its cells age)")
    odometry_silent_s: float = Field(0.5, gt=0, description="warn when a log with odometry has none for this long (the motion is predicted at constant velocity)")


class VehicleConfig(StrictModel):
    """The vehicle, as far as the settings derived from it need (:mod:`dem_graph.pipeline.derived`)."""

    speed_mps: float = Field(
        1.5,
        gt=0,
        description="the vehicle's usual speed, m/s: with the camera's frame rate it sets frontend.tracker.max_search_half_size_px and "
        "frontend.focus.nominal_speed_mps where those are left at their defaults (the defaults suit 1.5 m/s at 25 Hz)",
    )


class RunConfig(SharedSettings):
    """A run: which estimator, the settings all estimators share (front end, motion model, false
    matches), each estimator's own options, the DEM and the Fig. 8 measure."""

    estimator: EstimatorName = Field("ptpm", description="which estimator")
    vehicle: VehicleConfig = Field(default_factory=VehicleConfig, description="the vehicle: what the settings its speed decides are derived from")
    ekf: EkfOptions = Field(default_factory=EkfOptions, description="EKF baselines (gm, ptpm)")
    isam2: Isam2Options = Field(default_factory=Isam2Options, description="the graph estimator (isam2, isam2-batch)")
    max_frames: int | None = Field(None, ge=1, description="stop after this many camera frames")
    realtime: bool = Field(
        False,
        description="give each event to the estimator when its time since the first event has passed on the wall clock, as the sensors would on the "
        "vehicle; false: as fast as the estimator takes them. Matters with isam2.graph_process, whose graph then keeps up as it would live",
    )
    checkpoint_every_s: float = Field(
        10.0, gt=0, description="wall-clock seconds between writes of the trajectory and map points so far into the run folder (what Ctrl-C, a kill or a late fault keeps)"
    )
    blas_threads: int = Field(1, ge=1, description="threads numpy's linear algebra may use while the estimator runs (the matrices are small; README, Benchmarks: one thread against two)")
    dem: DemConfig = Field(default_factory=DemConfig, description="the dense DEM made from the run's poses")
    local_error: LocalErrorConfig = Field(default_factory=LocalErrorConfig, description="the Fig. 8 measure: the local DEM's error ahead of the vehicle (with truth)")
    live_map: LiveMapConfig = Field(default_factory=LiveMapConfig, description="the map built while the run goes, the one the guidance steers by")


GRAPH_ESTIMATORS: tuple[str, ...] = ("isam2", "isam2-batch")
"""The estimators that read the ``isam2`` section (the EKF baselines ignore it)."""

GRAPH_PROCESS = "isam2-process"
"""The name (``run``, the bench, studies) of ``isam2`` with ``isam2.graph_process``: its graph in a second process."""


def split_graph_process(name: str) -> tuple[str, bool]:
    """``(estimator, graph_process)`` of an estimator's name: :data:`GRAPH_PROCESS` is ``("isam2", True)``,
    any other name ``(name, False)``."""
    return ("isam2", True) if name == GRAPH_PROCESS else (name, False)


@dataclass
class RunOverrides:
    """Values set over the configuration file: what the command line's flags set. None (or False)
    leaves the layer below in place."""

    estimator: EstimatorName | None = None
    max_frames: int | None = None
    max_points: int | None = None  # frontend.max_points
    no_odometry: bool = False  # motion.model: constant_velocity
    no_imu: bool = False  # motion.use_imu: false
    lag_s: float | None = None  # isam2.lag_s
    keyframe_every: int | None = None  # isam2.keyframe_every; for isam2-batch, its online pass's (batch_keyframe_every)
    graph_process: bool = False  # isam2.graph_process
    realtime: bool = False

    def graph_only(self) -> list[str]:
        """The command-line flags of the values set here that only the graph estimators
        (:data:`GRAPH_ESTIMATORS`) read: what ``gm`` and ``ptpm`` would silently ignore."""
        given = (("--lag-s", self.lag_s is not None), ("--keyframe-every", self.keyframe_every is not None), ("--graph-process", self.graph_process))
        return [flag for flag, set_ in given if set_]

    def apply(self, config: RunConfig) -> RunConfig:
        """Set the given values on ``config`` (validated on assignment) and return it."""
        if self.estimator is not None:
            config.estimator = self.estimator
        if self.max_frames is not None:
            config.max_frames = self.max_frames
        if self.max_points is not None:
            config.frontend.max_points = self.max_points
        if self.no_odometry:
            config.motion.model = "constant_velocity"
        if self.no_imu:
            config.motion.use_imu = False
        if self.lag_s is not None:
            config.isam2.lag_s = self.lag_s
        if self.keyframe_every is not None:  # the batch's online pass has its own spacing
            if config.estimator == "isam2-batch":
                config.isam2.batch_keyframe_every = self.keyframe_every
            else:
                config.isam2.keyframe_every = self.keyframe_every
        if self.graph_process:
            config.isam2.graph_process = True
        if self.realtime:
            config.realtime = True
        return config


def merge_settings(base: dict, over: dict) -> dict:
    """``base`` with ``over``'s values in its place, key by key down nested mappings."""
    out = dict(base)
    for key, value in over.items():
        out[key] = merge_settings(out[key], value) if isinstance(value, dict) and isinstance(out.get(key), dict) else value
    return out


def without_restated_defaults(given: dict, dataset: dict, defaults: dict, prefix: str = "") -> tuple[dict, list[str]]:
    """``given`` (a configuration file's mapping) without the values that restate a default where
    ``dataset`` (a dataset's run settings) sets the key, and the dotted names of those left out: a
    file that restates the defaults (``dem-graph config``) leaves a dataset's own settings in place,
    a value that differs from the default wins over them."""
    out, kept = {}, []
    for key, value in given.items():
        name = f"{prefix}{key}"
        if key in dataset and isinstance(value, dict) and isinstance(dataset[key], dict) and isinstance(defaults.get(key), dict):
            out[key], inner = without_restated_defaults(value, dataset[key], defaults[key], name + ".")
            kept += inner
        elif key in dataset and key in defaults and _same(value, defaults[key]):
            kept.append(name)
        else:
            out[key] = value
    return out, kept


def _same(a, b) -> bool:
    """Equal as YAML values (a tuple and a list of the same items are)."""
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    if isinstance(a, bool) or isinstance(b, bool):
        return a is b
    return a == b


# the Fig. 8 window's settings sat under ``dem`` before they had a section of their own
_MOVED_TO_LOCAL_ERROR = {"local_start_m": "start_m", "local_length_m": "length_m", "local_width_m": "width_m", "local_every_n_frames": "every_n_frames"}


def _upgrade(data: dict, path: Path) -> dict:
    dem = data.get("dem")
    if not isinstance(dem, dict) or not any(k in dem for k in _MOVED_TO_LOCAL_ERROR):
        return data
    data, dem = dict(data), dict(dem)
    local_error = dict(data.get("local_error") or {})
    for old, new in _MOVED_TO_LOCAL_ERROR.items():
        if old in dem:
            local_error.setdefault(new, dem.pop(old))
    log.info("%s: dem.local_* read as local_error.* (the Fig. 8 window's section)", path)
    data["dem"], data["local_error"] = dem, local_error
    return data


def read_config_file(path: str | Path) -> dict:
    """The mapping in a YAML run configuration; :class:`ConfigError` naming the file if it cannot be read."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError("configuration file not found", path)
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except (yaml.YAMLError, OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"cannot read the configuration ({str(exc).splitlines()[0]})", path) from None
    if not isinstance(data, dict):
        raise ConfigError("a run configuration must be a mapping", path)
    return _upgrade(data, path)


def configured_estimator(config_file: str | Path | None, overrides: RunOverrides | None = None) -> str:
    """The estimator a run will use, before its dataset is open: the override's, else the
    configuration file's, else the default (no dataset's run settings choose one)."""
    if overrides is not None and overrides.estimator is not None:
        return overrides.estimator
    return run_config(None, config_file).estimator


def run_config(sequence: Sequence | None = None, config_file: str | Path | None = None, overrides: RunOverrides | None = None) -> RunConfig:
    """The run configuration: the defaults, then ``sequence``'s own run settings, then the YAML
    file ``config_file``, then ``overrides``; then, with a ``sequence``, the settings its rig and
    ``vehicle.speed_mps`` decide where they are left at their defaults (:func:`derive_from_vehicle`,
    logged in one line). A wrong value anywhere is a :class:`ConfigError`."""
    data: dict = sequence.run_settings() if sequence is not None else {}
    path = Path(config_file) if config_file is not None else None
    if path is not None:
        given = read_config_file(path)
        if data:
            given, kept = without_restated_defaults(given, data, RunConfig().model_dump(mode="json"))
            if kept:
                log.info("%s: %d values restate a default where the dataset brings its own setting: the dataset's kept (%s)", path, len(kept), ", ".join(kept))
        data = merge_settings(data, given)
    try:
        config = RunConfig.model_validate(data)
        if overrides is not None:
            overrides.apply(config)
    except ValidationError as exc:
        raise ConfigError(f"invalid run configuration: {format_validation_error(exc)}", path) from None
    if sequence is not None:
        log.info("settings %s", derive_from_vehicle(config, sequence.rig).text())
    return config


__all__ = ["DemConfig", "ESTIMATORS", "GRAPH_ESTIMATORS", "configured_estimator", "EstimatorName", "GRAPH_PROCESS", "LiveMapConfig", "RunConfig", "RunOverrides", "VehicleConfig", "merge_settings", "read_config_file", "run_config", "split_graph_process", "without_restated_defaults"]
