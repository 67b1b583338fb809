"""TUM trajectory text files: one pose ``t tx ty tz qx qy qz qw`` per line.

``t`` is in seconds, ``tx ty tz`` is the body position in the world frame (metres) and
``qx qy qz qw`` the body orientation (unit quaternion, scalar last), so each line is one
``T_world_body``. Lines starting with ``#`` are comments; blank lines are ignored. Columns are
separated by single spaces when written (any whitespace when read).

Numbers are written with Python's shortest round-trip ``repr``, so ``read_tum(write_tum(x))``
reproduces every float bit for bit. The files are readable by ``evo``.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from dem_graph.errors import DatasetError, DemGraphError
from dem_graph.geometry.trajectory import Trajectory

_HEADER = "# t tx ty tz qx qy qz qw"
_N_COLUMNS = 8
_QUAT_NORM_TOL = 1e-3  # the tolerance Trajectory itself accepts


def read_tum(path: str | Path) -> Trajectory:
    """Read a TUM trajectory file.

    Raises :class:`DatasetError` naming the file (and the line, where there is one) when the file
    is missing or unreadable, a line does not hold 8 numbers, a value is NaN or infinite, a
    quaternion is not unit length, times do not strictly increase, or there is no pose at all.
    """
    path = Path(path)
    if not path.is_file():
        raise DatasetError(path, "file not found" if not path.exists() else "not a regular file")
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise DatasetError(path, "not a text file") from None
    except OSError as exc:
        raise DatasetError(path, f"cannot read ({exc.strerror or exc})") from None

    rows: list[list[float]] = []
    previous_t: float | None = None
    for line_no, line in enumerate(text.splitlines(), start=1):
        stripped = line.strip()
        if not stripped or stripped.startswith("#"):
            continue
        tokens = stripped.split()
        if len(tokens) != _N_COLUMNS:
            raise DatasetError(
                path, f"line {line_no}: expected {_N_COLUMNS} columns (t tx ty tz qx qy qz qw), got {len(tokens)}"
            )
        values = []
        for token in tokens:
            try:
                values.append(float(token))
            except ValueError:
                raise DatasetError(path, f"line {line_no}: not a number: {token!r}") from None
        if not all(math.isfinite(v) for v in values):
            raise DatasetError(path, f"line {line_no}: NaN or infinite value in the pose")
        t = values[0]
        if previous_t is not None and not t > previous_t:
            raise DatasetError(
                path,
                f"line {line_no}: time {t!r} is not after the previous time {previous_t!r} "
                "(times must be strictly increasing)",
            )
        norm = math.sqrt(sum(v * v for v in values[4:]))
        if abs(norm - 1.0) > _QUAT_NORM_TOL:
            raise DatasetError(path, f"line {line_no}: quaternion is not unit length (norm {norm:.6g})")
        previous_t = t
        rows.append(values)

    if not rows:
        raise DatasetError(path, "empty: the file holds no pose")
    data = np.array(rows, dtype=float)
    try:
        return Trajectory(data[:, 0], data[:, 1:4], data[:, 4:8])
    except DemGraphError as exc:  # the checks above should already catch everything it rejects
        raise DatasetError(path, str(exc)) from None


def _format_float(value: float) -> str:
    return repr(float(value))


def write_tum(path: str | Path, trajectory: Trajectory) -> None:
    """Write ``trajectory`` as a TUM file, numbers repr-exact. Raises :class:`DatasetError` if it cannot."""
    path = Path(path)
    data = np.concatenate(
        [trajectory.t_s[:, None], trajectory.positions_xyz, trajectory.orientations_quat_xyzw], axis=1
    )
    lines = [_HEADER]
    lines.extend(" ".join(_format_float(v) for v in row) for row in data.tolist())
    try:
        path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    except OSError as exc:
        raise DatasetError(path, f"cannot write ({exc.strerror or exc})") from None
