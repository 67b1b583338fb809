"""`dem-graph bench --plot`: the paper's Fig. 12 drawn from a benchmark's table."""

from __future__ import annotations

import numpy as np
import pytest
from click.testing import CliRunner

from dem_graph.cli import main
from dem_graph.evaluation.timing import TimingStats
from dem_graph.studies.bench_estimators import BenchRow
from dem_graph.viz.bench_figure import FRAME_BUDGET_MS, time_per_frame_figure

# a known table: (estimator, cap, live points, median ms, p95 ms), rows out of order on purpose
_TABLE = [
    ("gm", 100, 96.0, 30.5, 41.25),
    ("gm", 50, 48.0, 12.0, 15.5),
    ("gm", 500, 470.0, 210.0, 260.0),
    ("ptpm", 50, 49.0, 14.0, 18.0),
    ("ptpm", 100, 97.0, 35.0, 47.0),
    ("isam2-process", 50, 47.0, 9.0, 13.0),
]


def _rows() -> list[BenchRow]:
    def stats(median, p95):
        return TimingStats(100, median, p95, median)

    none = stats(0.0, 0.0)
    return [BenchRow(name, cap, stats(m, p), none, none, none, live, live, 0.5) for name, cap, live, m, p in _TABLE]


def test_plotted_lines_are_the_tables_medians_against_live_points(tmp_path):
    figure = time_per_frame_figure(tmp_path / "fig12.png", _rows())
    assert figure.path.stat().st_size > 0
    assert figure.path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    (ax,) = figure.figure.axes
    lines = {line.get_label(): line for line in ax.get_lines()}
    for name in ("gm", "ptpm", "isam2-process"):
        expected = sorted((live, m, p) for n, _, live, m, p in _TABLE if n == name)
        line = lines[f"{name} (median)"]
        # exactly the table's numbers, in order of live points
        np.testing.assert_array_equal(line.get_xdata(), [x for x, _, _ in expected])
        np.testing.assert_array_equal(line.get_ydata(), [m for _, m, _ in expected])
        np.testing.assert_array_equal(figure.series[name].p95_ms, [p for _, _, p in expected])
    # the 25 Hz budget: a horizontal line at exactly 40 ms
    budget = lines["40 ms (25 Hz)"]
    assert FRAME_BUDGET_MS == 40.0 and set(budget.get_ydata()) == {40.0}
    assert ax.get_xlabel() == "live points per frame (median)" and ax.get_ylabel() == "time per frame (ms, log scale)"
    assert ax.get_yscale() == "log"


def test_p95_band_spans_median_to_p95(tmp_path):
    figure = time_per_frame_figure(tmp_path / "fig12.png", _rows())
    (ax,) = figure.figure.axes
    band = next(c for c in ax.collections if c.get_label() == "gm (to p95)")
    vertices = np.vstack([p.vertices for p in band.get_paths()])
    # the band's top edge is the p95 and its bottom the median, to the float
    assert np.isclose(vertices[:, 1].max(), 260.0, rtol=0, atol=1e-9)
    assert np.isclose(vertices[:, 1].min(), 12.0, rtol=0, atol=1e-9)


@pytest.mark.parametrize(
    "args, message",
    [
        (["--max-points", "50,x"], "not a list of integers"),
        (["--max-points", "0,50"], "1 point or more"),
        (["--estimators", "gm,ekf"], "unknown estimator ekf"),
        (["--plot", "fig.jpg"], "the plot is a PNG"),
    ],
)
def test_bad_bench_options_are_one_line_errors(args, message):
    result = CliRunner().invoke(main, ["research", "bench", *args])
    assert result.exit_code == 2
    assert message in result.output and "Traceback" not in result.output


def test_a_noimu_bench_row_is_the_run_without_the_imu():
    """``ptpm-noimu`` in the bench is PTPM with the log's IMU ignored: its drift over 30 frames of
    `smoke` equals a direct run with ``motion.use_imu: false`` on the same frames to the float, and
    differs from the bench's ``ptpm`` row (which uses the IMU)."""
    from dem_graph.datasets.events import CameraFrame
    from dem_graph.datasets.memory import InMemorySequence
    from dem_graph.pipeline.run import run_estimator
    from dem_graph.sim.scenarios import scenario
    from dem_graph.sim.simulator import SimulatedSequence
    from dem_graph.studies.bench_estimators import bench_estimators, config_for_points

    result = bench_estimators(("ptpm", "ptpm-noimu"), (60,), "smoke", frames=30, realtime=False)
    rows = {r.estimator: r for r in result.rows}
    sim = SimulatedSequence.from_config(scenario("smoke", seed=0))
    events = []
    for e in sim.events():
        events.append(e)
        if isinstance(e, CameraFrame) and e.index + 1 >= 30:
            break
    log = InMemorySequence(sim.rig, events, sim.T_world_body_initial, sim.t_start_s, sim.ground_truth, sim.name)
    config = config_for_points("ptpm", 60, sim.rig)
    config.motion.use_imu = False
    direct = run_estimator(log, config).metrics.trajectory.drift_percent
    assert rows["ptpm-noimu"].drift_percent == direct
    assert rows["ptpm"].drift_percent != direct
