"""What every figure of the package shares: a headless pyplot, the estimators' colours, and saving
a figure with a one-line error naming the file."""

from __future__ import annotations

from pathlib import Path

from dem_graph.errors import DatasetError

_COLOURS = {"gm": "tab:orange", "ptpm": "tab:blue", "isam2": "tab:green", "isam2-batch": "tab:red"}


def colour(name: str, index: int = 0) -> str:
    """The estimator's colour (a fixed one for the known estimators)."""
    return _COLOURS.get(name, f"C{4 + index % 6}")


def pyplot():
    """matplotlib.pyplot on the Agg backend (no display needed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig, path: str | Path, dpi: int = 100) -> Path:
    """Lay out, write and close ``fig``; a file that cannot be written is a one-line error."""
    plt = pyplot()
    path = Path(path)
    try:
        fig.tight_layout()
        fig.savefig(path, dpi=dpi)
    except OSError as exc:
        raise DatasetError(path, f"cannot write ({exc.strerror or exc})") from None
    finally:
        plt.close(fig)
    return path
