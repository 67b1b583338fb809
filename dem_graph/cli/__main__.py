"""``python -m dem_graph.cli``: the ``dem-graph`` command line."""

from dem_graph.cli import main

main()
