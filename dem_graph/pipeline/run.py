"""Running an estimator over a dataset: the loop, its metrics and its DEM.

``run_estimator`` owns the loop over a :class:`Sequence` (the estimators only see events). If the
loop fails part way (a corrupt image late in a log, frames out of time order), what was estimated
so far is still returned, with the error, so :func:`~dem_graph.pipeline.run_folder.write_run` can
save it.

:func:`run_dataset` is what ``dem-graph run`` runs, as one call for a notebook: open the dataset,
layer the configuration (:func:`~dem_graph.pipeline.config.run_config`), run, write the run folder.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Iterator
from pathlib import Path

from threadpoolctl import threadpool_limits

from dem_graph.datasets.base import Sequence
from dem_graph.datasets.events import CameraFrame, ImuSample, LaserScan, Odometry
from dem_graph.datasets.open import DatasetOptions, open_dataset
from dem_graph.errors import DemGraphError, one_line
from dem_graph.estimators.base import Estimator
from dem_graph.pipeline.checkpoint import RunCheckpoint, StopRequest, stop_at_event_boundaries
from dem_graph.pipeline.config import RunConfig, RunOverrides, run_config
from dem_graph.pipeline.derived import DEFAULT_NOMINAL_SPEED_MPS
from dem_graph.pipeline.live import LivePipeline
from dem_graph.pipeline.live import make_estimator as make_estimator_for
from dem_graph.pipeline.live_run import LiveRun
from dem_graph.pipeline.live_view import ViewerListener, ViewerOptions
from dem_graph.pipeline.metrics import compute_metrics
from dem_graph.pipeline.result import RunResult
from dem_graph.pipeline.run_dem import DemFailure, RunDem, dem_from_result, make_run_dem
from dem_graph.pipeline.run_folder import prepare_run_folder, write_run, write_run_config, write_run_rig
from dem_graph.progress import progress

log = logging.getLogger(__name__)


def make_estimator(sequence: Sequence, config: RunConfig) -> Estimator:
    """``config``'s estimator for ``sequence`` (its rig, start and odometry)."""
    return make_estimator_for(sequence.rig, sequence.T_world_body_initial, sequence.t_start_s, sequence.has_odometry, config)


# A run at the camera's rate does the pipeline's idle work (the last frame's keyframe work, the graph's
# results, the live map moved with them: 5-6 ms median on a `paper` run, docs/isam2_design.md) while it
# waits for an event, when the next camera frame is due at least this long after now, so that the work
# does not make the frame late.
IDLE_MIN_WAIT_S = 0.010


def feed(
    estimator: Estimator | LivePipeline,
    sequence: Sequence,
    max_frames: int | None = None,
    finish: bool = True,
    realtime: bool = False,
    stop: StopRequest | None = None,
) -> Iterator[int]:
    """Give the sequence's events to ``estimator`` in time order (with a progress bar), up to
    ``max_frames`` camera frames, then call its ``finish`` (unless ``finish`` is false). Yields the
    number of camera frames given so far after each one. With ``realtime`` an event is given no
    sooner than its time after the first event's has passed on the wall clock (an estimator that
    falls behind gets the next one at once, as from a sensor's buffer), and while it waits, with the
    next camera frame at least ``IDLE_MIN_WAIT_S`` away (one camera interval after the last), its
    ``idle`` work is done. ``stop``: checked before
    each event (KeyboardInterrupt once a stop was asked for)."""
    frames = 0
    t0_s = wall0_s = None
    last_frame_t_s, next_frame_t_s = None, -math.inf  # no idle work until the camera's interval is known
    for event in progress(sequence.events(), total=sequence.event_count(), desc=estimator.name, unit="event"):
        if stop is not None:
            stop.check()
        if realtime:
            if t0_s is None:
                t0_s, wall0_s = event.t_s, time.perf_counter()
            elapsed_s = time.perf_counter() - wall0_s
            wait_s = event.t_s - t0_s - elapsed_s
            if wait_s > 0 and next_frame_t_s - t0_s - elapsed_s >= IDLE_MIN_WAIT_S and estimator.idle():
                wait_s = event.t_s - t0_s - (time.perf_counter() - wall0_s)
            if wait_s > 0:
                time.sleep(wait_s)
        if isinstance(event, CameraFrame):
            if last_frame_t_s is not None and event.t_s > last_frame_t_s:  # the next frame expected one interval on
                next_frame_t_s = 2 * event.t_s - last_frame_t_s
            last_frame_t_s = event.t_s
            estimator.on_frame(event)
            frames += 1
            yield frames
            if max_frames and frames >= max_frames:
                break
        elif isinstance(event, LaserScan):
            estimator.on_scan(event)
        elif isinstance(event, Odometry):
            estimator.on_odometry(event)
        elif isinstance(event, ImuSample):
            estimator.on_imu(event)
    if finish:
        estimator.finish()


def with_dataset_speed(sequence: Sequence, config: RunConfig) -> RunConfig:
    """``config``, its starting speed replaced by the dataset's own estimate (``initial_speed_mps``)
    when ``motion.initial_speed_from_dataset`` asks for it and the dataset has one (and the focus
    area's speed before the estimator has measured one, where it is left at its default)."""
    if not config.motion.initial_speed_from_dataset or config.motion.uses_odometry(sequence.has_odometry):
        return config
    speed = sequence.initial_speed_mps
    if speed is None:
        log.warning("the dataset gives no starting speed: starting at %.2f m/s (motion.initial_speed_mps)", config.motion.initial_speed_mps)
        return config
    config = config.model_copy(deep=True)
    config.motion.initial_speed_mps = float(speed)
    if config.frontend.focus.nominal_speed_mps == DEFAULT_NOMINAL_SPEED_MPS and abs(float(speed)) > 0:  # the focus area's first frames, as vehicle.speed_mps would set it
        config.frontend.focus.nominal_speed_mps = abs(float(speed))
    return config


def run_estimator(
    sequence: Sequence,
    config: RunConfig | None = None,
    with_dem: bool = True,
    viewer: ViewerOptions | None = None,
    checkpoint_dir: str | Path | None = None,
    instrument: Callable[[LivePipeline], object] | None = None,
) -> RunResult:
    """Run ``config``'s estimator over ``sequence`` in a :class:`LivePipeline` (the live map built as
    the events come, measured against the truth as the guidance had it), then make the run's
    metrics and its DEM from the final poses. ``viewer``: show it in rerun as it goes, or record it.
    ``checkpoint_dir``: the run folder, where the trajectory and map points so far are kept current
    every ``config.checkpoint_every_s`` (:mod:`~dem_graph.pipeline.checkpoint`) and the saved live
    maps are appended as they are saved (:mod:`~dem_graph.io.live_maps`). ``instrument``: called
    with the pipeline before the first event, for studies that change what a part sees
    (:class:`~dem_graph.studies.ablation.TrueTracks`).

    Ctrl-C, SIGTERM (main thread) or an error part way stops the loop, not the run: what was
    estimated up to there is returned with ``error`` saying why, and its metrics and DEM are made.

    ``config`` is taken as it is (make it with :func:`~dem_graph.pipeline.config.run_config` to
    have the dataset's own run settings under it); None: the defaults with the dataset's settings,
    as ``dem-graph run`` would without options."""
    config = with_dataset_speed(sequence, config or run_config(sequence))
    # a Ctrl-C or SIGTERM while the estimator starts (its kernels loaded, its graph process started)
    # stops the run at its first event, as one during the run does at the next
    with stop_at_event_boundaries() as stop:
        pipeline = LivePipeline.for_sequence(sequence, config, strict_order=True)
        if instrument is not None:
            instrument(pipeline)
        live = LiveRun.attach(pipeline, sequence.ground_truth, config.local_error, run_dir=checkpoint_dir)
        shown = ViewerListener(pipeline, viewer, sequence.ground_truth) if viewer is not None else None
        if shown is not None:
            pipeline.listeners.append(shown)
        checkpoint = RunCheckpoint(pipeline, checkpoint_dir, config.checkpoint_every_s) if checkpoint_dir is not None else None
        if checkpoint is not None:
            pipeline.listeners.append(checkpoint)
        start = time.perf_counter()
        error, interrupted = None, False
        frames = 0
        try:
            with threadpool_limits(limits=config.blas_threads, user_api="blas"):
                for frames in feed(pipeline, sequence, config.max_frames, realtime=config.realtime, stop=stop):  # noqa: B007 - read in the handler below
                    pass
        except DemGraphError as exc:
            error = str(exc)
            log.error("run stopped after %d frames: %s", frames, exc)
        except KeyboardInterrupt as exc:
            interrupted = True
            error = f"interrupted after {frames} frames ({str(exc) or 'Ctrl-C'})"
            log.error("run %s: keeping what was done", error)
        except Exception as exc:  # noqa: BLE001 - a fault late in a long run must not lose the run
            error = f"stopped after {frames} frames by an internal error: {type(exc).__name__}: {one_line(exc)}"
            log.error("run %s (please report it; -vv shows where)", error)
            log.debug("internal error", exc_info=True)
    if shown is not None:
        shown.close()
    try:
        result = pipeline.result()
    except Exception as exc:  # a second Ctrl-C inside a frame tears the estimator's state
        where = f": {checkpoint_dir} keeps the trajectory and map points of the last checkpoint" if checkpoint_dir is not None else ""
        raise DemGraphError(
            f"the run's results could not be gathered after it stopped ({error}; {type(exc).__name__}: {one_line(exc)}){where}"
        ) from None
    run = RunResult(result, config, error=error, interrupted=interrupted, elapsed_s=time.perf_counter() - start, live=live)
    run.metrics = compute_metrics(sequence, result, error, run.elapsed_s)
    if result.frames:
        run.metrics.live_map = live.metrics()
    if with_dem and result.frames:
        run.dem = run_dem(run, sequence)
    return run


def run_dem(run: RunResult, sequence: Sequence) -> RunDem | None:
    """The run's DEM and its metrics (into ``run.metrics.dem``); a failure is logged, the run kept."""
    try:
        returns, poses = dem_from_result(run.estimator, sequence, run.config.dem)
        half_width = run.config.frontend.focus.corridor_width_m / 2.0
        dem = make_run_dem(
            returns, poses, sequence.ground_truth, run.config.dem, corridor_half_width_m=half_width, local_error=run.config.local_error
        )
    except DemGraphError as exc:
        log.warning("no DEM for this run: %s", exc)
        run.metrics.dem = DemFailure(error=str(exc))
        return None
    run.metrics.dem = dem.metrics
    return dem


def run_dataset(
    dataset: str | Path | Sequence,
    overrides: RunOverrides | None = None,
    config_file: str | Path | None = None,
    out_dir: str | Path | None = None,
    dataset_options: DatasetOptions | None = None,
    fmt: str | None = None,
    viewer: ViewerOptions | None = None,
    overwrite: bool = False,
) -> RunResult:
    """What ``dem-graph run DATASET`` runs: the dataset opened (a folder, KITTI or a ROS bag, told from
    the path unless ``fmt``; or a :class:`Sequence` already open), its configuration layered
    (defaults < the dataset's run settings < ``config_file`` < ``overrides``), the estimator run,
    and, with ``out_dir``, the run folder written (``result.paths``); ``viewer``: shown or recorded in rerun. A run that stopped early
    (``result.error``: an error, Ctrl-C or SIGTERM) is written too, up to where it stopped.

    ``out_dir`` is made ready before any estimating (:func:`~dem_graph.pipeline.run_folder.prepare_run_folder`:
    writable, and an earlier run in it refused unless ``overwrite``), and is kept current as the run goes."""
    if isinstance(dataset, Sequence):
        sequence, where = dataset, getattr(dataset, "path", None)
    else:
        sequence, where = open_dataset(dataset, fmt, dataset_options), dataset
    config = run_config(sequence, config_file, overrides)
    if out_dir is not None:
        prepare_run_folder(out_dir, overwrite)
        write_run_config(out_dir, config)
        rig_path = write_run_rig(out_dir, sequence.rig)
    result = run_estimator(sequence, config, viewer=viewer, checkpoint_dir=out_dir)
    if where is not None:
        result.metrics.dataset = str(Path(where).resolve())
    result.metrics.dataset_options = sequence.open_options()
    if out_dir is not None:
        result.paths = {**write_run(result, out_dir), "rig": rig_path}
    return result


__all__ = ["RunResult", "feed", "make_estimator", "run_dataset", "run_dem", "run_estimator", "with_dataset_speed"]
