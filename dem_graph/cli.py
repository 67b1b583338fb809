"""The ``dem-graph`` command line: one thin command per library function.

Library errors (:class:`DemGraphError`) become a one-line message on stderr and exit code 2.
"""

from __future__ import annotations

import functools
import logging
import sys
from pathlib import Path

import click

from dem_graph.errors import DemGraphError


def _friendly_errors(fn):
    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except DemGraphError as exc:
            click.echo(f"dem-graph: error: {exc}", err=True)
            sys.exit(2)
        except KeyboardInterrupt:
            click.echo("dem-graph: interrupted", err=True)
            sys.exit(130)

    return wrapper


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.option("-v", "--verbose", count=True, help="More log output (-v info, -vv debug).")
@click.option("--no-progress", is_flag=True, help="Hide progress bars.")
@click.version_option(package_name="dem-graph")
def main(verbose: int, no_progress: bool) -> None:
    """Camera + single-line laser SLAM and dense Digital Elevation Maps."""
    level = logging.WARNING if verbose == 0 else logging.INFO if verbose == 1 else logging.DEBUG
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s")
    if no_progress:
        from dem_graph.progress import set_progress_enabled

        set_progress_enabled(False)


@main.command()
def scenarios() -> None:
    """List the built-in simulation scenarios."""
    from dem_graph.sim.scenarios import DEFAULT_SCENARIO, describe_scenarios

    for name, text in describe_scenarios().items():
        mark = " (default)" if name == DEFAULT_SCENARIO else ""
        click.echo(f"{name:8s} {text}{mark}")


@main.command()
@click.option("--scenario", "scenario_name", default=None, help="Scenario name (see `dem-graph scenarios`); default: demo.")
@click.option("--seed", type=int, default=None, help="Random seed; the same seed gives the same dataset.")
@click.option("--length-m", type=float, default=None, help="Distance to drive, metres.")
@click.option("--speed-mps", type=float, default=None, help="Mean speed, m/s.")
@click.option("--no-odometry", is_flag=True, help="Leave wheel odometry out of the dataset.")
@click.option("--no-imu", is_flag=True, help="Leave the IMU (gyroscope and accelerometer, imu.npz) out of the dataset.")
@click.option("--out", "out_dir", required=True, type=click.Path(file_okay=False, path_type=Path), help="Output dataset folder.")
@click.option("--overwrite", is_flag=True, help="Replace an existing output folder.")
@_friendly_errors
def simulate(scenario_name, seed, length_m, speed_mps, no_odometry, no_imu, out_dir, overwrite) -> None:
    """Simulate a scenario and write it as a dataset folder, with a preview picture."""
    from dem_graph.sim.pipeline import simulate as run
    from dem_graph.sim.scenarios import DEFAULT_SCENARIO, scenario

    config = scenario(
        scenario_name or DEFAULT_SCENARIO, seed=seed, length_m=length_m, speed_mps=speed_mps, with_odometry=False if no_odometry else None,
        with_imu=False if no_imu else None,
    )
    result = run(config, out_dir, overwrite=overwrite)
    click.echo(
        f"simulated '{config.name}' (seed {config.seed}): {result.length_m:.1f} m in {result.duration_s:.1f} s, "
        f"{result.n_frames} frames, {result.n_scans} laser scans, {result.n_odometry} odometry increments, {result.n_imu} IMU samples "
        f"({result.elapsed_s:.1f} s of computing)"
    )
    click.echo(f"dataset: {result.out_dir}")
    if result.preview_png:
        click.echo(f"picture: {result.preview_png}")


def _dataset_options_of(options: dict):
    from dem_graph.datasets.open import DatasetOptions

    return DatasetOptions(**{k: v for k, v in options.items() if v is not None})


def _open_dataset(path: Path, fmt: str | None = None, **options):
    """The dataset at ``path``: a dataset folder, KITTI (either layout) or a ROS bag (told from the path unless ``fmt``)."""
    from dem_graph.datasets.open import open_dataset

    return open_dataset(path, fmt, _dataset_options_of(options))


_DATASET_OPTIONS = (
    click.option("--format", "fmt", type=click.Choice(["folder", "kitti-odometry", "kitti-raw", "rosbag"]), default=None, help="Dataset format [default: told from the path]."),
    click.option("--sequence", default=None, help="KITTI odometry: the sequence number, when the folder holds several."),
    click.option("--ring", type=click.IntRange(0, 63), default=None, help="KITTI: the Velodyne ring used as the line laser (0 highest, 63 lowest) [default: the one hitting the road about 10 m ahead]."),
    click.option("--camera", type=click.IntRange(0, 3), default=None, help="KITTI raw: the camera (0, 1 grey; 2, 3 colour, read as grey) [default: the first the drive holds]."),
    click.option(
        "--truth",
        type=click.Choice(["positions", "velocities"]),
        default=None,
        help="KITTI raw: the true trajectory from the OXTS GPS positions (the development kit's) or from its velocities integrated (steadier over a short drive) [default: positions].",
    ),
    click.option("--rig", type=click.Path(dir_okay=False, path_type=Path), default=None, help="ROS bag: a rig YAML, whole or in part, over the rig the bag holds field by field [default: the bag's own: CameraInfo, LaserScan, tf]."),
    click.option("--image-topic", default=None, help="ROS bag: sensor_msgs Image or CompressedImage topic."),
    click.option("--scan-topic", default=None, help="ROS bag: sensor_msgs LaserScan topic."),
    click.option("--odometry-topic", default=None, help="ROS bag: nav_msgs Odometry topic (optional)."),
    click.option("--imu-topic", default=None, help="ROS bag: sensor_msgs Imu topic (optional; T_body_imu from tf, its noise from the defaults unless --rig gives them)."),
    click.option("--camera-info-topic", default=None, help="ROS bag: sensor_msgs CameraInfo topic [default: the image topic's sibling camera_info]."),
    click.option(
        "--body-frame",
        default=None,
        help="ROS bag: the body's tf frame, origin on the ground, z up [default: base_footprint, else base_link].",
    ),
    click.option("--camera-frame", default=None, help="ROS bag: the camera's tf frame [default: the images' frame_id]; given, tf wins over --rig."),
    click.option("--laser-frame", default=None, help="ROS bag: the laser's tf frame [default: the scans' frame_id]; given, tf wins over --rig."),
)
_DATASET_KEYS = (
    "sequence", "ring", "camera", "truth", "rig", "image_topic", "scan_topic", "odometry_topic", "imu_topic", "camera_info_topic", "body_frame", "camera_frame",
    "laser_frame",
)


def _dataset_options(fn):
    for option in reversed(_DATASET_OPTIONS):
        fn = option(fn)
    return fn


def _pop_dataset_options(kwargs: dict) -> dict:
    return {"fmt": kwargs.pop("fmt")} | {k: kwargs.pop(k) for k in _DATASET_KEYS}


@main.command()
@click.argument("dataset", type=click.Path(path_type=Path))
@click.option(
    "--estimator",
    type=click.Choice(["gm", "ptpm", "isam2", "isam2-batch", "odometry"]),
    default=None,
    help="gm, ptpm: the paper's EKF variants; isam2: the online graph (fixed-lag smoothing); isam2-batch: the online pass, then the whole log smoothed; odometry: the odometry integrated alone (a baseline). [default: the config file's, else ptpm]",
)
@click.option("--lag", "lag_s", type=float, default=None, help="isam2: fixed lag of the smoother, seconds.")
@click.option("--keyframe-every", type=int, default=None, help="isam2: a keyframe every this many frames (1: every frame); isam2-batch: the same for its online pass [default: 1 for isam2, 5 for isam2-batch].")
@click.option("--graph-process", is_flag=True, help="isam2: run the graph in a second process, on another core (faster frames; results depend on the timing).")
@click.option("--realtime", is_flag=True, help="Give the estimator each event when its time has come on the wall clock, as the sensors would live (a run takes the log's duration at least).")
@click.option("--out", "out_dir", required=True, type=click.Path(file_okay=False, path_type=Path), help="Run folder to write (kept current as the run goes: Ctrl-C keeps what was done).")
@click.option("--overwrite", is_flag=True, help="Empty a run folder that holds an earlier run and write this one there.")
@click.option("--config", "config_path", type=click.Path(dir_okay=False, path_type=Path), default=None, help="YAML run configuration (see config.yaml of a run).")
@click.option("--max-points", type=int, default=None, help="Cap n on live points.")
@click.option("--no-odometry", is_flag=True, help="Ignore the dataset's odometry (constant-velocity model).")
@click.option("--no-imu", is_flag=True, help="Ignore the dataset's IMU.")
@click.option("--max-frames", type=int, default=None, help="Stop after this many camera frames.")
@click.option("--viewer", is_flag=True, help="Show the run live in rerun (pip install 'dem-graph[viewer]'): image and tracked points, live local map, trajectory.")
@click.option("--record", "record_path", type=click.Path(dir_okay=False, path_type=Path), default=None, help="Save what --viewer shows to this rerun recording (.rrd), without a screen.")
@click.option("--viewer-colour", "viewer_colour", type=click.Choice(["height", "sigma"]), default="height", show_default=True, help="Colour the viewer's map surfaces by height or by the height's standard deviation.")
@_dataset_options
@_friendly_errors
def run(dataset, estimator, lag_s, keyframe_every, graph_process, realtime, out_dir, overwrite, config_path, max_points, no_odometry, no_imu, max_frames, viewer, record_path, viewer_colour, **kwargs) -> None:
    """Run an estimator over a dataset (folder, KITTI or ROS bag); write trajectory.tum, points.ply, metrics.json, config.yaml
    (isam2 also trajectory_smoothed.tum; isam2-batch also trajectory_online.tum)."""
    from dem_graph.pipeline.config import GRAPH_ESTIMATORS, RunOverrides, configured_estimator
    from dem_graph.pipeline.live_view import ViewerOptions
    from dem_graph.pipeline.metrics import summary_lines
    from dem_graph.pipeline.run import run_dataset

    options = _pop_dataset_options(kwargs)
    fmt = options.pop("fmt")
    overrides = RunOverrides(
        estimator=estimator, max_frames=max_frames, max_points=max_points, no_odometry=no_odometry, no_imu=no_imu, lag_s=lag_s,
        keyframe_every=keyframe_every, graph_process=graph_process, realtime=realtime,
    )
    graph_only = overrides.graph_only()
    if graph_only:
        chosen = configured_estimator(config_path, overrides)
        if chosen not in GRAPH_ESTIMATORS:
            raise click.UsageError(f"{', '.join(graph_only)}: used only by --estimator {' or '.join(GRAPH_ESTIMATORS)}, not by {chosen} (the run's estimator): leave {'it' if len(graph_only) == 1 else 'them'} out or choose one of those")
    shown = ViewerOptions(spawn=viewer, record_path=record_path, colour_by=viewer_colour) if viewer or record_path else None
    result = run_dataset(dataset, overrides, config_path, out_dir, _dataset_options_of(options), fmt, viewer=shown, overwrite=overwrite)
    for line in summary_lines(result.metrics):
        click.echo(line)
    click.echo(f"run folder: {out_dir} ({', '.join(p.name for p in result.paths.values())})")
    if result.error:
        click.echo(f"dem-graph: error: {result.error} (results up to there were written)", err=True)
        sys.exit(130 if result.interrupted else 2)


@main.command("bag-info")
@click.argument("bag", type=click.Path(path_type=Path))
@click.option("--rig", "rig_path", type=click.Path(dir_okay=False, path_type=Path), default=None, help="A rig YAML over the bag's rig, as `run --rig` takes it.")
@_friendly_errors
def bag_info_command(bag, rig_path) -> None:
    """List a ROS bag's topics (type, messages, rate, frame), propose the topics for `dem-graph run`, and print the rig it would read from
    the bag (CameraInfo, LaserScan, tf) as YAML."""
    from dem_graph.datasets.bag_info import bag_info

    for line in bag_info(bag, rig_path).lines():
        click.echo(line)


@main.command("config")
@_friendly_errors
def config_command() -> None:
    """Print the whole default run configuration as YAML, each setting under its meaning and unit
    (`dem-graph config > my.yaml`, edit, then `dem-graph run DATASET --config my.yaml`)."""
    from dem_graph.pipeline.config_yaml import config_yaml

    click.echo(config_yaml(), nl=False)


@main.command()
@click.argument("run_dir", metavar="RUN", type=click.Path(file_okay=False, path_type=Path))
@click.option("--dataset", type=click.Path(path_type=Path), default=None, help="Dataset folder the run was made from [default: the one in RUN/metrics.json].")
@click.option("--at", "at_s", type=float, default=None, help="The local map at this time (seconds) as the guidance had it then (RUN/live_maps.nc), instead of the global map.")
@click.option("--hindsight", is_flag=True, help="With --at: the local map made again from the run's final poses, not the live one.")
@click.option("--resolution", "resolution_m", type=float, default=None, help="Cell size, metres [default: the run's, else 0.1].")
@click.option("--out", "out_dir", type=click.Path(file_okay=False, path_type=Path), default=None, help="Folder for dem.tif, dem.npz, dem.png, cloud.ply [default: RUN, or RUN/dem_at_<T> with --at].")
@_friendly_errors
def dem(run_dir, dataset, at_s, hindsight, resolution_m, out_dir) -> None:
    """Make a run's DEM again from its poses (global), or show the local map at a time: the live one
    the guidance had (from RUN/live_maps.nc), or with --hindsight one made from the final poses."""
    from dem_graph.pipeline.metrics import laser_cells_error_text
    from dem_graph.pipeline.run_dem import DemMetrics
    from dem_graph.pipeline.run_folder import live_map_of_run, remake_dem, write_dem_outputs, write_run_dem

    if at_s is not None and not hindsight:
        if resolution_m is not None:
            raise click.UsageError("--resolution remakes a map: give it with --hindsight (the live map keeps the run's cells)")
        live = live_map_of_run(run_dir, at_s)
        out_dir = out_dir or run_dir / f"dem_at_{at_s:g}"
        paths = write_dem_outputs(out_dir, live)
        click.echo(f"live local map at {live.meta['t_s']:.3f} s (the last one saved at or before {at_s:g} s): {int(live.covered.sum())} cells of {live.geometry.resolution_m:g} m known")
        click.echo(f"written: {', '.join(str(p) for p in paths.values())}")
        return
    result = remake_dem(run_dir, dataset, at_s, resolution_m)
    out_dir = out_dir or (run_dir if at_s is None else run_dir / f"dem_at_{at_s:g}")
    paths = write_run_dem(result, out_dir)
    m = result.metrics
    click.echo(f"DEM ({result.dem.frame}{', hindsight' if at_s is not None else ''}): {m.covered_cells} cells of {result.dem.geometry.resolution_m:g} m covered")
    e, c = (m.height_error_laser_cells, m.corridor) if isinstance(m, DemMetrics) else (None, None)  # a local map has no truth figures
    if e is not None and c is not None:
        click.echo(f"{laser_cells_error_text(e)}; corridor {100 * c.coverage:.0f} % covered")
    click.echo(f"written: {', '.join(str(p) for p in paths.values())}")


@main.command()
@click.argument("dataset", type=click.Path(path_type=Path))
@click.option("--out", "out_dir", required=True, type=click.Path(file_okay=False, path_type=Path), help="Output dataset folder.")
@click.option("--camera-gap", multiple=True, metavar="T0:T1", help="No camera frame from T0 to T1 s (a blackout); repeatable.")
@click.option("--laser-gap", multiple=True, metavar="T0:T1", help="No laser scan from T0 to T1 s; repeatable.")
@click.option("--odometry-gap", multiple=True, metavar="T0:T1", help="No odometry message from T0 to T1 s; repeatable.")
@click.option("--black-frames", multiple=True, metavar="T0:T1", help="Frames from T0 to T1 s arrive black; repeatable.")
@click.option("--overwrite", is_flag=True, help="Replace an existing output folder.")
@_dataset_options
@_friendly_errors
def degrade(dataset, out_dir, camera_gap, laser_gap, odometry_gap, black_frames, overwrite, **kwargs) -> None:
    """Write a copy of a dataset with sensor faults put in (gaps, black frames), to measure how the
    estimators survive them. Times are the log's own clock, seconds; the ground truth is kept whole."""
    from dem_graph.datasets.faults import Faults, parse_interval, write_faulty_dataset

    options = _pop_dataset_options(kwargs)
    faults = Faults(
        camera_gaps=tuple(parse_interval(t) for t in camera_gap),
        laser_gaps=tuple(parse_interval(t) for t in laser_gap),
        odometry_gaps=tuple(parse_interval(t) for t in odometry_gap),
        black_frames=tuple(parse_interval(t) for t in black_frames),
    )
    path = write_faulty_dataset(_open_dataset(dataset, options.pop("fmt"), **options), faults, out_dir, overwrite=overwrite)
    click.echo(f"{faults.describe()}: {path}")


@main.command()
@click.argument("run_dir", metavar="RUN", type=click.Path(path_type=Path))
@click.option("--truth", "dataset", required=True, type=click.Path(path_type=Path), help="Dataset folder with ground truth (the one the run was made from).")
@click.option("--out", "out_path", type=click.Path(dir_okay=False, path_type=Path), default=None, help="JSON file to write [default: RUN/evaluation.json].")
@_friendly_errors
def evaluate(run_dir, dataset, out_path) -> None:
    """The metrics of a run folder against the ground truth: ATE (anchored, aligned), drift, RPE over
    10 m, the DEM's height errors and coverage, the Fig. 8 local error; time and points per frame."""
    from dem_graph.studies.evaluate import EVALUATION_JSON, evaluate_run

    result = evaluate_run(run_dir, _open_dataset(dataset))
    path = result.write_json(out_path or Path(run_dir) / EVALUATION_JSON)
    click.echo(result.table())
    click.echo(f"written: {path}")


@main.command()
@click.argument("dataset", type=click.Path(path_type=Path))
@click.option("--out", "out_dir", required=True, type=click.Path(file_okay=False, path_type=Path), help="Folder for the run folders, summary.json and the report.")
@click.option("--estimators", default=None, help="Comma-separated estimators to run (odometry: the odometry integrated alone, a baseline). [default: odometry (when the log has it), gm, ptpm, isam2, isam2-batch]")
@click.option("--max-frames", type=int, default=None, help="Stop each run after this many camera frames.")
@click.option("--config", "config_path", type=click.Path(dir_okay=False, path_type=Path), default=None, help="YAML run configuration shared by every run (its estimator is ignored).")
@_dataset_options
@_friendly_errors
def compare(dataset, out_dir, estimators, max_frames, config_path, **kwargs) -> None:
    """Run the estimators on the same data and settings; print one table, write each run into
    OUT/<estimator>/, OUT/summary.json, OUT/report.md and a self-contained OUT/report.html."""
    from dem_graph.pipeline.config import RunOverrides, run_config
    from dem_graph.studies.compare import compare as run_comparison
    from dem_graph.studies.compare import parse_estimators

    names = parse_estimators(estimators) if estimators is not None else None
    sequence = _open_dataset(dataset, **_pop_dataset_options(kwargs))
    config = run_config(sequence, config_path, RunOverrides(max_frames=max_frames))
    result = run_comparison(sequence, out_dir, names, config, dataset=Path(dataset).resolve())
    click.echo(result.table())
    click.echo(f"report: {result.paths['report_html']} (and report.md); summary: {result.paths['summary']}")
    click.echo(f"run folders: {', '.join(str(r.run_dir) for r in result.runs)}")
    figures = [p for k, p in result.paths.items() if k.startswith("figure_")]
    if figures:
        click.echo(f"figures: {figures[0].parent}/ ({', '.join(p.name for p in figures)})")
    failed = [r for r in result.runs if r.status == "failed"]
    if failed:
        click.echo(f"dem-graph: error: {len(failed)} of {len(result.runs)} runs failed ({'; '.join(f'{r.estimator}: {r.error}' for r in failed)})", err=True)
        sys.exit(2)


def _number_list(text: str, kind, what: str) -> tuple:
    """``"0-7"``, ``"1,2,5"`` or ``"1.5"`` as numbers; a usage error naming ``what`` otherwise."""
    out = []
    try:
        for part in (p.strip() for p in text.split(",") if p.strip()):
            if kind is int and "-" in part[1:]:
                lo, hi = part.split("-", 1) if not part.startswith("-") else (part, part)
                out.extend(range(int(lo), int(hi) + 1))
            else:
                out.append(kind(part))
    except ValueError:
        raise click.BadParameter(f"{text!r} is not a list of numbers", param_hint=what) from None
    if not out:
        raise click.BadParameter("give at least one", param_hint=what)
    return tuple(dict.fromkeys(out))


@main.command()
@click.option("--data", "data_dir", required=True, type=click.Path(file_okay=False, path_type=Path), help="Folder for the simulated datasets and each run's result (study_results/): a study started again keeps what is done there.")
@click.option("--scenario", "scenario_name", default="paper", show_default=True, help="Simulated scenario.")
@click.option("--seeds", default="0-7", show_default=True, help="Seeds: a list (0,3,5) or a range (0-7).")
@click.option("--speeds", default="1.5", show_default=True, help="Speeds, m/s, comma-separated.")
@click.option("--budgets", default="default", show_default=True, help="Caps on live points, comma-separated; 'default': dem-graph run's settings.")
@click.option("--estimators", default="gm,ptpm,isam2,isam2-batch", show_default=True, help="Comma-separated estimators (isam2-process: isam2 with its graph in a second process; a name ending in -noimu: that estimator ignoring the dataset's IMU).")
@click.option("--realtime", is_flag=True, help="Give each run its events at the camera's rate (fair only with a core per run: use --workers).")
@click.option("--max-frames", type=int, default=None, help="Stop each run after this many camera frames.")
@click.option("--length", "length_m", type=float, default=None, help="Shorten the drive to this many metres.")
@click.option("--scheduler", default="local", show_default=True, help="local: a Dask cluster on this machine; serial: one run after the other in this process; or the address of a Dask scheduler (tcp://HOST:8786).")
@click.option("--workers", "n_workers", type=click.IntRange(1, None), default=None, help="local: worker processes [default: one per core].")
@click.option("--out", "csv_path", type=click.Path(dir_okay=False, path_type=Path), default=None, help="The rows as CSV [default: DATA/study.csv].")
@_friendly_errors
def study(data_dir, scenario_name, seeds, speeds, budgets, estimators, realtime, max_frames, length_m, scheduler, n_workers, csv_path) -> None:
    """Accuracy against cost: every estimator and point budget on the scenario simulated for every
    seed and speed, as a grid of runs on Dask (a local cluster unless told); prints the table and
    what it says, writes the CSV."""
    from dem_graph.studies.study import estimator_study, parse_study_estimators

    caps = [None if b.strip() == "default" else _number_list(b, int, "--budgets")[0] for b in budgets.split(",") if b.strip()]
    result = estimator_study(
        data_dir, scenario_name, _number_list(seeds, int, "--seeds"), _number_list(speeds, float, "--speeds"), caps,
        parse_study_estimators(estimators), max_frames, length_m, scheduler, n_workers, realtime,
    )
    click.echo(result.table())
    click.echo(result.conclusion())
    path = result.write_csv(csv_path or Path(data_dir) / "study.csv")
    click.echo(f"rows: {path}")
    failed = [r for r in result.rows if r.status != "ok"]
    if failed:
        click.echo(f"dem-graph: error: {len(failed)} of {len(result.rows)} runs failed or stopped ({'; '.join(f'{r.estimator} seed {r.seed}: {r.status}' for r in failed[:3])})", err=True)
        sys.exit(2)


@main.command()
@click.option("--estimators", default="gm,ptpm,isam2,isam2-process", show_default=True, help="Comma-separated estimators (gm, ptpm, isam2, isam2-process: isam2 with its graph in a second process; a name ending in -noimu: that estimator ignoring the log's IMU).")
@click.option("--points", default="50,100,130,150,200,300", show_default=True, help="Comma-separated caps on live points.")
@click.option("--scenario", "scenario_name", default="demo", show_default=True, help="Simulated scenario to replay.")
@click.option("--frames", type=int, default=150, show_default=True, help="Camera frames per run (1550 or more: also the cost at frame 1500 over frame 150).")
@click.option("--plot", "plot_path", type=click.Path(dir_okay=False, path_type=Path), default=None, help="Also draw the paper's Fig. 12 (time per frame against live points) into this PNG.")
@click.option(
    "--realtime/--as-fast-as-possible",
    default=True,
    show_default=True,
    help="Feed the frames at the camera's rate, as on the vehicle, or as fast as each estimator takes them (the graph in a second process then falls behind and the front end waits for it).",
)
@_friendly_errors
def bench(estimators, points, scenario_name, frames, plot_path, realtime) -> None:
    """Benchmark the estimators: time per frame against the number of points, tracking included."""
    from dem_graph.studies.bench_estimators import BENCH_ESTIMATORS, bench_estimators, without_no_imu

    try:
        counts = tuple(int(x) for x in points.split(",") if x.strip())
    except ValueError:
        raise click.BadParameter(f"not a list of integers: {points}", param_hint="--points") from None
    if not counts or min(counts) < 1:
        raise click.BadParameter(f"give caps of 1 point or more: {points}", param_hint="--points")
    names = tuple(x.strip() for x in estimators.split(",") if x.strip())
    unknown = [n for n in names if without_no_imu(n) not in BENCH_ESTIMATORS]
    if unknown or not names:
        raise click.BadParameter(
            f"unknown estimator {', '.join(unknown) or '(none given)'}: choose from {', '.join(BENCH_ESTIMATORS)}, each optionally ending in -noimu",
            param_hint="--estimators",
        )
    if plot_path is not None and plot_path.suffix.lower() != ".png":
        raise click.BadParameter(f"the plot is a PNG: {plot_path}", param_hint="--plot")
    result = bench_estimators(names, counts, scenario_name, frames, realtime=realtime)
    click.echo(result.table())
    if plot_path is not None:
        from dem_graph.viz.bench_figure import time_per_frame_figure

        figure = time_per_frame_figure(plot_path, result.rows, f"'{result.scenario}' {result.image_size}, {result.frames} frames {'at the camera rate' if result.realtime else 'as fast as possible'}, on {result.machine}")
        click.echo(f"plot: {figure.path}")


@main.command("bench-dem")
@click.argument("dataset", required=False, type=click.Path(path_type=Path))
@click.option("--run", "run_dir", type=click.Path(file_okay=False, path_type=Path), default=None, help="Place the returns with this run's poses [default: the dataset's ground truth].")
@click.option("--points", "n_points", type=int, default=5_000_000, show_default=True, help="Measurements in the throughput test.")
@click.option("--repeats", type=int, default=5, show_default=True, help="Timed repeats of each stage (the table gives their median and p95).")
@_friendly_errors
def bench_dem_command(dataset, run_dir, n_points, repeats) -> None:
    """Benchmark the DEM: fusion throughput and the time to rebuild a whole run's DEM."""
    from dem_graph.pipeline.run_folder import load_run_poses
    from dem_graph.studies.bench_dem import bench_dem

    sequence = _open_dataset(dataset) if dataset is not None else None
    poses = load_run_poses(run_dir) if run_dir is not None else None
    click.echo(bench_dem(sequence, poses, n_points=n_points, repeats=repeats).table())


@main.command()
@click.argument("datasets", nargs=-1, required=True, type=click.Path(file_okay=False, path_type=Path))
@click.option("--estimator", default="isam2-batch", show_default=True, help="The estimator run in every condition.")
@click.option(
    "--conditions",
    default="none;tracks;laser;odometry",
    show_default=True,
    help="Sets of ingredients replaced by their truth, ';'-separated, each a ','-list of tracks, laser, odometry (none: the dataset as it is).",
)
@click.option("--sigma-px", type=click.FloatRange(0.0, None), default=0.2, show_default=True, help="White noise on the true tracks, pixels.")
@click.option("--work", "work_dir", type=click.Path(file_okay=False, path_type=Path), default=None, help="Folder for the datasets with true streams and the kept results [default: beside the first dataset].")
@click.option("--scheduler", default="local", show_default=True, help="local (a Dask cluster here), serial, or a scheduler's address.")
@click.option("--workers", "n_workers", type=click.IntRange(1, None), default=None, help="local: worker processes [default: one per core].")
@click.option("--out", "csv_path", type=click.Path(dir_okay=False, path_type=Path), default=None, help="The rows as CSV [default: WORK/ablation.csv].")
@_friendly_errors
def ablate(datasets, estimator, conditions, sigma_px, work_dir, scheduler, n_workers, csv_path) -> None:
    """Which input makes the drift: the estimator on simulated DATASETS with tracks, laser or
    odometry replaced by their truth; prints each run's signed end height and pitch errors, ATE and
    DEM error, and per condition the mean height error with its standard error."""
    from dem_graph.studies.ablation import ablation_study, parse_ingredients

    parsed = [parse_ingredients(c) for c in conditions.split(";")]
    result = ablation_study(datasets, estimator, parsed, sigma_px, work_dir, scheduler, n_workers)
    click.echo(result.table())
    path = result.write_csv(csv_path or Path(work_dir or Path(datasets[0]).parent) / "ablation.csv")
    click.echo(f"rows: {path}")


@main.command("track-noise")
@click.argument("dataset", type=click.Path(path_type=Path))
@click.option("--frames", "max_frames", type=int, default=None, help="Camera frames to track [default: all].")
@click.option("--config", "config_path", type=click.Path(dir_okay=False, path_type=Path), default=None, help="YAML run configuration (its front end is measured).")
@_friendly_errors
def track_noise(dataset, max_frames, config_path) -> None:
    """Measure the front end's tracking error on a simulated dataset: its size, its correlation from
    frame to frame, and the frontend.sigma_px that matches them."""
    from dem_graph.pipeline.config import run_config
    from dem_graph.studies.tracking_noise import measure_tracking_noise

    sequence = _open_dataset(dataset)
    click.echo(measure_tracking_noise(sequence, max_frames, run_config(sequence, config_path)).table())


@main.command("bench-sim")
@click.option("--scenario", "scenario_name", default="paper", show_default=True, help="Scenario to benchmark.")
@click.option("--frames", "n_frames", type=int, default=40, show_default=True, help="Frames to render for the timing.")
@click.option("--skip-full", is_flag=True, help="Skip simulating the whole scenario to disk.")
@_friendly_errors
def bench_sim(scenario_name, n_frames, skip_full) -> None:
    """Benchmark the simulator: render and laser throughput, and the time to simulate a scenario."""
    from dem_graph.studies.bench_sim import bench_sim as run

    click.echo(run(scenario_name, n_frames=n_frames, full=not skip_full).table())


def _angle_window(text: str | None):
    if text is None:
        return None
    try:
        lo, hi = (float(x) for x in text.split(","))
    except ValueError:
        raise click.BadParameter("give two angles in degrees, as A,B", param_hint="--window-deg") from None
    if not lo < hi:
        raise click.BadParameter("the first angle must be smaller than the second", param_hint="--window-deg")
    import math

    return (math.radians(lo), math.radians(hi))


def _board_corners(ctx, param, text: str | None):
    """``COLSxROWS`` inner corners, both at least 2."""
    if text is None:
        return None
    parts = text.lower().split("x")
    try:
        cols, rows = (int(x) for x in parts)
    except ValueError:
        raise click.BadParameter(f"give the board's inner corners as COLSxROWS, e.g. 9x6, not {text!r}") from None
    if cols < 2 or rows < 2:
        raise click.BadParameter(f"a board has at least 2x2 inner corners, not {text!r}")
    return cols, rows


def _calibration_board(recording_board, corners, square_m):
    """The recording's board with ``--board`` / ``--square-m`` in place of its parts; None when a part is unknown."""
    from dem_graph.calibration.board import BoardSpec

    cols, rows = corners if corners else (recording_board.cols, recording_board.rows) if recording_board else (None, None)
    square = square_m if square_m is not None else recording_board.square_m if recording_board else None
    return BoardSpec(cols, rows, square) if cols is not None and square is not None else None


_ROSBAG_OPTIONS = ("image_topic", "scan_topic", "camera_info_topic", "intrinsics_path")


def _read_calibration_recording(recording: Path, layout: str, topics: dict):
    """The recording in ``layout``, after checking that the options given are those of that layout."""
    flag = {name: "--" + name.replace("_path", "").replace("_", "-") for name in _ROSBAG_OPTIONS}
    if layout == "radlocc":
        given = [flag[k] for k, v in topics.items() if v is not None and k != "intrinsics_path"]
        if given:
            raise click.UsageError(f"{', '.join(given)}: only for --format rosbag")
        from dem_graph.calibration.readers import read_radlocc_recording

        return read_radlocc_recording(recording, intrinsics_path=topics["intrinsics_path"])
    for name in ("image_topic", "scan_topic"):
        if topics[name] is None:
            raise click.UsageError(f"--format rosbag needs {flag[name]}")
    if (topics["camera_info_topic"] is None) == (topics["intrinsics_path"] is None):
        raise click.UsageError("--format rosbag needs the intrinsics: give --camera-info-topic or --intrinsics (one of them)")
    if topics["intrinsics_path"] is not None and topics["intrinsics_path"].suffix.lower() == ".mat":
        raise click.UsageError("--intrinsics: a MATLAB .mat file is read only with --format radlocc; give an OpenCV XML/YAML file")
    from dem_graph.calibration.rosbag_reader import read_rosbag_recording

    return read_rosbag_recording(recording, **topics)


def _camera_body_pose(rig_path, height_m: float | None, pitch_deg: float | None):
    """``T_body_cam`` of a calibration without ``--rig``: the camera ``height_m`` above the body origin on the ground,
    pitched down ``pitch_deg``; None with ``--rig`` (its own). Neither given: refused, the body frame would be the camera's."""
    import numpy as np

    from dem_graph.geometry.rig import camera_mount

    if rig_path is not None:
        if height_m is not None or pitch_deg is not None:
            raise click.UsageError("--camera-height-m and --camera-pitch-deg are for a calibration without --rig (the rig's T_body_cam is used): leave them out")
        return None
    if height_m is None or pitch_deg is None:
        raise click.UsageError(
            "the body's pose is unknown: give --rig RIG.yaml (its T_body_cam), or --camera-height-m H --camera-pitch-deg P (the camera H m above the "
            "ground, pitched P degrees down; the body origin on the ground below it, z up), else the rig would put the body at the camera"
        )
    return camera_mount([0.0, 0.0, height_m], np.radians(pitch_deg))


@main.command()
@click.argument("recording", type=click.Path(path_type=Path))
@click.option("--rig", "rig_path", type=click.Path(dir_okay=False, path_type=Path), default=None, help="Rig YAML to update [default: one made from the recording's intrinsics and scans].")
@click.option("--out", "out_dir", required=True, type=click.Path(file_okay=False, path_type=Path), help="Folder for rig.yaml, calibration.json and views/.")
@click.option(
    "--format", "layout", type=click.Choice(["radlocc", "rosbag"]), default="radlocc", show_default=True, help="Layout of the recording: a RADLOCC folder, or a ROS 1 or ROS 2 bag."
)
@click.option("--board", "board_corners", default=None, callback=_board_corners, help="Inner corners of the checkerboard, COLSxROWS, e.g. 9x6 [default: from the intrinsics file].")
@click.option("--square-m", type=click.FloatRange(min=0.0, min_open=True), default=None, help="Side of the checkerboard's squares, metres [default: from the intrinsics file].")
@click.option("--image-topic", default=None, help="rosbag: sensor_msgs/Image or CompressedImage topic.")
@click.option("--scan-topic", default=None, help="rosbag: sensor_msgs/LaserScan topic.")
@click.option("--camera-info-topic", default=None, help="rosbag: sensor_msgs/CameraInfo topic with the intrinsics (or give --intrinsics).")
@click.option("--intrinsics", "intrinsics_path", type=click.Path(dir_okay=False, path_type=Path), default=None, help="Intrinsics file: OpenCV XML/YAML or (radlocc only) the MATLAB toolbox's Calib_Results.mat; rosbag: instead of --camera-info-topic [radlocc default: xml/out_camera_data.xml, else Calib_Results.mat in the folder or data/].")
@click.option("--window-deg", default=None, help="Search the board only between these beam angles, degrees, as A,B.")
@click.option("--max-dt-s", type=float, default=0.05, show_default=True, help="Longest time between an image and its scan, seconds.")
@click.option(
    "--range-sigma-m",
    type=click.FloatRange(min=0.0, min_open=True),
    default=None,
    help="Range noise of the scanner, metres: a starting value; the residuals decide (a warning when they disagree by more than 2x) [default: from the scans].",
)
@click.option("--fix-range-sigma", is_flag=True, help="Hold --range-sigma-m instead of estimating the noise from the residuals.")
@click.option("--board-margin-m", type=click.FloatRange(min=0.0), default=None, help="How far the board extends beyond its outer squares, metres [default: half a square].")
@click.option("--plane-tol-m", type=click.FloatRange(min=0.0, min_open=True), default=None, help="Farthest an on-board return may lie from the board's plane, metres [default: 4 sigma of the range noise].")
@click.option("--dark-bias/--no-dark-bias", default=True, show_default=True, help="Estimate and remove the range bias of returns on dark squares.")
@click.option("--jackknife/--no-jackknife", default=True, show_default=True, help="Also the leave-one-pose-out spread of the estimate.")
@click.option("--camera-height-m", type=click.FloatRange(min=0.0, min_open=True), default=None, help="Without --rig: the camera's height above the ground, metres (with --camera-pitch-deg: T_body_cam).")
@click.option("--camera-pitch-deg", type=click.FloatRange(-90.0, 90.0), default=None, help="Without --rig: the camera's pitch below the horizontal, degrees (positive: looking down).")
@_friendly_errors
def calibrate(
    recording, rig_path, out_dir, layout, board_corners, square_m, image_topic, scan_topic, camera_info_topic, intrinsics_path, window_deg, max_dt_s,
    range_sigma_m, fix_range_sigma, board_margin_m, plane_tol_m, dark_bias, jackknife, camera_height_m, camera_pitch_deg,
) -> None:
    """Estimate T_cam_laser from checkerboard views and write the rig with it."""
    import numpy as np

    from dem_graph.calibration.pipeline import CalibrationOptions, calibrate_recording
    from dem_graph.calibration.report import rig_from_recording, write_calibration
    from dem_graph.geometry.rig import load_rig

    if fix_range_sigma and range_sigma_m is None:
        raise click.UsageError("--fix-range-sigma holds the value of --range-sigma-m: give it")
    options = CalibrationOptions(
        window_rad=_angle_window(window_deg), max_dt_s=max_dt_s, range_sigma_m=range_sigma_m, estimate_range_sigma=not fix_range_sigma,
        board_margin_m=board_margin_m, plane_tol_m=plane_tol_m, dark_bias=dark_bias, jackknife=jackknife,
    )
    topics = {"image_topic": image_topic, "scan_topic": scan_topic, "camera_info_topic": camera_info_topic, "intrinsics_path": intrinsics_path}
    data = _read_calibration_recording(recording, layout, topics)
    board = _calibration_board(data.board, board_corners, square_m)
    if board is None:
        raise click.UsageError(f"the board's size is not known ({recording} does not give it): give --board COLSxROWS and --square-m")
    mount = _camera_body_pose(rig_path, camera_height_m, camera_pitch_deg)
    rig = load_rig(rig_path) if rig_path else rig_from_recording(data, range_sigma_m or 0.01, source=recording, T_body_cam=mount)  # a bad recording fails here, first
    result = calibrate_recording(data, options, board)
    if not rig_path:  # the rig made from the recording carries the noise the calibration found
        rig = rig_from_recording(data, result.noise.sigma_m, source=recording, T_body_cam=mount)
    paths = write_calibration(result, data, rig, out_dir, max_dt_s)
    used = sum(v.used for v in result.views)
    click.echo(f"T_cam_laser from {used} of {len(result.views)} views:\n{np.array2string(result.T_cam_laser, precision=4, suppress_small=True)}")
    click.echo(f"sigma rot (deg): {np.round(result.sigma_rot_deg, 3).tolist()}, sigma trans (mm): {np.round(result.sigma_trans_mm, 1).tolist()}")
    click.echo(result.noise.summary())
    click.echo(result.dark.summary())
    report = result.to_dict()
    if report["jackknife"] is not None:
        jk = report["jackknife"]
        click.echo(
            f"leave-one-pose-out ({result.n_poses} poses): sigma rot (deg): {np.round(jk['sigma_rot_deg'], 3).tolist()}, "
            f"sigma trans (mm): {np.round(jk['sigma_trans_mm'], 1).tolist()}"
        )
    if result.model_sensitivity is not None:
        click.echo(
            f"noise model (noise halved, doubled, no dark bias): moves up to rot (deg) {np.round(np.degrees(result.model_sensitivity[:3]), 3).tolist()}, "
            f"trans (mm) {np.round(1000 * result.model_sensitivity[3:], 1).tolist()}"
        )
    if report["rig_covariance"] == "jackknife":
        click.echo("the leave-one-pose-out spread exceeds the formal covariance (range errors are not white noise): the rig carries the spread")
    click.echo(f"residual RMS {report['residual_rms_mm']:.1f} mm, variance factor {result.variance_factor:.2f}")
    click.echo(f"rig: {paths['rig']}\nreport: {paths['report']}\npictures: {paths['views']}")


@main.command("simulate-calibration")
@click.option("--seed", type=int, default=0, show_default=True, help="Random seed.")
@click.option("--views", "n_views", type=int, default=15, show_default=True, help="Board poses.")
@click.option("--corner-sigma-px", type=float, default=0.3, show_default=True, help="Corner noise of the truth file's corners (the images carry their own).")
@click.option("--range-sigma-m", type=float, default=0.02, show_default=True, help="Range noise, metres.")
@click.option(
    "--poses",
    type=click.Choice(["random", "guided"]),
    default="random",
    show_default=True,
    help="How the board is held: random tilts (many nearly upright), or as docs/calibration.md advises (tilted 34-57 deg forward or back).",
)
@click.option("--board", "board_corners", default="9x6", show_default=True, callback=_board_corners, help="Inner corners of the checkerboard, COLSxROWS.")
@click.option("--square-m", type=click.FloatRange(min=0.0, min_open=True), default=0.09, show_default=True, help="Side of the squares, metres.")
@click.option("--margin-m", type=click.FloatRange(min=0.0), default=0.05, show_default=True, help="White border of the board beyond its squares, metres.")
@click.option("--dark-dropout", type=click.FloatRange(0.0, 1.0), default=0.0, show_default=True, help="Probability that a return on a dark square is lost.")
@click.option("--dark-bias-m", type=float, default=0.0, show_default=True, help="Range bias of the returns on dark squares, metres (positive: read too far).")
@click.option("--neighbour", is_flag=True, help="A panel beside the board, 3-8 cm from its edge and 1-4 cm behind its plane.")
@click.option("--out", "out_dir", required=True, type=click.Path(file_okay=False, path_type=Path), help="Recording folder to write (RADLOCC layout, with truth.yaml).")
@_friendly_errors
def simulate_calibration_command(seed, n_views, corner_sigma_px, range_sigma_m, poses, board_corners, square_m, margin_m, dark_dropout, dark_bias_m, neighbour, out_dir) -> None:
    """Write a synthetic calibration recording with known T_cam_laser."""
    from dem_graph.calibration.board import BoardSpec
    from dem_graph.calibration.simulate import simulate_calibration, write_recording

    if n_views < 1:
        raise click.BadParameter("at least one view", param_hint="--views")
    sim = simulate_calibration(
        seed, n_views, corner_sigma_px, range_sigma_m, board=BoardSpec(*board_corners, square_m), margin_m=margin_m, pose_protocol=poses,
        dark_dropout=dark_dropout, dark_bias_m=dark_bias_m, neighbour=neighbour,
    )
    out = write_recording(sim, out_dir, seed)
    click.echo(f"recording: {out} ({n_views} views, truth in {out / 'truth.yaml'})")


if __name__ == "__main__":
    main()
