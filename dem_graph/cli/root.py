"""The ``dem-graph`` group, and what every command shares: a library error as one line on stderr."""

from __future__ import annotations

import copy
import functools
import logging
import sys

import click

from dem_graph.cli.options import Group
from dem_graph.cli.out_folder import drop_empty_folders
from dem_graph.errors import DemGraphError

EXIT_RUN_FAILED = 3
"""The exit code of a run that went to its end and wrote its files but measured nothing (its tracking
failed: :func:`dem_graph.pipeline.metrics.tracking_failure`); 2 is an error, 130 an interruption."""

CONTEXT_SETTINGS = {"help_option_names": ["-h", "--help"], "max_content_width": 100}  # 80 columns unless the terminal is wider


def friendly_errors(fn):
    """``fn`` with a :class:`DemGraphError` turned into one line on stderr and exit code 2, and
    Ctrl-C into exit code 130; a default output folder it left empty is removed."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except DemGraphError as exc:
            drop_empty_folders()
            click.echo(f"dem-graph: error: {exc}", err=True)
            sys.exit(2)
        except KeyboardInterrupt:
            drop_empty_folders()
            click.echo("dem-graph: interrupted", err=True)
            sys.exit(130)

    return wrapper


@click.group(cls=Group, context_settings=CONTEXT_SETTINGS)
@click.option("-v", "--verbose", count=True, help="More log output (-v info, -vv debug).")
@click.option("--no-progress", is_flag=True, help="Hide progress bars.")
@click.version_option(package_name="dem-graph")
def main(verbose: int, no_progress: bool) -> None:
    """Camera + single-line laser SLAM and dense Digital Elevation Maps.

    Benchmarks, studies and ablations are under `dem-graph research`."""
    level = logging.WARNING if verbose == 0 else logging.INFO if verbose == 1 else logging.DEBUG
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s")
    if no_progress:
        from dem_graph.progress import set_progress_enabled

        set_progress_enabled(False)


def add_hidden_aliases(group: click.Group, commands) -> None:
    """Add a hidden copy of each of ``commands`` to ``group`` under its own name: an old spelling
    (``dem-graph bench``) that still runs but is not listed."""
    for command in commands:
        alias = copy.copy(command)
        alias.hidden = True
        group.add_command(alias, command.name)
