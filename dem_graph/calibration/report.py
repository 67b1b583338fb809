"""What a calibration writes: the rig with the new ``T_cam_laser``, ``calibration.json`` and one picture per view.

The picture of a view is its image with every laser return of its scan projected through the estimate:
returns on the board in green, the others in red, the board's corners in blue. A person sees at a glance
whether the green line lies across the board.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np

from dem_graph.calibration.laser_line import points_from_ranges
from dem_graph.calibration.readers import CalibrationRecording, pair_nearest
from dem_graph.calibration.result import CalibrationResult
from dem_graph.errors import DatasetError
from dem_graph.geometry.rig import SensorRig, save_rig, validated


def rig_from_recording(recording: CalibrationRecording, range_sigma_m: float = 0.02, source: str | Path | None = None, T_body_cam=None) -> SensorRig:
    """A rig with the recording's camera at ``T_body_cam`` (None: at the body origin, the body frame the
    camera's, which breaks the body convention of an origin on the ground, z up: ``dem-graph calibrate``
    asks for the camera's height and pitch instead) and its scanner's beams; ``T_cam_laser`` is the identity.

    Every value is validated as a rig file's would be: a bad one is a :class:`ConfigError` naming
    ``source`` (the recording) and the field."""
    intr, scans = recording.intrinsics, recording.scans
    K = np.asarray(intr.K, dtype=float)
    camera = {
        "width_px": int(intr.width_px),
        "height_px": int(intr.height_px),
        "fx_px": float(K[0, 0]),
        "fy_px": float(K[1, 1]),
        "cx_px": float(K[0, 2]),
        "cy_px": float(K[1, 2]),
        "distortion": [float(x) for x in intr.distortion],
        "T_body_cam": (np.eye(4) if T_body_cam is None else np.asarray(T_body_cam, dtype=float)).tolist(),
    }
    beams = {"kind": "planar", "angle_min_rad": float(scans.angle_min_rad), "angle_increment_rad": float(scans.angle_increment_rad), "count": int(scans.n_beams)}
    finite = scans.ranges_m[np.isfinite(scans.ranges_m)]
    range_max = float(max(finite.max() if finite.size else 30.0, 1.0))
    laser = {"T_body_laser": camera["T_body_cam"], "beams": beams, "range_max_m": range_max, "range_sigma_m": float(range_sigma_m)}
    return validated(SensorRig, {"camera": camera, "laser": laser}, source)


def rig_with_calibration(rig: SensorRig, result: CalibrationResult) -> SensorRig:
    """``rig`` with ``T_body_laser = T_body_cam @ T_cam_laser`` and :attr:`CalibrationResult.rig_covariance`; ``T_body_cam`` kept."""
    T_body_laser = rig.T_body_cam @ result.T_cam_laser
    laser = rig.laser.model_copy(update={"T_body_laser": T_body_laser.tolist()})
    return rig.model_copy(update={"laser": laser, "T_cam_laser_covariance": result.rig_covariance.tolist()})


def draw_view(image: np.ndarray, recording_ranges_m: np.ndarray, angles_rad: np.ndarray, on_board: np.ndarray, result: CalibrationResult, K, distortion, view: int) -> np.ndarray:
    """The view's image with its laser returns projected through ``result.T_cam_laser``."""
    out = image.copy() if image.ndim == 3 else cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    points = points_from_ranges(recording_ranges_m, angles_rad)
    finite = np.all(np.isfinite(points), axis=1)
    X = points @ result.T_cam_laser[:3, :3].T + result.T_cam_laser[:3, 3]
    front = finite & (np.nan_to_num(X[:, 2], nan=-1.0) > 0.05)
    mask = np.zeros(len(points), dtype=bool)
    mask[on_board] = True
    if np.any(front):
        uv, _ = cv2.projectPoints(X[front].reshape(-1, 1, 3), np.zeros(3), np.zeros(3), np.asarray(K, float), np.asarray(distortion, float))
        for (u, v), on in zip(uv.reshape(-1, 2), mask[front]):
            if -1e4 < u < 1e4 and -1e4 < v < 1e4:
                cv2.circle(out, (int(round(u)), int(round(v))), 2, (0, 200, 0) if on else (0, 0, 255), -1, cv2.LINE_AA)
    board = result.boards.get(view)
    if board is not None:
        for u, v in board.corners_px:
            cv2.circle(out, (int(round(u)), int(round(v))), 2, (255, 120, 0), 1, cv2.LINE_AA)
    report = result.views[view]
    text = f"{report.name}: {report.n_returns} returns on the board, rms {report.rms_mm:.1f} mm" if report.used else f"{report.name}: not used ({report.reason})"
    (w, h), base = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, 0.5, 1)
    cv2.rectangle(out, (4, 4), (12 + w, 12 + h + base), (0, 0, 0), -1)
    cv2.putText(out, text, (8, 8 + h), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA)
    return out


def write_calibration(result: CalibrationResult, recording: CalibrationRecording, rig: SensorRig, out_dir: str | Path, max_dt_s: float) -> dict[str, Path]:
    """Write ``rig.yaml``, ``calibration.json`` and ``views/view_NN.png`` (one per view whose board was found, NN the
    input's number for the image: RGB31.png gives view_31.png)."""
    out = Path(out_dir)
    views_dir = out / "views"
    try:
        views_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise DatasetError(out, f"cannot create the output folder ({exc.strerror or exc})") from None
    new_rig = rig_with_calibration(rig, result)
    save_rig(new_rig, out / "rig.yaml")
    (out / "calibration.json").write_text(json.dumps(result.to_dict(), indent=2))
    pairs = pair_nearest(recording.image_times_s, recording.scans.times_s, max_dt_s)
    K, dist = recording.intrinsics.K, recording.intrinsics.distortion
    for k in range(len(result.views)):
        if k not in result.boards or pairs[k] < 0:
            continue
        picture = draw_view(recording.load_image(k, color=True), recording.scans.ranges_m[pairs[k]], recording.scans.angles_rad, result.on_board.get(k, np.zeros(0, int)), result, K, dist, k)
        path = views_dir / f"view_{recording.view_numbers[k]:02d}.png"  # numbered as the input numbers its images
        if not cv2.imwrite(str(path), picture):
            raise DatasetError(path, "cannot write the picture")
    return {"rig": out / "rig.yaml", "report": out / "calibration.json", "views": views_dir}
