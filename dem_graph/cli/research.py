"""``dem-graph research``: the commands that measure the method rather than map a log (benchmarks,
studies, ablations, the tracker's noise, a synthetic calibration recording). Each is also still
reached by its old top-level name (``dem-graph bench``), hidden from ``dem-graph --help``."""

from __future__ import annotations

import sys
from pathlib import Path

import click

from dem_graph.cli.calibration import board_corners
from dem_graph.cli.datasets import open_dataset
from dem_graph.cli.options import number_list, option, realtime_option
from dem_graph.cli.out_folder import out_folder, out_option
from dem_graph.cli.root import add_hidden_aliases, friendly_errors, main

_AS_FAST = "results sooner, as `run`; fair timing needs a core per run (--workers)"
_TIMED = "unlike `run` and `study`, as the bench times the frames as on the vehicle"


@main.group(short_help="Benchmarks, studies, ablations (research tools).")
def research() -> None:
    """Benchmarks, studies and ablations: the commands that measure the method rather than map a log."""


@research.command(short_help="Accuracy against cost over seeds and speeds.")
@option("--work", "work_dir", required=True, type=click.Path(file_okay=False, path_type=Path), old="--data", help="Folder for the simulated datasets and each run's result (study_results/): a study started again keeps what is done there.")
@option("--scenario", "scenario_name", default="paper", show_default=True, help="Simulated scenario.")
@option("--seeds", default="0-7", show_default=True, help="Seeds: a list (0,3,5) or a range (0-7).")
@option("--speeds-mps", "speeds_mps", default="1.5", show_default=True, old="--speeds", help="Speeds, m/s, comma-separated.")
@option("--max-points", default="default", show_default=True, old="--budgets", help="Caps on live points, comma-separated; 'default': dem-graph run's settings.")
@option("--estimators", default="gm,ptpm,isam2,isam2-batch", show_default=True, help="Comma-separated estimators (isam2-process: isam2 with its graph in a second process; a name ending in -noimu: that estimator ignoring the dataset's IMU).")
@realtime_option(False, _AS_FAST)
@option("--max-frames", type=int, default=None, help="Stop each run after this many camera frames.")
@option("--length-m", "length_m", type=float, default=None, old="--length", help="Shorten the drive to this many metres.")
@option("--scheduler", default="local", show_default=True, help="local: a Dask cluster on this machine; serial: one run after the other in this process; or the address of a Dask scheduler (tcp://HOST:8786).")
@option("--workers", "n_workers", type=click.IntRange(1, None), default=None, help="local: worker processes [default: one per core].")
@option("--out", "csv_path", type=click.Path(dir_okay=False, path_type=Path), default=None, help="The rows as CSV [default: WORK/study.csv].")
@friendly_errors
def study(work_dir, scenario_name, seeds, speeds_mps, max_points, estimators, realtime, max_frames, length_m, scheduler, n_workers, csv_path) -> None:
    """Accuracy against cost: every estimator and point cap on the scenario simulated for every
    seed and speed, as a grid of runs on Dask (a local cluster unless told); prints the table and
    what it says, writes the CSV."""
    from dem_graph.studies.study import estimator_study, parse_study_estimators

    caps = [None if b.strip() == "default" else number_list(b, int, "--max-points")[0] for b in max_points.split(",") if b.strip()]
    result = estimator_study(
        work_dir, scenario_name, number_list(seeds, int, "--seeds"), number_list(speeds_mps, float, "--speeds-mps"), caps,
        parse_study_estimators(estimators), max_frames, length_m, scheduler, n_workers, realtime,
    )
    click.echo(result.table())
    click.echo(result.conclusion())
    path = result.write_csv(csv_path or Path(work_dir) / "study.csv")
    click.echo(f"rows: {path}")
    failed = [r for r in result.rows if r.status != "ok"]
    if failed:
        click.echo(f"dem-graph: error: {len(failed)} of {len(result.rows)} runs failed or stopped ({'; '.join(f'{r.estimator} seed {r.seed}: {r.status}' for r in failed[:3])})", err=True)
        sys.exit(2)


def _point_caps(text: str) -> tuple[int, ...]:
    """``"150,500"`` as caps on live points, each at least 1; a usage error naming ``--max-points`` otherwise."""
    try:
        caps = tuple(int(x) for x in text.split(",") if x.strip())
    except ValueError:
        raise click.BadParameter(f"not a list of integers: {text}", param_hint="--max-points") from None
    if not caps or min(caps) < 1:
        raise click.BadParameter(f"give caps of 1 point or more: {text}", param_hint="--max-points")
    return caps


def _bench_estimators(text: str) -> tuple[str, ...]:
    """The bench's estimators from ``"gm,isam2-process"``; a usage error naming ``--estimators`` for an unknown one."""
    from dem_graph.studies.bench_estimators import BENCH_ESTIMATORS, without_no_imu

    names = tuple(x.strip() for x in text.split(",") if x.strip())
    unknown = [n for n in names if without_no_imu(n) not in BENCH_ESTIMATORS]
    if unknown or not names:
        raise click.BadParameter(
            f"unknown estimator {', '.join(unknown) or '(none given)'}: choose from {', '.join(BENCH_ESTIMATORS)}, each optionally ending in -noimu",
            param_hint="--estimators",
        )
    return names


@research.command(short_help="Time per frame against live points.")
@option("--estimators", default="gm,ptpm,isam2,isam2-process", show_default=True, help="Comma-separated estimators (gm, ptpm, isam2, isam2-process: isam2 with its graph in a second process; a name ending in -noimu: that estimator ignoring the log's IMU).")
@option("--max-points", default="50,100,130,150,200,300", show_default=True, old="--points", help="Caps on live points, comma-separated.")
@option("--scenario", "scenario_name", default="demo", show_default=True, help="Simulated scenario to replay.")
@option("--max-frames", type=int, default=150, show_default=True, old="--frames", help="Camera frames per run (1550 or more: also the cost at frame 1500 over frame 150).")
@option("--plot", "plot_path", type=click.Path(dir_okay=False, path_type=Path), default=None, help="Also draw the paper's Fig. 12 (time per frame against live points) into this PNG.")
@realtime_option(True, _TIMED)
@friendly_errors
def bench(estimators, max_points, scenario_name, max_frames, plot_path, realtime) -> None:
    """Benchmark the estimators: time per frame against the number of points, tracking included."""
    from dem_graph.studies.bench_estimators import bench_estimators

    caps = _point_caps(max_points)
    names = _bench_estimators(estimators)
    if plot_path is not None and plot_path.suffix.lower() != ".png":
        raise click.BadParameter(f"the plot is a PNG: {plot_path}", param_hint="--plot")
    result = bench_estimators(names, caps, scenario_name, max_frames, realtime=realtime)
    click.echo(result.table())
    if plot_path is not None:
        from dem_graph.viz.bench_figure import time_per_frame_figure

        figure = time_per_frame_figure(plot_path, result.rows, f"'{result.scenario}' {result.image_size}, {result.frames} frames {'at the camera rate' if result.realtime else 'as fast as possible'}, on {result.machine}")
        click.echo(f"plot: {figure.path}")


@research.command("bench-dem", short_help="DEM fusion throughput and rebuild time.")
@click.argument("dataset", required=False, type=click.Path(path_type=Path))
@option("--run", "run_dir", type=click.Path(file_okay=False, path_type=Path), default=None, help="Place the returns with this run's poses [default: the dataset's ground truth].")
@option("--measurements", "n_measurements", type=int, default=5_000_000, show_default=True, old="--points", help="Measurements in the throughput test.")
@option("--repeats", type=int, default=5, show_default=True, help="Timed repeats of each stage (the table gives their median and p95).")
@friendly_errors
def bench_dem_command(dataset, run_dir, n_measurements, repeats) -> None:
    """Benchmark the DEM: fusion throughput and the time to rebuild a whole run's DEM."""
    from dem_graph.pipeline.run_folder import load_run_poses
    from dem_graph.studies.bench_dem import bench_dem

    sequence = open_dataset(dataset) if dataset is not None else None
    poses = load_run_poses(run_dir) if run_dir is not None else None
    click.echo(bench_dem(sequence, poses, n_points=n_measurements, repeats=repeats).table())


@research.command(short_help="Which input makes the drift (truth swapped in).")
@click.argument("datasets", nargs=-1, required=True, type=click.Path(file_okay=False, path_type=Path))
@option("--estimator", default="isam2-batch", show_default=True, help="The estimator run in every condition.")
@option(
    "--conditions",
    default="none;tracks;laser;odometry",
    show_default=True,
    help="Sets of ingredients replaced by their truth, ';'-separated, each a ','-list of tracks, laser, odometry (none: the dataset as it is).",
)
@option("--sigma-px", type=click.FloatRange(0.0, None), default=0.2, show_default=True, help="White noise on the true tracks, pixels.")
@option("--work", "work_dir", type=click.Path(file_okay=False, path_type=Path), default=None, help="Folder for the datasets with true streams and the kept results [default: beside the first dataset].")
@option("--scheduler", default="local", show_default=True, help="local (a Dask cluster here), serial, or a scheduler's address.")
@option("--workers", "n_workers", type=click.IntRange(1, None), default=None, help="local: worker processes [default: one per core].")
@option("--out", "csv_path", type=click.Path(dir_okay=False, path_type=Path), default=None, help="The rows as CSV [default: WORK/ablation.csv].")
@friendly_errors
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


@research.command("track-noise", short_help="The tracker's pixel error against the truth.")
@click.argument("dataset", type=click.Path(path_type=Path))
@option("--max-frames", type=int, default=None, old="--frames", help="Camera frames to track [default: all].")
@option("--config", "config_path", type=click.Path(dir_okay=False, path_type=Path), default=None, help="YAML run configuration (its front end is measured).")
@friendly_errors
def track_noise(dataset, max_frames, config_path) -> None:
    """Measure the front end's tracking error on a simulated dataset: its size, its correlation from
    frame to frame, and the frontend.sigma_px that matches them."""
    from dem_graph.pipeline.config import run_config
    from dem_graph.studies.tracking_noise import measure_tracking_noise

    sequence = open_dataset(dataset)
    click.echo(measure_tracking_noise(sequence, max_frames, run_config(sequence, config_path)).table())


@research.command("bench-sim", short_help="Simulator throughput.")
@option("--scenario", "scenario_name", default="paper", show_default=True, help="Scenario to benchmark.")
@option("--frames", "n_frames", type=int, default=40, show_default=True, help="Frames to render for the timing, spread over the drive.")
@option("--skip-full", is_flag=True, help="Skip simulating the whole scenario to disk.")
@friendly_errors
def bench_sim(scenario_name, n_frames, skip_full) -> None:
    """Benchmark the simulator: render and laser throughput, and the time to simulate a scenario."""
    from dem_graph.studies.bench_sim import bench_sim as run

    click.echo(run(scenario_name, n_frames=n_frames, full=not skip_full).table())


@research.command("bench-ros2", short_help="The ROS 2 node's latency, camera message to GridMap.")
@option("--work", "work_dir", required=True, type=click.Path(file_okay=False, path_type=Path), help="Folder for the simulated drive (its bag, kept) and each run's files.")
@option("--duration-s", type=float, default=40.0, show_default=True, help="Seconds of driving (640x480 at 25 Hz, the laser at 50 Hz).")
@option("--warmup-s", type=float, default=10.0, show_default=True, help="The latency is of the frames after this many seconds (the node's start is timed apart).")
@option("--runs", type=click.IntRange(1, None), default=3, show_default=True, help="Runs of player, node and subscriber.")
@option("--estimator", default="isam2-process", show_default=True, help="The node's estimator (isam2-process: the vehicle's).")
@option("--seed", type=int, default=0, show_default=True, help="The drive's seed.")
@friendly_errors
def bench_ros2(work_dir, duration_s, warmup_s, runs, estimator, seed) -> None:
    """Time the ROS 2 node from a camera message on the wire to the GridMap of that frame on the wire, with the player, the node and a
    subscriber in three processes on this machine (loopback), and what the node received against what was sent."""
    from dem_graph.studies.bench_ros2 import bench_ros2 as run

    click.echo(run(work_dir, duration_s, runs, seed, estimator, warmup_s).table())


@research.command("simulate-calibration", short_help="A synthetic calibration recording.")
@option("--seed", type=int, default=0, show_default=True, help="Random seed.")
@option("--views", "n_views", type=int, default=15, show_default=True, help="Board poses.")
@option("--corner-sigma-px", type=float, default=0.3, show_default=True, help="Corner noise of the truth file's corners (the images carry their own).")
@option("--range-sigma-m", type=float, default=0.02, show_default=True, help="Range noise, metres.")
@option(
    "--poses",
    type=click.Choice(["random", "guided"]),
    default="random",
    show_default=True,
    help="How the board is held: random tilts (many nearly upright), or as docs/calibration.md advises (tilted 34-57 deg forward or back).",
)
@option("--board", "board_corners", default="9x6", show_default=True, callback=board_corners, help="Inner corners of the checkerboard, COLSxROWS.")
@option("--square-m", type=click.FloatRange(min=0.0, min_open=True), default=0.09, show_default=True, help="Side of the squares, metres.")
@option("--board-margin-m", "margin_m", type=click.FloatRange(min=0.0), default=0.05, show_default=True, old="--margin-m", help="White border of the board beyond its squares, metres.")
@option("--dark-dropout", type=click.FloatRange(0.0, 1.0), default=0.0, show_default=True, help="Probability that a return on a dark square is lost.")
@option("--dark-bias-m", type=float, default=0.0, show_default=True, help="Range bias of the returns on dark squares, metres (positive: read too far).")
@option("--neighbour", is_flag=True, help="A panel beside the board, 3-8 cm from its edge and 1-4 cm behind its plane.")
@out_option("Recording folder to write (RADLOCC layout, with truth.yaml).", "simulate-calibration", "seed<seed>")
@friendly_errors
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
    out = write_recording(sim, out_folder(out_dir, "simulate-calibration", f"seed{seed}"), seed)
    click.echo(f"recording: {out} ({n_views} views, truth in {out / 'truth.yaml'})")


add_hidden_aliases(main, research.commands.values())
