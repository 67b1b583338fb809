"""Experiments built on the pipeline: many runs, one table, a report.

- :mod:`~dem_graph.studies.compare`: every estimator on one dataset (``dem-graph compare``);
- :mod:`~dem_graph.studies.evaluate`: one run folder against a truth (``dem-graph evaluate``);
- :mod:`~dem_graph.studies.study`: accuracy against cost over scenarios, seeds and point budgets;
- :mod:`~dem_graph.studies.bench_estimators`, :mod:`~dem_graph.studies.bench_dem`,
  :mod:`~dem_graph.studies.bench_sim`: the benchmarks (``dem-graph research bench``, ``bench-dem``, ``bench-sim``);
- :mod:`~dem_graph.studies.tracking_noise`: the tracker's error against the truth (``dem-graph research track-noise``);
- :mod:`~dem_graph.studies.search_regions`: the graph's search regions against exact marginals;
- :mod:`~dem_graph.studies.headline`: the table columns; :mod:`~dem_graph.studies.report`: the report page.
"""
