"""Reading numpy ``.npz`` archives with every failure a one-line :class:`DatasetError` naming the file."""

from __future__ import annotations

import zipfile
import zlib
from pathlib import Path

import numpy as np

from dem_graph.errors import DatasetError

# what numpy and zipfile raise on a truncated, corrupt or foreign file, at np.load or at reading an array
_READ_ERRORS = (OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error)


def _why(exc: BaseException) -> str:
    text = str(exc).splitlines()[0] if str(exc) else ""
    return text or type(exc).__name__


def read_npz(path: str | Path, required: tuple[str, ...], optional: tuple[str, ...] = (), prefix: str | None = None, missing_hint: str = "") -> dict[str, np.ndarray]:
    """The arrays ``required`` (all of them), ``optional`` (those present) and, when ``prefix`` is given,
    every array whose name starts with it, of the archive at ``path``.

    A missing file, a file that is not an npz archive, a missing required array or an array that cannot
    be decompressed is a :class:`DatasetError` naming the file (``missing_hint`` is added when the file
    does not exist). The file is opened here, so it is closed even when numpy fails half-way through."""
    path = Path(path)
    if not path.is_file():
        raise DatasetError(path, ("not found" if not path.exists() else "is not a regular file") + (f": {missing_hint}" if missing_hint else ""))
    try:
        with open(path, "rb") as f:
            try:
                archive = np.load(f, allow_pickle=False)
            except _READ_ERRORS as exc:
                raise DatasetError(path, f"not a readable npz archive ({_why(exc)})") from None
            if not isinstance(archive, np.lib.npyio.NpzFile):
                raise DatasetError(path, "not an npz archive (a single .npy array)")
            with archive:
                arrays = {}
                extra = tuple(k for k in archive.files if prefix is not None and k.startswith(prefix) and k not in required + optional)
                for key in required + optional + extra:
                    if key not in archive.files:
                        if key in optional:
                            continue
                        raise DatasetError(path, f"missing array {key!r} (has: {', '.join(archive.files) or 'none'})")
                    try:
                        arrays[key] = archive[key]
                    except _READ_ERRORS as exc:
                        raise DatasetError(path, f"array {key!r} is corrupt ({_why(exc)})") from None
                return arrays
    except OSError as exc:
        raise DatasetError(path, f"cannot read ({exc.strerror or exc})") from None

