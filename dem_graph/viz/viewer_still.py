"""A still of the viewer's 3D view, drawn with matplotlib from a recording (rerun has no headless
renderer): what :class:`~dem_graph.viz.rerun_viewer.RerunViewer` logged, read back with rerun's
reader, at one time.

Drawn: the whole live map as last logged at or before the time (its surface, the viewer's own
vertex colours), the focus area's outline placed with its heading frame, the returns of the
latest scan, the estimated trajectory and, where the recording has it, the true one.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dem_graph.errors import DemGraphError
from dem_graph.viz.rerun_viewer import ESTIMATE_COLOR, LASER_COLOR, TRUTH_COLOR, recording_column, recording_rows


def _at(rows: list[tuple[float, np.ndarray]], t_s: float) -> np.ndarray | None:
    """The latest row at or before ``t_s`` (a static row has time 0), None if there is none."""
    before = [values for t, values in rows if t <= t_s + 1e-9]
    return before[-1] if before else None


def unpack_rgba(packed: np.ndarray) -> np.ndarray:
    """(N,4) floats in [0, 1] from rerun's colours packed as 0xRRGGBBAA."""
    p = np.asarray(packed, dtype=np.uint64).ravel()
    return np.stack([(p >> 24) & 255, (p >> 16) & 255, (p >> 8) & 255, p & 255], axis=1).astype(float) / 255.0


def map_surface_at(path: str | Path, t_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The whole map as the recording ``path`` held it at ``t_s``: each tile's latest surface at or
    before then, joined: vertices (N,3) world metres, triangles (M,3) int, colours (N,4) in [0, 1]."""
    tiles = sorted(e.lstrip("/") for e in recording_rows(path) if e.startswith("/world/map/tiles/"))
    vertices, triangles, colours = [np.zeros((0, 3))], [np.zeros((0, 3), dtype=int)], [np.zeros((0, 4))]
    offset = 0
    for tile in tiles:
        v = _at(recording_column(path, tile, "Mesh3D:vertex_positions"), t_s)
        if v is None or not len(v):
            continue
        vertices.append(v)
        triangles.append(_at(recording_column(path, tile, "Mesh3D:triangle_indices"), t_s).astype(int) + offset)
        colours.append(unpack_rgba(_at(recording_column(path, tile, "Mesh3D:vertex_colors"), t_s)))
        offset += len(v)
    return np.concatenate(vertices), np.concatenate(triangles), np.concatenate(colours)


def recording_still(
    path: str | Path, t_s: float, out_png: str | Path, title: str | None = None, half_extent_m: float = 5.0, elev_deg: float = 35.0, azim_deg: float = -120.0,
) -> Path:
    """Draw the 3D view of the recording ``path`` at ``t_s`` (seconds on its ``time`` timeline)
    into ``out_png``, over the square of ``half_extent_m`` around the focus area's heading frame
    moved 2 m ahead (the whole map when the recording has no focus area); returns the file.
    :class:`DemGraphError` when no map surface was logged by then."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    vertices, triangles, colours = map_surface_at(path, t_s)
    if not len(vertices):
        raise DemGraphError(f"{path}: no map surface logged at or before {t_s:.3f} s")
    translation = _at(recording_column(path, "world/focus", "Transform3D:translation"), t_s)
    rotation = _at(recording_column(path, "world/focus", "Transform3D:mat3x3"), t_s)
    outline = _at(recording_column(path, "world/focus/outline", "LineStrips3D:strips"), t_s)
    has_focus = translation is not None and rotation is not None and outline is not None
    if has_focus:
        R_world_local = rotation.reshape(3, 3).T  # rerun keeps a 3x3 matrix column by column
        centre_xy = (translation.ravel() + 2.0 * R_world_local[:, 0])[:2]
    else:
        centre_xy = (vertices[:, :2].min(axis=0) + vertices[:, :2].max(axis=0)) / 2.0
        half_extent_m = float(np.ptp(vertices[:, :2], axis=0).max()) / 2.0

    def inside(xyz: np.ndarray) -> np.ndarray:
        return np.all(np.abs(xyz[..., :2] - centre_xy) <= half_extent_m, axis=-1)

    fig = plt.figure(figsize=(9.0, 6.0), dpi=120)
    ax = fig.add_subplot(projection="3d")
    faces = vertices[triangles]
    shown = np.all(inside(faces), axis=1)
    ax.add_collection3d(Poly3DCollection(faces[shown], facecolors=colours[triangles[shown]].mean(axis=1), edgecolors="none"))
    if has_focus:
        ring = outline.reshape(-1, 3) @ R_world_local.T + translation.ravel()
        ax.plot(ring[:, 0], ring[:, 1], ring[:, 2] + 0.02, color="black", linewidth=1.5, label="focus area")
    scan = _at(recording_column(path, "world/scan", "Points3D:positions"), t_s)
    scan = scan[inside(scan)] if scan is not None else None
    if scan is not None and len(scan):
        ax.scatter(scan[:, 0], scan[:, 1], scan[:, 2] + 0.01, s=2.0, color=np.array(LASER_COLOR) / 255.0, depthshade=False, label="latest scan's returns")
    for entity, colour, label in (("world/truth", TRUTH_COLOR, "true path"), ("world/trajectory", ESTIMATE_COLOR, "estimated path")):
        path_xyz = _at(recording_column(path, entity, "LineStrips3D:strips"), t_s)
        if path_xyz is not None and len(path_xyz):
            p = path_xyz.reshape(-1, 3)
            p = p[inside(p)]
            ax.plot(p[:, 0], p[:, 1], p[:, 2], color=np.array(colour) / 255.0, linewidth=1.5, label=label)
    z = faces[shown][..., 2] if shown.any() else vertices[:, 2]
    z_lo, z_hi = np.percentile(z, [1, 99])
    ax.set_xlim(centre_xy[0] - half_extent_m, centre_xy[0] + half_extent_m)
    ax.set_ylim(centre_xy[1] - half_extent_m, centre_xy[1] + half_extent_m)
    ax.set_zlim(z_lo - 0.3, z_hi + 0.5)
    ax.set_box_aspect((1.0, 1.0, 0.35))
    ax.view_init(elev=elev_deg, azim=azim_deg)
    ax.set_xlabel("x (m, world)")
    ax.set_ylabel("y (m, world)")
    ax.set_zlabel("z (m)")
    ax.legend(loc="upper left", fontsize=8)
    ax.set_title(title or f"the viewer's 3D view at t = {t_s:.2f} s (drawn from the recording)", fontsize=10)
    out = Path(out_png)
    fig.savefig(out, bbox_inches="tight")
    plt.close(fig)
    return out


__all__ = ["map_surface_at", "recording_still", "unpack_rgba"]
