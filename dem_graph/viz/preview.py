"""A one-page picture of a dataset: the terrain and path from above, and a camera frame with a laser scan on it."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dem_graph.datasets.base import Sequence
from dem_graph.datasets.events import CameraFrame, LaserScan
from dem_graph.geometry.se3 import invert, transform_points


def _laser_points_world(sequence: Sequence, scans: list[LaserScan], max_range_m: float = np.inf) -> np.ndarray:
    """The returns of ``scans`` (up to ``max_range_m``) in the world frame, placed with the ground-truth poses."""
    rig, gt = sequence.rig, sequence.ground_truth.trajectory
    dirs = rig.laser.beam_directions()
    points = []
    for scan in scans:
        ok = rig.laser.valid_ranges(scan.ranges_m, max_range_m)
        p_laser = dirs[ok] * scan.ranges_m[ok, None]
        points.append(transform_points(gt.at(scan.t_s) @ rig.T_body_laser, p_laser))
    return np.concatenate(points) if points else np.zeros((0, 3))


def dataset_preview(sequence: Sequence, out_png: str | Path, frame: CameraFrame, scans: list[LaserScan]) -> Path:
    """Write ``out_png``: left, the ground truth from above (relief, path, laser returns); right,
    ``frame`` with the returns of the scan nearest in time projected through the ground truth."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import LightSource

    gt = sequence.ground_truth
    rig = sequence.rig
    fig, (ax_map, ax_img) = plt.subplots(1, 2, figsize=(15, 6.5), gridspec_kw={"width_ratios": [1.0, 1.15]})

    xy = gt.trajectory.positions_xyz[:, :2] if gt is not None else np.zeros((1, 2))
    if gt is not None and gt.elevation is not None:
        g = gt.elevation.geometry
        lo, hi = xy.min(axis=0) - 6.0, xy.max(axis=0) + 6.0
        row_lo, col_lo, _ = g.cell_index(lo[0], hi[1])
        row_hi, col_hi, _ = g.cell_index(hi[0], lo[1])
        r0, r1 = max(int(row_lo), 0), min(int(row_hi) + 1, g.n_rows)
        c0, c1 = max(int(col_lo), 0), min(int(col_hi) + 1, g.n_cols)
        z = np.asarray(gt.elevation.z_m[r0:r1, c0:c1], dtype=float)
        step = max(1, int(np.ceil(max(z.shape) / 1500)))
        z = z[::step, ::step]
        extent = (g.x_min_m + c0 * g.resolution_m, g.x_min_m + c1 * g.resolution_m, g.y_max_m - r1 * g.resolution_m, g.y_max_m - r0 * g.resolution_m)
        shaded = LightSource(azdeg=315, altdeg=40).shade(z, cmap=plt.get_cmap("terrain"), vert_exag=3.0, dx=g.resolution_m * step, dy=g.resolution_m * step, blend_mode="soft")
        ax_map.imshow(shaded, extent=extent, origin="upper", interpolation="bilinear")
        mappable = plt.cm.ScalarMappable(cmap="terrain", norm=plt.Normalize(np.nanmin(z), np.nanmax(z)))
        fig.colorbar(mappable, ax=ax_map, shrink=0.8, label="ground-truth elevation (m)")
    if gt is not None:
        ax_map.plot(xy[:, 0], xy[:, 1], color="black", lw=1.5, label="vehicle path (ground truth)")
        ax_map.plot(*xy[0], "o", color="lime", mec="black", ms=8, label="start")
        pts = _laser_points_world(sequence, scans[:: max(1, len(scans) // 300)], max_range_m=8.0)
        ax_map.scatter(pts[:, 0], pts[:, 1], s=0.2, c="red", alpha=0.35, label="laser returns within 8 m", rasterized=True)
        ax_map.legend(loc="upper right", fontsize=8)
        pad = 6.0
        ax_map.set_xlim(xy[:, 0].min() - pad, xy[:, 0].max() + pad)
        ax_map.set_ylim(xy[:, 1].min() - pad, xy[:, 1].max() + pad)
    ax_map.set_aspect("equal")
    ax_map.set_xlabel("x (m)")
    ax_map.set_ylabel("y (m)")
    ax_map.set_title(f"{sequence.name}: terrain, path and laser returns from above")

    image = frame.image if frame.image.ndim == 2 else frame.image[..., ::-1]
    ax_img.imshow(image, cmap="gray", vmin=0, vmax=255)
    if gt is not None and scans:
        scan = min(scans, key=lambda s: abs(s.t_s - frame.t_s))
        pts = _laser_points_world(sequence, [scan])
        T_cam_world = invert(gt.trajectory.at(frame.t_s) @ rig.T_body_cam)
        uv, in_front = rig.camera_model.project(transform_points(T_cam_world, pts))
        keep = in_front & rig.camera_model.in_image(uv)
        ax_img.scatter(uv[keep, 0], uv[keep, 1], s=4, c="red", label=f"laser scan at t={scan.t_s:.3f} s (ground-truth poses)")
        ax_img.legend(loc="lower right", fontsize=8)
    ax_img.set_title(f"camera frame {frame.index} at t={frame.t_s:.3f} s")
    ax_img.set_xlabel("u (px)")
    ax_img.set_ylabel("v (px)")
    fig.tight_layout()
    out_png = Path(out_png)
    fig.savefig(out_png, dpi=110)
    plt.close(fig)
    return out_png
