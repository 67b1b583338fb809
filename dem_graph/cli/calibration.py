"""``calibrate``: the camera-laser extrinsics from checkerboard views, and what it and
``research simulate-calibration`` share (the board's corners)."""

from __future__ import annotations

from pathlib import Path

import click

from dem_graph.cli.options import option
from dem_graph.cli.out_folder import name_of, out_folder, out_option
from dem_graph.cli.root import friendly_errors, main

_ROSBAG_OPTIONS = ("image_topic", "scan_topic", "camera_info_topic", "intrinsics_path")


def board_corners(ctx, param, text: str | None):
    """``COLSxROWS`` inner corners, both at least 2 (a click callback)."""
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


def _angle_window(text: str | None):
    """``"A,B"`` degrees as a (low, high) pair of radians; None for None."""
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


def _calibration_board(recording_board, corners, square_m):
    """The recording's board with ``--board`` / ``--square-m`` in place of its parts; None when a part is unknown."""
    from dem_graph.calibration.board import BoardSpec

    cols, rows = corners if corners else (recording_board.cols, recording_board.rows) if recording_board else (None, None)
    square = square_m if square_m is not None else recording_board.square_m if recording_board else None
    return BoardSpec(cols, rows, square) if cols is not None and square is not None else None


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


def _print_calibration(result, report: dict, paths: dict) -> None:
    """The calibration's figures, one line each, and where they were written."""
    import numpy as np

    used = sum(v.used for v in result.views)
    click.echo(f"T_cam_laser from {used} of {len(result.views)} views:\n{np.array2string(result.T_cam_laser, precision=4, suppress_small=True)}")
    click.echo(f"sigma rot (deg): {np.round(result.sigma_rot_deg, 3).tolist()}, sigma trans (mm): {np.round(result.sigma_trans_mm, 1).tolist()}")
    click.echo(result.noise.summary())
    click.echo(result.dark.summary())
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


@main.command(short_help="T_cam_laser from checkerboard views; a rig.")
@click.argument("recording", type=click.Path(path_type=Path))
@option(
    "--format", "layout", type=click.Choice(["radlocc", "rosbag"]), default="radlocc", show_default=True, group="Input",
    help="Layout of the recording: a RADLOCC folder, or a ROS 1 or ROS 2 bag.",
)
@option("--rig", "rig_path", type=click.Path(dir_okay=False, path_type=Path), default=None, group="Input", help="Rig YAML to update [default: one made from the recording's intrinsics and scans].")
@option(
    "--intrinsics", "intrinsics_path", type=click.Path(dir_okay=False, path_type=Path), default=None, group="Input",
    help="Intrinsics file: OpenCV XML/YAML or (radlocc only) the MATLAB toolbox's Calib_Results.mat; rosbag: instead of --camera-info-topic "
    "[radlocc default: xml/out_camera_data.xml, else Calib_Results.mat in the folder or data/].",
)
@option("--image-topic", default=None, group="ROS bag", help="sensor_msgs/Image or CompressedImage topic.")
@option("--scan-topic", default=None, group="ROS bag", help="sensor_msgs/LaserScan topic.")
@option("--camera-info-topic", default=None, group="ROS bag", help="sensor_msgs/CameraInfo topic with the intrinsics (or give --intrinsics).")
@option("--board", "board_corners", default=None, callback=board_corners, group="Board", help="Inner corners of the checkerboard, COLSxROWS, e.g. 9x6 [default: from the intrinsics file].")
@option("--square-m", type=click.FloatRange(min=0.0, min_open=True), default=None, group="Board", help="Side of the checkerboard's squares, metres [default: from the intrinsics file].")
@option("--board-margin-m", type=click.FloatRange(min=0.0), default=None, group="Board", help="How far the board extends beyond its outer squares, metres [default: half a square].")
@option("--window-deg", default=None, group="Scans", help="Search the board only between these beam angles, degrees, as A,B.")
@option("--max-dt-s", type=float, default=0.05, show_default=True, group="Scans", help="Longest time between an image and its scan, seconds.")
@option(
    "--range-sigma-m", type=click.FloatRange(min=0.0, min_open=True), default=None, group="Scans",
    help="Range noise of the scanner, metres: a starting value; the residuals decide (a warning when they disagree by more than 2x) [default: from the scans].",
)
@option("--fix-range-sigma", is_flag=True, group="Scans", help="Hold --range-sigma-m instead of estimating the noise from the residuals.")
@option("--plane-tol-m", type=click.FloatRange(min=0.0, min_open=True), default=None, group="Scans", help="Farthest an on-board return may lie from the board's plane, metres [default: 4 sigma of the range noise].")
@option("--dark-bias/--no-dark-bias", default=True, show_default=True, group="Scans", help="Estimate and remove the range bias of returns on dark squares.")
@option("--jackknife/--no-jackknife", default=True, show_default=True, group="Scans", help="Also the leave-one-pose-out spread of the estimate.")
@option("--camera-height-m", type=click.FloatRange(min=0.0, min_open=True), default=None, group="Body (without --rig)", help="The camera's height above the ground, metres (with --camera-pitch-deg: T_body_cam).")
@option("--camera-pitch-deg", type=click.FloatRange(-90.0, 90.0), default=None, group="Body (without --rig)", help="The camera's pitch below the horizontal, degrees (positive: looking down).")
@out_option("Folder for rig.yaml, calibration.json and views/.", "calibrate", "<recording>", group="Output")
@friendly_errors
def calibrate(
    recording, layout, rig_path, intrinsics_path, image_topic, scan_topic, camera_info_topic, board_corners, square_m, board_margin_m, window_deg, max_dt_s,
    range_sigma_m, fix_range_sigma, plane_tol_m, dark_bias, jackknife, camera_height_m, camera_pitch_deg, out_dir,
) -> None:
    """Estimate T_cam_laser from checkerboard views and write the rig with it."""
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
    paths = write_calibration(result, data, rig, out_folder(out_dir, "calibrate", name_of(recording)), max_dt_s)
    _print_calibration(result, result.to_dict(), paths)
