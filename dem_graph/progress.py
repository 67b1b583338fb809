"""The one progress-bar helper. Library code calls it; it can be switched off globally."""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from typing import TypeVar

from tqdm.auto import tqdm

T = TypeVar("T")

_enabled = True


def set_progress_enabled(enabled: bool) -> None:
    """Switch every progress bar of dem_graph on or off (for example in tests or batch jobs)."""
    global _enabled
    _enabled = enabled


def progress(iterable: Iterable[T], total: int | None = None, desc: str = "", unit: str = "it") -> Iterator[T]:
    """Wrap ``iterable`` in a progress bar on stderr, unless progress bars are off."""
    if not _enabled:
        yield from iterable
        return
    # disable=None: no bar when stderr is not a terminal (CI logs, pipes)
    yield from tqdm(iterable, total=total, desc=desc, unit=unit, leave=False, dynamic_ncols=True, disable=None, mininterval=0.5)
