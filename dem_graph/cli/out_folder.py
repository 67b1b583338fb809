"""Where a command writes when ``--out`` is not given: a new folder
``results/<command>_<name>_<YYYY-MM-DD_HH-MM-SS>/`` under the current directory, and the link
``results/latest`` pointed at it (as kiss-icp does), so that the newest result is always at the
same path."""

from __future__ import annotations

import os
import re
from datetime import datetime
from pathlib import Path

import click

from dem_graph.cli.options import option

RESULTS = Path("results")
LATEST = "latest"
_made: list[Path] = []  # the folders this process made here, for drop_empty_folders


def out_option(what: str, command: str, name: str = "<dataset>", **kwargs):
    """The optional ``--out DIR`` of ``command``, which writes a folder; ``what`` says what goes there,
    ``name`` what names the default folder."""
    return option(
        "--out", "out_dir", type=click.Path(file_okay=False, path_type=Path), metavar="DIR", default=None,
        help=f"{what} [default: results/{command}_{name}_<time>/, and results/latest links to it].", **kwargs,
    )


def name_of(path: str | Path, *extra: str | None) -> str:
    """A short name for a dataset or recording at ``path`` (its folder's name, a file's stem), with
    the ``extra`` parts given (a KITTI sequence), fit for a folder's name."""
    p = Path(path).resolve()  # results/latest: the folder it points at
    name = p.stem if p.is_file() else p.name
    return "_".join(_safe(part) for part in (name, *extra) if part)


def through_links(path: str | Path) -> Path:
    """``path`` with its symbolic links resolved when it goes through one, else as given: a dataset
    given as ``results/latest`` stays the one it was once a new results folder moves the link."""
    p = Path(path)
    real = p.resolve()
    return real if real != p.absolute() else p


def _safe(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9._+-]+", "-", str(text)).strip("-") or "data"


def new_results_folder(command: str, name: str, now: datetime | None = None, root: Path = RESULTS) -> Path:
    """Create ``root/<command>_<name>_<time>/`` (``_2``, ``_3``, ... when a folder of the same second
    exists), point ``root/latest`` at it and return it (a path relative to the current directory
    when ``root`` is)."""
    stamp = (now or datetime.now()).strftime("%Y-%m-%d_%H-%M-%S")
    base = f"{_safe(command)}_{_safe(name)}_{stamp}"
    root.mkdir(parents=True, exist_ok=True)
    for n in range(1, 1000):
        folder = root / (base if n == 1 else f"{base}_{n}")
        try:
            folder.mkdir()
            break
        except FileExistsError:
            continue
    else:
        raise click.ClickException(f"{root}: no free name for {base}: give --out")
    link_latest(root, folder.name)
    _made.append(folder)
    return folder


def drop_empty_folders() -> None:
    """Remove the folders :func:`new_results_folder` made in this process that are still empty (a
    command that failed before it wrote anything), and ``latest`` where it points at one of them."""
    while _made:
        folder = _made.pop()
        try:
            if any(folder.iterdir()):
                continue
            folder.rmdir()
            latest = folder.parent / LATEST
            if latest.is_symlink() and os.readlink(latest) == folder.name:
                latest.unlink()
        except OSError:
            continue


def link_latest(root: Path, target: str) -> Path | None:
    """Point ``root/latest`` at ``root/target`` (a relative link, replaced atomically: a reader sees
    the old target or the new one, never none); None, with a warning, where no link can be made
    (a file system without symbolic links, or a ``latest`` that is a real folder)."""
    latest = root / LATEST
    temporary = root / f".{LATEST}.{os.getpid()}"
    try:
        temporary.unlink(missing_ok=True)
        temporary.symlink_to(target, target_is_directory=True)
        os.replace(temporary, latest)
    except OSError as exc:
        temporary.unlink(missing_ok=True)
        click.echo(f"dem-graph: warning: {latest} not updated ({exc.strerror or exc})", err=True)
        return None
    return latest


def out_folder(out_dir: Path | None, command: str, name: str) -> Path:
    """``out_dir`` when given; else a new :func:`new_results_folder`, printed."""
    if out_dir is not None:
        return out_dir
    folder = new_results_folder(command, name)
    click.echo(f"output folder: {folder} ({RESULTS / LATEST} points at it)")
    return folder
