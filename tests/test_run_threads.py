"""A run limits numpy's BLAS to ``blas_threads`` while the estimator works, and gives the threads back after."""

from __future__ import annotations

from threadpoolctl import threadpool_info

from dem_graph.estimators.ekf import EkfSlam
from dem_graph.pipeline import RunConfig, run_estimator


def _blas_threads() -> int:
    return max((p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"), default=1)


def test_the_estimator_runs_with_the_configured_blas_threads(smoke_log, monkeypatch):
    seen = []
    on_frame = EkfSlam.on_frame

    def recording(self, event):
        seen.append(_blas_threads())
        return on_frame(self, event)

    monkeypatch.setattr(EkfSlam, "on_frame", recording)
    before = _blas_threads()
    run_estimator(smoke_log, RunConfig(estimator="ptpm", max_frames=3), with_dem=False)
    assert seen == [1, 1, 1]
    assert _blas_threads() == before  # given back
    if before > 1:  # on a one-core machine there is nothing more to ask for
        seen.clear()
        run_estimator(smoke_log, RunConfig(estimator="ptpm", max_frames=2, blas_threads=before), with_dem=False)
        assert seen == [before, before]
