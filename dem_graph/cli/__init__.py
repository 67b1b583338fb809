"""The ``dem-graph`` command line: one thin command per library function.

The user's commands sit at the top (:mod:`~dem_graph.cli.commands`, :mod:`~dem_graph.cli.calibration`),
the research tools under ``dem-graph research`` (:mod:`~dem_graph.cli.research`), the ROS 2 node and player under
``dem-graph ros2`` (:mod:`~dem_graph.cli.ros2`); what they share is
in :mod:`~dem_graph.cli.options` (the options' old spellings and headings), :mod:`~dem_graph.cli.datasets`
(how a dataset is opened) and :mod:`~dem_graph.cli.out_folder` (``results/`` when ``--out`` is not given).
Library errors (:class:`DemGraphError`) become a one-line message on stderr and exit code 2.
"""

from __future__ import annotations

from dem_graph.cli import calibration, commands, research, ros2  # noqa: F401 - each adds its commands to main
from dem_graph.cli.root import main

__all__ = ["main"]

if __name__ == "__main__":
    main()
