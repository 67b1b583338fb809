"""The estimators, each fed the same events through the same front end and returning the same
:class:`~dem_graph.estimators.base.EstimatorResult`:

- :mod:`~dem_graph.estimators.ekf`: the paper's EKF in its two variants, GM and PTPM;
- :mod:`~dem_graph.estimators.isam2`: the factor-graph estimator, online (fixed-lag iSAM2) and
  smoothed over the whole log (``isam2-batch``, :mod:`~dem_graph.estimators.batch`).
"""
