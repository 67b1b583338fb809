"""``simulate``: a scenario to a dataset folder on disk, with its preview picture."""

from __future__ import annotations

import logging
import shutil
import time
from dataclasses import dataclass
from pathlib import Path

import yaml

from dem_graph.datasets.events import CameraFrame, LaserScan
from dem_graph.datasets.folder import write_folder_dataset
from dem_graph.errors import DatasetError
from dem_graph.sim.config import ScenarioConfig
from dem_graph.sim.simulator import SimulatedSequence

log = logging.getLogger(__name__)

SCENARIO_YAML = "scenario.yaml"
PREVIEW_PNG = "preview.png"


@dataclass(frozen=True)
class SimulationResult:
    out_dir: Path
    preview_png: Path | None
    n_frames: int
    n_scans: int
    n_odometry: int
    n_imu: int
    length_m: float
    duration_s: float
    elapsed_s: float


def simulate(config: ScenarioConfig, out_dir: str | Path, overwrite: bool = False, preview: bool = True) -> SimulationResult:
    """Simulate ``config`` and write it as a dataset folder (see ``docs/dataset_format.md``) in ``out_dir``,
    with the effective scenario in ``scenario.yaml`` and a picture in ``preview.png``."""
    out_dir = Path(out_dir)
    if out_dir.exists() and any(out_dir.iterdir()):
        if not overwrite:
            raise DatasetError(out_dir, "output folder exists and is not empty (use overwrite)")
        shutil.rmtree(out_dir)
    start = time.perf_counter()
    sequence = SimulatedSequence.from_config(config)
    write_folder_dataset(sequence, out_dir, progress_desc=f"simulating {config.name}", description=f"simulated scenario '{config.name}', seed {config.seed}")
    (out_dir / SCENARIO_YAML).write_text(yaml.safe_dump(config.model_dump(mode="json"), sort_keys=False, default_flow_style=None))
    elapsed = time.perf_counter() - start
    png = None
    if preview:
        from dem_graph.viz.preview import dataset_preview

        times = sequence.camera_times()
        t_frame = float(times[len(times) // 3])
        frame = CameraFrame(t_frame, sequence.renderer.render(sequence.world.motion.T_world_body(t_frame) @ sequence.rig.T_body_cam), len(times) // 3)
        scans = [LaserScan(float(t), r) for t, r in zip(sequence.laser_times(), sequence.noiseless_scans())]
        png = dataset_preview(sequence, out_dir / PREVIEW_PNG, frame, scans)
    gt = sequence.ground_truth.trajectory
    return SimulationResult(
        out_dir=out_dir,
        preview_png=png,
        n_frames=len(sequence.camera_times()),
        n_scans=len(sequence.laser_times()),
        n_odometry=len(sequence.odometry_times()),
        n_imu=len(sequence.imu_times()),
        length_m=gt.path_length_m,
        duration_s=gt.duration_s,
        elapsed_s=elapsed,
    )
