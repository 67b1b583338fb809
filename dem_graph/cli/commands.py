"""The user's commands: simulate or bring a log, run an estimator over it, read the result."""

from __future__ import annotations

import sys
from pathlib import Path

import click

from dem_graph.cli.datasets import FORMAT_OPTION, dataset_options_of, open_dataset, pop_dataset_options, pop_reader_options, reader_options
from dem_graph.cli.options import option, realtime_option
from dem_graph.cli.out_folder import name_of, out_folder, out_option, through_links
from dem_graph.cli.root import EXIT_RUN_FAILED, friendly_errors, main

GRAPH_PROCESS = "isam2-process"  # pipeline.config.GRAPH_PROCESS, spelled out: the library is imported only when a command runs
RUN_ESTIMATORS = ["gm", "ptpm", "isam2", GRAPH_PROCESS, "isam2-batch", "odometry"]


@main.command(short_help="List the built-in simulation scenarios.")
def scenarios() -> None:
    """List the built-in simulation scenarios."""
    from dem_graph.sim.scenarios import DEFAULT_SCENARIO, describe_scenarios

    for name, text in describe_scenarios().items():
        mark = " (default)" if name == DEFAULT_SCENARIO else ""
        click.echo(f"{name:8s} {text}{mark}")


@main.command(short_help="Simulate a scenario as a dataset folder.")
@option("--scenario", "scenario_name", default=None, group="Scenario", help="Scenario name (see `dem-graph scenarios`) [default: demo].")
@option("--seed", type=int, default=None, group="Scenario", help="Random seed; the same seed gives the same dataset.")
@option("--length-m", type=float, default=None, group="Scenario", help="Distance to drive, metres.")
@option("--speed-mps", type=float, default=None, group="Scenario", help="Mean speed, m/s.")
@option("--no-odometry", is_flag=True, group="Scenario", help="Leave wheel odometry out of the dataset.")
@option("--no-imu", is_flag=True, group="Scenario", help="Leave the IMU (imu.npz) out of the dataset.")
@out_option("Dataset folder to write.", "simulate", "<scenario>", group="Output")
@option("--overwrite", is_flag=True, group="Output", help="Replace an existing output folder.")
@option("--bag", "bag_path", type=click.Path(path_type=Path), default=None, group="Output", help="Also write the log as a ROS bag, as a robot records one: a .bag file (ROS 1) or a folder (ROS 2, MCAP).")
@friendly_errors
def simulate(scenario_name, seed, length_m, speed_mps, no_odometry, no_imu, out_dir, overwrite, bag_path) -> None:
    """Simulate a scenario and write it as a dataset folder with ground truth, and a preview picture."""
    from dem_graph.sim.pipeline import simulate as run
    from dem_graph.sim.scenarios import DEFAULT_SCENARIO, scenario

    config = scenario(
        scenario_name or DEFAULT_SCENARIO, seed=seed, length_m=length_m, speed_mps=speed_mps, with_odometry=False if no_odometry else None,
        with_imu=False if no_imu else None,
    )
    result = run(config, out_folder(out_dir, "simulate", config.name), overwrite=overwrite)
    click.echo(
        f"simulated '{config.name}' (seed {config.seed}): {result.length_m:.1f} m in {result.duration_s:.1f} s, "
        f"{result.n_frames} frames, {result.n_scans} laser scans, {result.n_odometry} odometry increments, {result.n_imu} IMU samples "
        f"({result.elapsed_s:.1f} s of computing)"
    )
    click.echo(f"dataset: {result.out_dir}")
    if result.preview_png:
        click.echo(f"picture: {result.preview_png}")
    if bag_path is not None:
        from dem_graph.datasets.bag_writer import BagOptions, write_robot_bag

        write_robot_bag(bag_path, result.out_dir, "ros1" if bag_path.suffix == ".bag" else "mcap", BagOptions(imu=True, image_encoding=config.camera_encoding))
        topics = ["/camera/image_raw", "/camera/camera_info", "/scan"] + ["/odom"] * (result.n_odometry > 0) + ["/imu/data"] * (result.n_imu > 0) + ["/tf"] * (result.n_odometry > 0) + ["/tf_static"]
        click.echo(f"bag: {bag_path} (images {config.camera_encoding}; topics {', '.join(topics)})")


def _run_overrides(estimator, graph_process: bool, **values):
    """The :class:`RunOverrides` of ``run``'s flags, ``isam2-process`` read as ``isam2 --graph-process``."""
    from dem_graph.pipeline.config import RunOverrides, split_graph_process

    if estimator is not None:
        estimator, in_process = split_graph_process(estimator)
        graph_process = graph_process or in_process
    return RunOverrides(estimator=estimator, graph_process=graph_process, **values)


def _refuse_graph_flags_without_graph(overrides, config_path) -> None:
    """A usage error when a flag only the graph estimators read is given to another estimator."""
    from dem_graph.pipeline.config import GRAPH_ESTIMATORS, configured_estimator

    graph_only = overrides.graph_only()
    if not graph_only:
        return
    chosen = configured_estimator(config_path, overrides)
    if chosen not in GRAPH_ESTIMATORS:
        raise click.UsageError(
            f"{', '.join(graph_only)}: used only by --estimator {' or '.join(GRAPH_ESTIMATORS)}, not by {chosen} (the run's estimator): "
            f"leave {'it' if len(graph_only) == 1 else 'them'} out or choose one of those"
        )


@main.command(short_help="Run an estimator over a dataset.")
@click.argument("dataset", type=click.Path(path_type=Path))
@FORMAT_OPTION
@option("--config", "config_path", type=click.Path(dir_okay=False, path_type=Path), default=None, group="Input", help="YAML run settings (`dem-graph config` prints them).")
@option("--max-frames", type=int, metavar="N", default=None, group="Input", help="Stop after this many camera frames.")
@option("--no-odometry", is_flag=True, group="Input", help="Ignore the odometry (constant-velocity model).")
@option("--no-imu", is_flag=True, group="Input", help="Ignore the IMU.")
@option(
    "--estimator", type=click.Choice(RUN_ESTIMATORS), metavar="NAME", default=None, group="Estimator",
    help="gm, ptpm (the paper's EKFs), isam2 (the online graph), isam2-process (its graph on another core), "
    "isam2-batch (isam2, then the whole log smoothed), odometry (alone) [default: the config's, else ptpm].",
)
@option("--max-points", type=int, metavar="N", default=None, group="Estimator", help="Cap on live points.")
@option("--lag-s", "lag_s", type=float, metavar="S", default=None, old="--lag", group="Estimator", help="isam2: the smoother's fixed lag, seconds.")
@option("--keyframe-every", type=int, metavar="N", default=None, group="Estimator", help="isam2: a keyframe every N frames [default: 1, isam2-batch 5].")
@option("--graph-process", is_flag=True, group="Estimator", help="isam2, isam2-batch: the graph on another core (results then depend on the timing).")
@realtime_option(False, "results sooner", group="Estimator")
@out_option("Run folder, kept current as the run goes.", "run", group="Output")
@option("--overwrite", is_flag=True, group="Output", help="Replace an earlier run in --out.")
@option("--viewer", is_flag=True, group="Viewer", help="Show the run live in rerun (the [viewer] extra).")
@option("--record", "record_path", type=click.Path(dir_okay=False, path_type=Path), default=None, group="Viewer", help="Save what --viewer shows to an .rrd file.")
@option("--viewer-colour", type=click.Choice(["height", "sigma"]), metavar="WHAT", default="height", show_default=True, group="Viewer", help="Colour the map by its height or its sigma.")
@reader_options
@friendly_errors
def run(dataset, fmt, config_path, max_frames, no_odometry, no_imu, estimator, max_points, lag_s, keyframe_every, graph_process, realtime, out_dir, overwrite, viewer, record_path, viewer_colour, **kwargs) -> None:
    """Run an estimator over a dataset (a dataset folder, KITTI or a ROS bag) and write the run folder:
    trajectory, points, the DEM, metrics.json, config.yaml (docs/guide/running.md)."""
    from dem_graph.pipeline.live_view import ViewerOptions
    from dem_graph.pipeline.metrics import failure_line, summary_lines
    from dem_graph.pipeline.run import run_dataset

    options = pop_reader_options(kwargs)
    overrides = _run_overrides(
        estimator, graph_process, max_frames=max_frames, max_points=max_points, no_odometry=no_odometry, no_imu=no_imu, lag_s=lag_s,
        keyframe_every=keyframe_every, realtime=realtime,
    )
    _refuse_graph_flags_without_graph(overrides, config_path)
    shown = ViewerOptions(spawn=viewer, record_path=record_path, colour_by=viewer_colour) if viewer or record_path else None
    if out_dir is None:
        dataset = through_links(dataset)
    out_dir = out_folder(out_dir, "run", name_of(dataset, options["sequence"]))
    result = run_dataset(dataset, overrides, config_path, out_dir, dataset_options_of(options), fmt, viewer=shown, overwrite=overwrite)
    for line in summary_lines(result.metrics):
        click.echo(line)
    click.echo(f"run folder: {out_dir} ({', '.join(p.name for p in result.paths.values())})")
    if result.error:
        click.echo(f"dem-graph: error: {result.error} (results up to there were written)", err=True)
        sys.exit(130 if result.interrupted else 2)
    failed = failure_line(result.metrics)
    if failed is not None:
        click.echo(failed, err=True)
        sys.exit(EXIT_RUN_FAILED)


@main.command("bag-info", short_help="A ROS bag's topics, the run line, its rig.")
@click.argument("bag", type=click.Path(path_type=Path))
@option("--rig", "rig_path", type=click.Path(dir_okay=False, path_type=Path), default=None, help="A rig YAML over the bag's rig, as `run --rig` takes it.")
@friendly_errors
def bag_info_command(bag, rig_path) -> None:
    """List a ROS bag's topics (type, messages, rate, frame), propose the topics for `dem-graph run`, and print the rig it would read from
    the bag (CameraInfo, LaserScan, tf) as YAML."""
    from dem_graph.datasets.bag_info import bag_info

    for line in bag_info(bag, rig_path).lines():
        click.echo(line)


@main.command("config", short_help="Print the default run configuration (YAML).")
@friendly_errors
def config_command() -> None:
    """Print the whole default run configuration as YAML, each setting under its meaning and unit
    (`dem-graph config > my.yaml`, edit, then `dem-graph run DATASET --config my.yaml`)."""
    from dem_graph.pipeline.config_yaml import config_yaml

    click.echo(config_yaml(), nl=False)


@main.command(short_help="A run's DEM again, or its local map at a time.")
@click.argument("run_dir", metavar="RUN", type=click.Path(file_okay=False, path_type=Path))
@option("--dataset", type=click.Path(path_type=Path), default=None, help="The dataset the run was made from [default: the one in RUN/metrics.json].")
@option("--at-s", "at_s", type=float, default=None, old="--at", help="The local map at this time, seconds, as the guidance had it then (RUN/live_maps.nc), instead of the global map.")
@option("--hindsight", is_flag=True, help="With --at-s: the local map made again from the run's final poses, not the live one.")
@option("--resolution-m", "resolution_m", type=float, default=None, old="--resolution", help="Cell size, metres [default: the run's, else 0.1].")
@option("--out", "out_dir", type=click.Path(file_okay=False, path_type=Path), default=None, help="Folder for dem.tif, dem.npz, dem.png, cloud.ply [default: RUN, or RUN/dem_at_<T> with --at-s].")
@friendly_errors
def dem(run_dir, dataset, at_s, hindsight, resolution_m, out_dir) -> None:
    """Make a run's DEM again from its poses (global), or show the local map at a time: the live one
    the guidance had (from RUN/live_maps.nc), or with --hindsight one made from the final poses."""
    from dem_graph.pipeline.metrics import laser_cells_error_text
    from dem_graph.pipeline.run_dem import DemMetrics
    from dem_graph.pipeline.run_folder import live_map_of_run, remake_dem, write_dem_outputs, write_run_dem

    if at_s is not None and not hindsight:
        if resolution_m is not None:
            raise click.UsageError("--resolution-m remakes a map: give it with --hindsight (the live map keeps the run's cells)")
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


@main.command(short_help="A copy of a dataset with sensor faults put in.")
@click.argument("dataset", type=click.Path(path_type=Path))
@FORMAT_OPTION
@option("--camera-gap", multiple=True, metavar="T0:T1", group="Faults", help="No camera frame from T0 to T1 s (a blackout); repeatable.")
@option("--laser-gap", multiple=True, metavar="T0:T1", group="Faults", help="No laser scan from T0 to T1 s; repeatable.")
@option("--odometry-gap", multiple=True, metavar="T0:T1", group="Faults", help="No odometry message from T0 to T1 s; repeatable.")
@option("--black-frames", multiple=True, metavar="T0:T1", group="Faults", help="Frames from T0 to T1 s arrive black; repeatable.")
@out_option("Dataset folder to write.", "degrade", group="Output")
@option("--overwrite", is_flag=True, group="Output", help="Replace an existing output folder.")
@reader_options
@friendly_errors
def degrade(dataset, camera_gap, laser_gap, odometry_gap, black_frames, out_dir, overwrite, **kwargs) -> None:
    """Write a copy of a dataset with sensor faults put in (gaps, black frames), to measure how the
    estimators survive them. Times are the log's own clock, seconds; the ground truth is kept whole."""
    from dem_graph.datasets.faults import Faults, parse_interval, write_faulty_dataset

    options = pop_dataset_options(kwargs)
    faults = Faults(
        camera_gaps=tuple(parse_interval(t) for t in camera_gap),
        laser_gaps=tuple(parse_interval(t) for t in laser_gap),
        odometry_gaps=tuple(parse_interval(t) for t in odometry_gap),
        black_frames=tuple(parse_interval(t) for t in black_frames),
    )
    sequence = open_dataset(dataset, options.pop("fmt"), **options)
    path = write_faulty_dataset(sequence, faults, out_folder(out_dir, "degrade", name_of(dataset, options["sequence"])), overwrite=overwrite)
    click.echo(f"{faults.describe()}: {path}")


@main.command(short_help="A run folder's metrics against the ground truth.")
@click.argument("run_dir", metavar="RUN", type=click.Path(path_type=Path))
@option("--dataset", required=True, type=click.Path(path_type=Path), old="--truth", help="The dataset the run was made from, with its ground truth.")
@option("--out", "out_path", type=click.Path(dir_okay=False, path_type=Path), default=None, help="JSON file to write [default: RUN/evaluation.json].")
@friendly_errors
def evaluate(run_dir, dataset, out_path) -> None:
    """The metrics of a run folder against the ground truth: ATE (anchored, aligned), drift, RPE over
    10 m, the DEM's height errors and coverage, the Fig. 8 local error; time and points per frame."""
    from dem_graph.studies.evaluate import EVALUATION_JSON, evaluate_run

    result = evaluate_run(run_dir, open_dataset(dataset))
    path = result.write_json(out_path or Path(run_dir) / EVALUATION_JSON)
    click.echo(result.table())
    click.echo(f"written: {path}")


@main.command(short_help="Every estimator on one dataset: a table, a report.")
@click.argument("dataset", type=click.Path(path_type=Path))
@FORMAT_OPTION
@option("--config", "config_path", type=click.Path(dir_okay=False, path_type=Path), default=None, group="Input", help="YAML run configuration shared by every run (its estimator is ignored).")
@option("--max-frames", type=int, metavar="N", default=None, group="Input", help="Stop each run after this many camera frames.")
@option(
    "--estimators", default=None, group="Estimators",
    help="Comma-separated estimators (odometry: the odometry alone, a baseline) [default: odometry (when the log has it), gm, ptpm, isam2, isam2-batch].",
)
@out_option("Folder for the run folders, summary.json and the report.", "compare", group="Output")
@reader_options
@friendly_errors
def compare(dataset, config_path, max_frames, estimators, out_dir, **kwargs) -> None:
    """Run the estimators on the same data and settings; print one table, write each run into
    OUT/<estimator>/, OUT/summary.json, OUT/report.md and a self-contained OUT/report.html."""
    from dem_graph.pipeline.config import RunOverrides, run_config
    from dem_graph.studies.compare import compare as run_comparison
    from dem_graph.studies.compare import parse_estimators

    names = parse_estimators(estimators) if estimators is not None else None
    options = pop_dataset_options(kwargs)
    sequence = open_dataset(dataset, **options)
    config = run_config(sequence, config_path, RunOverrides(max_frames=max_frames))
    out_dir = out_folder(out_dir, "compare", name_of(dataset, options["sequence"]))
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
