"""Which input makes an estimate drift: runs of a simulated dataset with ingredients replaced by their truth.

Each ingredient is one source of error, taken out:

- ``tracks``: every matched pixel is replaced by the true projection of the ground point the track
  follows (the ground under its seed pixel, from the true camera pose at the seed frame, as
  :mod:`~dem_graph.studies.tracking_noise` defines it) plus white noise of ``sigma_px``; which
  points are matched, and when, stays the tracker's.
- ``laser``: the scans without range noise (the simulator's noiseless ranges); a laser point's
  position and the pixel its patch is cut at are then the true ones, up to the pose it is placed with.
- ``odometry``: every increment exact (from the true trajectory), its stated covariance kept.

``laser`` and ``odometry`` are datasets of their own (:func:`truth_dataset`: the images, camera
times and truth linked, the changed stream written); ``tracks`` instruments the front end of the run
(:class:`TrueTracks`). A row gives the signed height and pitch error at the end, which say whether
the drift goes one way, and the ATE and DEM error it makes (:func:`ablation_row`). The runs ignore a
simulated IMU (``motion.use_imu: false``), whose noise no ingredient takes out.
"""

from __future__ import annotations

import math
import os
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
import yaml
from scipy.spatial.transform import Rotation

from dem_graph.datasets.folder import LASER_NPZ, ODOMETRY_NPZ, FolderSequence
from dem_graph.errors import DatasetError, DemGraphError
from dem_graph.evaluation.timing import format_table
from dem_graph.frontend.tracker import TrackStatus
from dem_graph.geometry.se3 import invert
from dem_graph.pipeline.config import RunConfig, merge_settings, run_config
from dem_graph.pipeline.run import run_estimator
from dem_graph.sim.config import ScenarioConfig
from dem_graph.sim.pipeline import SCENARIO_YAML
from dem_graph.sim.simulator import SimulatedSequence
from dem_graph.studies.grid import LOCAL, GridJob, JobFailure, run_grid
from dem_graph.studies.headline import headline
from dem_graph.studies.study import mean_or_nan, standard_error, write_rows_csv

INGREDIENTS = ("tracks", "laser", "odometry")
DATASET_INGREDIENTS = ("laser", "odometry")  # those that make a dataset of their own


def parse_ingredients(text: str) -> tuple[str, ...]:
    """``"tracks,laser"`` as ingredients, in :data:`INGREDIENTS`' order; ``"none"`` or empty: none."""
    names = [n.strip() for n in text.split(",") if n.strip() and n.strip() != "none"]
    unknown = [n for n in names if n not in INGREDIENTS]
    if unknown:
        raise DemGraphError(f"unknown ingredient {', '.join(map(repr, unknown))}: choose from {', '.join(INGREDIENTS)} (or none)")
    return tuple(n for n in INGREDIENTS if n in names)


def _scenario_of(folder: Path) -> ScenarioConfig:
    path = folder / SCENARIO_YAML
    if not path.is_file():
        raise DatasetError(path, "not found: replacing an ingredient by its truth needs a simulated dataset (dem-graph simulate writes it)")
    try:
        return ScenarioConfig.model_validate(yaml.safe_load(path.read_text()))
    except (yaml.YAMLError, ValueError) as exc:
        raise DatasetError(path, f"not a scenario: {str(exc).splitlines()[0]}") from None


def truth_dataset(folder: str | Path, out: str | Path, ingredients) -> Path:
    """``folder`` (a simulated dataset) in ``out`` with the :data:`DATASET_INGREDIENTS` among
    ``ingredients`` replaced by their truth; every other file linked, not copied."""
    folder, out = Path(folder), Path(out)
    wanted = [i for i in ingredients if i in DATASET_INGREDIENTS]
    sim = SimulatedSequence.from_config(_scenario_of(folder))
    out.mkdir(parents=True, exist_ok=True)
    for p in folder.iterdir():
        q = out / p.name
        if p.name in (LASER_NPZ, ODOMETRY_NPZ) or q.exists() or q.is_symlink():
            continue
        os.symlink(p.resolve(), q)
    for name, ingredient in ((LASER_NPZ, "laser"), (ODOMETRY_NPZ, "odometry")):
        target = out / name
        if target.exists() or target.is_symlink():
            target.unlink()
        if ingredient not in wanted:
            if (folder / name).exists():
                os.symlink((folder / name).resolve(), target)
            continue
        with np.load(folder / name) as z:
            stream = {k: z[k] for k in z.files}
        if ingredient == "laser":
            clean = np.array(list(sim.noiseless_scans()), dtype=np.float32)
            if clean.shape != stream["ranges_m"].shape:
                raise DatasetError(folder / name, f"ranges of shape {stream['ranges_m'].shape}, its scenario gives {clean.shape}: not the dataset of {SCENARIO_YAML}")
            stream["ranges_m"] = clean
        else:
            T_prev = sim.world.motion.T_world_body(stream["t_prev_s"])
            T_curr = sim.world.motion.T_world_body(stream["t_s"])
            stream["T_prev_curr"] = np.einsum("nij,njk->nik", invert(T_prev), T_curr)
        np.savez(target, **stream)
    return out


class TrueTracks:
    """Instruments a front end so that every matched pixel is the true projection of its point plus
    white noise of ``sigma_px`` (``rng`` seeded: the same run gives the same noise, and a run with
    another sigma gets the same draws scaled). A point whose ray misses the terrain, or whose true
    projection leaves the image, keeps the tracker's pixel (``kept_tracker`` counts them)."""

    def __init__(self, frontend, sequence, sigma_px: float, seed: int = 0):
        from dem_graph.sim.raycast import TerrainScene

        truth = sequence.ground_truth
        if truth is None or truth.elevation is None:
            raise DemGraphError(f"{sequence.name}: true tracks need the true terrain (a simulated dataset)")
        self.trajectory = truth.trajectory
        self.scene = TerrainScene(truth.elevation)
        self.camera = sequence.rig.camera_model
        self.T_body_cam = np.asarray(sequence.rig.T_body_cam, dtype=float)
        self.sigma_px = float(sigma_px)
        self.rng = np.random.default_rng(seed)
        self.X_world: dict[int, np.ndarray] = {}
        self.replaced = 0
        self.kept_tracker = 0
        self._wrap(frontend)

    def _T_world_cam(self, t_s: float) -> np.ndarray:
        return self.trajectory.at(np.array([t_s]))[0] @ self.T_body_cam

    def _seed(self, point_id: int, uv, t_s: float) -> None:
        T = self._T_world_cam(t_s)
        d = T[:3, :3] @ self.camera.bearings_from_pixels(np.asarray(uv, dtype=float)[None])[0]
        t_hit = float(np.asarray(self.scene.cast(T[:3, 3][None].astype(np.float32), d[None].astype(np.float32)).t_hit_m)[0])
        if math.isfinite(t_hit):
            self.X_world[point_id] = T[:3, 3] + t_hit * d

    def true_pixel(self, point_id: int, t_s: float) -> np.ndarray | None:
        """The point's true projection at ``t_s`` plus the noise; None when it has none."""
        X = self.X_world.get(point_id)
        if X is None:
            return None
        T = invert(self._T_world_cam(t_s))
        uv, in_front = self.camera.project((T[:3, :3] @ X + T[:3, 3])[None])
        if not in_front[0] or not self.camera.in_image(uv, 0.0)[0]:
            return None
        return uv[0] + self.sigma_px * self.rng.standard_normal(2)

    def _replace(self, point_id: int, t_s: float):
        uv = self.true_pixel(point_id, t_s)
        if uv is None:
            self.kept_tracker += 1
        else:
            self.replaced += 1
        return uv

    def _wrap(self, fe) -> None:
        register, track, track_many = fe._register, fe.track, fe.track_many

        def _register(kind, image, uv, t_s, T_world_cam):
            point_id = register(kind, image, uv, t_s, T_world_cam)
            if point_id is not None:
                self._seed(point_id, uv, t_s)
            return point_id

        def _track(image, point_id, template, uv_pred, S_px2=None, half_size_px=None, t_s=0.0, T_world_cam=None):
            result = track(image, point_id, template, uv_pred, S_px2=S_px2, half_size_px=half_size_px, t_s=t_s, T_world_cam=T_world_cam)
            if result.status is TrackStatus.OK and (uv := self._replace(point_id, t_s)) is not None:
                return replace(result, uv_px=uv)
            return result

        def _track_many(image, point_ids, templates, uv_pred, S_px2=None, half_size_px=None, t_s=0.0, T_world_cam=None):
            batch = track_many(image, point_ids, templates, uv_pred, S_px2=S_px2, half_size_px=half_size_px, t_s=t_s, T_world_cam=T_world_cam)
            for i, point_id in enumerate(np.asarray(point_ids).tolist()):
                if batch.ok[i] and (uv := self._replace(point_id, t_s)) is not None:
                    batch.uv_px[i] = uv
            return batch

        fe._register, fe.track, fe.track_many = _register, _track, _track_many


@dataclass(frozen=True)
class AblationRow:
    dataset: str
    estimator: str
    ingredients: str  # replaced by their truth, comma-separated ("none": the dataset as it is)
    sigma_px: float  # white noise on the true tracks (NaN without them)
    final_height_error_m: float  # signed, estimate minus truth
    final_pitch_error_deg: float  # signed, about the body's y axis (negative: nose up, body x forward and z up)
    ate_m: float
    dem_rmse_m: float  # over the laser cells
    status: str = "ok"


def ablation_row(
    folder: str | Path, estimator: str, ingredients=(), sigma_px: float = 0.2, work_dir: str | Path | None = None, settings: dict | None = None
) -> AblationRow:
    """One run of ``estimator`` on the simulated dataset ``folder`` with ``ingredients`` replaced by
    their truth (the dataset ones written under ``work_dir``, default beside ``folder``);
    ``settings``: run settings over the dataset's (as a ``--config`` file would give them)."""
    folder = Path(folder)
    ingredients = tuple(i for i in INGREDIENTS if i in ingredients)
    data = folder
    on_disk = [i for i in ingredients if i in DATASET_INGREDIENTS]
    if on_disk:
        data = Path(work_dir or folder.parent) / f"{folder.name}_true_{'_'.join(on_disk)}"
        truth_dataset(folder, data, on_disk)
    sequence = FolderSequence(data)
    config = run_config(sequence).model_copy(update={"estimator": estimator}, deep=True)
    config.motion.use_imu = False  # the ingredients are the camera's, the laser's and the odometry's: an IMU's noise would stay in every row
    if settings:
        config = RunConfig.model_validate(merge_settings(config.model_dump(), settings))
    instrument = (lambda pipeline: TrueTracks(pipeline.estimator.frontend, sequence, sigma_px)) if "tracks" in ingredients else None
    run = run_estimator(sequence, config, instrument=instrument)
    est = run.estimator
    label = ",".join(ingredients) or "none"
    sigma = sigma_px if "tracks" in ingredients else math.nan
    if not est.frames:
        return AblationRow(folder.name, estimator, label, sigma, math.nan, math.nan, math.nan, math.nan, f"failed: {run.error}")
    T_est = est.frames[-1].T_world_body
    T_true = sequence.ground_truth.trajectory.at(np.array([est.frames[-1].t_s]))[0]
    pitch = Rotation.from_matrix(T_true[:3, :3].T @ T_est[:3, :3]).as_rotvec()[1]
    h = headline(run.metrics)
    return AblationRow(
        folder.name, estimator, label, sigma, h["final_height_error_m"], float(np.degrees(pitch)), h["ate_anchored_rmse_m"],
        h["dem_rmse_laser_cells_m"], "ok" if run.error is None else f"stopped: {run.error}",
    )


def ablation_job(folder: str, estimator: str, ingredients: list[str], sigma_px: float, work_dir: str) -> dict:
    """:func:`ablation_row` as a grid job (its fields as a dict)."""
    return asdict(ablation_row(folder, estimator, tuple(ingredients), sigma_px, work_dir))


@dataclass
class AblationResult:
    rows: list[AblationRow]

    def summary(self) -> list[tuple[str, int, float, float, float, float]]:
        """Per set of ingredients (in the order they ran): runs, mean signed end height error, its
        standard error, mean end pitch error, mean DEM RMSE."""
        out = []
        for label in dict.fromkeys(r.ingredients for r in self.rows):
            ok = [r for r in self.rows if r.ingredients == label and math.isfinite(r.final_height_error_m)]
            dz = [r.final_height_error_m for r in ok]
            dem = [r.dem_rmse_m for r in ok if math.isfinite(r.dem_rmse_m)]
            out.append((label, len(ok), mean_or_nan(dz), standard_error(dz), mean_or_nan([r.final_pitch_error_deg for r in ok]), mean_or_nan(dem)))
        return out

    def table(self) -> str:
        rows = [
            [r.dataset, r.estimator, r.ingredients, f"{r.sigma_px:g}", f"{r.final_height_error_m:+.3f}", f"{r.final_pitch_error_deg:+.2f}", f"{r.ate_m:.3f}", f"{100 * r.dem_rmse_m:.1f}", r.status]
            for r in self.rows
        ]
        headers = ["dataset", "estimator", "true ingredients", "sigma px", "end height error (m)", "end pitch error (deg)", "ATE (m)", "DEM RMSE (cm)", "status"]
        lines = [format_table(headers, rows, title="ablation: ingredients replaced by their truth")]
        for label, n, dz, se, pitch, dem in self.summary():
            t = dz / se if se > 0 else math.nan
            spread = f" +- {se:.3f} m (mean, standard error; {t:+.1f} standard errors from 0)" if math.isfinite(se) else " m"
            lines.append(f"{label}: {n} runs, end height error {dz:+.3f}{spread}, pitch {pitch:+.2f} deg, DEM {100 * dem:.1f} cm")
        return "\n".join(lines)

    def write_csv(self, path: str | Path) -> Path:
        return write_rows_csv(path, AblationRow, self.rows)


def ablation_study(
    folders, estimator: str = "isam2-batch", conditions=((), ("tracks",), ("laser",), ("odometry",)), sigma_px: float = 0.2,
    work_dir: str | Path | None = None, scheduler: str = LOCAL, n_workers: int | None = None,
) -> AblationResult:
    """Every condition (a set of ingredients replaced by their truth; () is the dataset as it is) on
    every simulated dataset folder, as a grid (:func:`~dem_graph.studies.grid.run_grid`, kept and
    resumed in ``work_dir/ablation_results``; the datasets with true laser or odometry go to
    ``work_dir``, default the first folder's parent)."""
    folders = [Path(f) for f in folders]
    if not folders:
        raise DemGraphError("an ablation needs at least one simulated dataset folder")
    work_dir = Path(work_dir or folders[0].parent)
    jobs, where = [], {}
    for folder in folders:
        for condition in conditions:
            ingredients = [i for i in INGREDIENTS if i in condition]
            label = "_".join(ingredients) or "none"
            key = f"ablation_{folder.name}_{estimator}_{label}" + (f"_{sigma_px:g}px" if "tracks" in ingredients else "")
            where[key] = (folder.name, ",".join(ingredients) or "none", sigma_px if "tracks" in ingredients else math.nan)
            jobs.append(GridJob(key, ablation_job, (str(folder), estimator, ingredients, float(sigma_px), str(work_dir))))
    done = run_grid(jobs, work_dir / "ablation_results", scheduler, n_workers, desc="ablation")
    rows = []
    for key, (name, label, sigma) in where.items():
        result = done[key]
        if isinstance(result, JobFailure):
            rows.append(AblationRow(name, estimator, label, sigma, math.nan, math.nan, math.nan, math.nan, f"failed: {result.error}"))
        else:
            rows.append(AblationRow(**result))
    return AblationResult(rows)


__all__ = [
    "DATASET_INGREDIENTS",
    "INGREDIENTS",
    "AblationResult",
    "AblationRow",
    "TrueTracks",
    "ablation_job",
    "ablation_row",
    "ablation_study",
    "parse_ingredients",
    "truth_dataset",
]
