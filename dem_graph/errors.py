"""The package's exception hierarchy.

Library code raises these; only the command line turns them into a one-line message and a
non-zero exit code.
"""

from __future__ import annotations

from pathlib import Path


def one_line(exc: BaseException, max_chars: int = 300) -> str:
    """An exception's whole message on one line (whitespace collapsed, at most ``max_chars``), or its
    type's name when it has none: for errors from libraries whose messages span lines (gtsam)."""
    return " ".join(str(exc).split())[:max_chars] or type(exc).__name__


class DemGraphError(Exception):
    """Base class of every error dem_graph raises on purpose."""


class ConfigError(DemGraphError):
    """A configuration or rig value is invalid."""

    def __init__(self, problem: str, source: str | Path | None = None):
        self.source = None if source is None else str(source)
        self.problem = problem
        super().__init__(problem if source is None else f"{source}: {problem}")


class DatasetError(DemGraphError):
    """A dataset file is missing, corrupt or inconsistent. The message names the file."""

    def __init__(self, path: str | Path, problem: str):
        self.path = str(path)
        self.problem = problem
        super().__init__(f"{path}: {problem}")


class EventOrderError(DemGraphError):
    """An event reached an estimator out of time order (a camera frame not after the one before)."""


class MissingDependencyError(DemGraphError):
    """An optional dependency is not installed."""

    def __init__(self, module: str, install_hint: str):
        super().__init__(f"the optional dependency '{module}' is missing: {install_hint}")


class CalibrationError(DemGraphError):
    """A calibration cannot be made from the data given: too few usable views, degenerate geometry."""
