"""The saved live maps in the run folder as they are written (``live_maps.part``), and read back after
a run that did not end: a real SIGKILL, a map cut short, a damaged header, a normal close.

Truth: the maps appended, made here from a formula (:func:`known_dem`: every layer's values, NaN
cells included, every time and pose known), compared bit for bit.
"""

from __future__ import annotations

import logging
import os
import signal
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import pytest

from dem_graph.dem.layers import Dem
from dem_graph.dem.views import heading_frame
from dem_graph.errors import DatasetError
from dem_graph.geometry.grid import GridGeometry
from dem_graph.io.live_maps import SAVED_LAYERS, LiveMapWriter, live_map_at, live_maps_part_path, read_live_maps, salvage_live_maps

# a save window as the recorder makes one: 0 to 4 m ahead, 3 m wide, 0.1 m cells
GEOMETRY = GridGeometry(x_min_m=0.0, y_max_m=1.5, resolution_m=0.1, n_rows=30, n_cols=40)
TEMP_PREFIX = "dem_graph_live_maps_"


def known_time_s(k: int) -> float:
    return 100.0 + 0.4 * k + 1e-7 * k  # not a round number: a time that loses digits is seen


def known_pose(k: int) -> tuple[float, float, float, float]:
    """Map ``k``'s heading frame: x, y, z (m) and yaw (rad)."""
    return 3.25 * k - 1.0, 0.5 - 0.75 * k, 0.125 + 0.01 * k, -0.3 + 0.2 * k


def known_dem(k: int) -> Dem:
    """Map ``k``: layer ``i`` holds ``1000 k + 10 i + cell / 7`` (float32), NaN on a diagonal band."""
    cells = np.arange(GEOMETRY.n_rows * GEOMETRY.n_cols, dtype=np.float64).reshape(GEOMETRY.shape)
    rows, cols = np.indices(GEOMETRY.shape)
    layers = {}
    for i, name in enumerate(SAVED_LAYERS):
        layer = (1000.0 * k + 10.0 * i + cells / 7.0).astype(np.float32)
        layer[(rows - cols + k) % 9 == 0] = np.nan
        layers[name] = layer
    x, y, z, yaw = known_pose(k)
    return Dem(GEOMETRY, layers, frame="local", meta={"t_s": known_time_s(k), "T_world_local": heading_frame([x, y, z], yaw)})


def assert_holds_known_maps(ds, n: int) -> None:
    """``ds`` (as :func:`read_live_maps` returns it) holds exactly maps 0 to n-1, bit for bit."""
    assert ds.sizes["time"] == n
    np.testing.assert_array_equal(ds["time"].values, [known_time_s(k) for k in range(n)])
    for name in SAVED_LAYERS:
        values = ds[name].values
        assert values.dtype == np.float32
        expected = np.stack([known_dem(k).layers[name] for k in range(n)])
        assert values.tobytes() == expected.tobytes(), name  # bit for bit, the NaN cells included
    poses = np.array([known_pose(k) for k in range(n)])
    for i, name in enumerate(("x_world_m", "y_world_m", "z_world_m")):
        np.testing.assert_array_equal(ds[name].values, poses[:, i])
    np.testing.assert_allclose(ds["yaw_rad"].values, poses[:, 3], rtol=0, atol=1e-15)  # atan2 of the frame's cos and sin


def assert_is_known_map(dem: Dem, k: int) -> None:
    truth = known_dem(k)
    assert dem.meta["t_s"] == known_time_s(k) and dem.frame == "local"
    np.testing.assert_allclose(dem.meta["T_world_local"], truth.meta["T_world_local"], rtol=0, atol=1e-15)
    for name in SAVED_LAYERS:
        assert dem.layers[name].tobytes() == truth.layers[name].tobytes(), name


def _warnings(caplog) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]


@pytest.fixture(autouse=True)
def temp_folder(tmp_path, monkeypatch):
    """The system's temp folder, for this test alone: none of them may leave a writer's temporary file."""
    folder = tmp_path / "system_tmp"
    folder.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(folder))
    yield folder
    assert not list(folder.glob(f"{TEMP_PREFIX}*"))


@pytest.fixture
def run_dir(tmp_path) -> Path:
    out = tmp_path / "run"
    out.mkdir()
    return out


def _write(run_dir: Path, n: int) -> LiveMapWriter:
    writer = LiveMapWriter(GEOMETRY, SAVED_LAYERS, run_dir / "live_maps.nc")
    for k in range(n):
        writer.append(known_dem(k))
    return writer


def test_the_part_file_in_the_run_folder_holds_every_map_appended_before_close(run_dir, temp_folder, caplog):
    writer = _write(run_dir, 5)
    assert len(writer) == 5
    assert sorted(p.name for p in run_dir.iterdir()) == ["live_maps.part"]
    assert not list(temp_folder.iterdir())  # a run with a folder makes no temporary file
    caplog.set_level(logging.WARNING)
    assert_holds_known_maps(read_live_maps(run_dir / "live_maps.nc"), 5)
    (warning,) = _warnings(caplog)
    assert warning.startswith(f"{run_dir / 'live_maps.part'}: the run did not end") and "part file written as it went" in warning
    assert_holds_known_maps(read_live_maps(run_dir / "live_maps.part"), 5)  # the part file read by its own name
    caplog.clear()
    assert_is_known_map(live_map_at(run_dir / "live_maps.nc", known_time_s(3) + 0.1), 3)  # the latest at or before
    assert len(_warnings(caplog)) == 1
    writer.append(known_dem(5))  # still writing after being read
    assert_holds_known_maps(read_live_maps(run_dir / "live_maps.nc"), 6)
    writer.close()


def test_after_a_normal_close_only_the_netcdf_file_remains_and_reads_back_equal(run_dir, caplog):
    writer = _write(run_dir, 4)
    caplog.set_level(logging.WARNING)
    assert writer.close() == run_dir / "live_maps.nc"
    assert sorted(p.name for p in run_dir.iterdir()) == ["live_maps.nc"]
    with (run_dir / "live_maps.nc").open("rb") as fh:
        assert fh.read(3) == b"CDF"
    assert_holds_known_maps(read_live_maps(run_dir / "live_maps.nc"), 4)
    assert_is_known_map(live_map_at(run_dir / "live_maps.nc", known_time_s(2)), 2)
    assert _warnings(caplog) == []


def test_a_writer_with_no_map_saved_closes_to_nothing(run_dir):
    writer = LiveMapWriter(GEOMETRY, SAVED_LAYERS, run_dir / "live_maps.nc")
    assert writer.close() is None
    assert list(run_dir.iterdir()) == []


def test_without_a_run_folder_the_maps_go_to_a_temporary_file_that_is_removed(tmp_path, temp_folder):
    writer = LiveMapWriter(GEOMETRY, SAVED_LAYERS)
    writer.append(known_dem(0))
    (made,) = temp_folder.glob(f"{TEMP_PREFIX}*.part")
    assert_holds_known_maps(read_live_maps(made), 1)  # a temporary file reads as a run folder's does
    assert writer.close(tmp_path / "maps.nc") == tmp_path / "maps.nc"
    assert_holds_known_maps(read_live_maps(tmp_path / "maps.nc"), 1)
    dropped = LiveMapWriter(GEOMETRY, SAVED_LAYERS)  # never closed
    dropped.append(known_dem(0))
    del dropped
    assert not list(temp_folder.iterdir())


def test_salvage_turns_the_part_file_of_a_run_that_did_not_end_into_the_netcdf_file(run_dir, caplog):
    writer = _write(run_dir, 3)
    del writer  # dropped unclosed, as by a run whose end was not written: its part file is kept
    assert sorted(p.name for p in run_dir.iterdir()) == ["live_maps.part"]
    caplog.set_level(logging.WARNING)
    assert salvage_live_maps(run_dir / "live_maps.nc") == run_dir / "live_maps.nc"
    assert sorted(p.name for p in run_dir.iterdir()) == ["live_maps.nc"]
    assert_holds_known_maps(read_live_maps(run_dir / "live_maps.nc"), 3)
    assert _warnings(caplog) == []
    with pytest.raises(DatasetError, match=r"live_maps\.part: not found: no live maps to salvage"):
        salvage_live_maps(run_dir / "live_maps.nc")


def test_a_map_cut_short_at_the_end_is_left_out_with_one_warning(run_dir, caplog):
    writer = _write(run_dir, 4)
    part = live_maps_part_path(run_dir / "live_maps.nc")
    record_bytes = 5 * 8 + len(SAVED_LAYERS) * GEOMETRY.n_rows * GEOMETRY.n_cols * 4  # the module's record: t_s and the pose, then the layers
    with part.open("r+b") as fh:  # what a kill in the middle of writing map 3 leaves
        fh.truncate(part.stat().st_size - record_bytes // 3)
    caplog.set_level(logging.WARNING)
    assert_holds_known_maps(read_live_maps(run_dir / "live_maps.nc"), 3)
    (warning,) = _warnings(caplog)
    assert "did not end" in warning and "its 3 live maps" in warning and warning.endswith("; a map cut short at its end is left out")
    assert_is_known_map(live_map_at(run_dir / "live_maps.nc", known_time_s(3)), 2)  # map 3 is not there: the one before it
    caplog.clear()
    assert salvage_live_maps(run_dir / "live_maps.nc") == run_dir / "live_maps.nc"
    (warning,) = _warnings(caplog)
    assert "a map cut short at its end" in warning
    assert_holds_known_maps(read_live_maps(run_dir / "live_maps.nc"), 3)
    assert len(writer) == 4


def _damage_text(part: Path) -> None:
    data = bytearray(part.read_bytes())
    data[0:12] = b"\x00garbage\xff\xfe!!"
    part.write_bytes(bytes(data))


def _damage_geometry(part: Path) -> None:
    data = part.read_bytes()
    part.write_bytes(data.replace(b'"n_rows": 30', b'"n_rows": -3', 1))


def _damage_format(part: Path) -> None:
    data = part.read_bytes()
    part.write_bytes(data.replace(b"dem_graph live maps part", b"someone else's format!!", 1))


def _damage_newline(part: Path) -> None:
    part.write_bytes(b"{" * 70000)


@pytest.mark.parametrize(
    "damage, problem",
    [
        (_damage_text, "damaged header (not JSON"),
        (_damage_geometry, "damaged header (DemGraphError: invalid grid geometry"),
        (_damage_format, "not a live-maps part file (its header does not say format"),
        (_damage_newline, "not a live-maps part file (it does not begin with its header line"),
        (lambda part: part.write_bytes(b""), "not a live-maps part file (it does not begin with its header line"),
    ],
    ids=["not_json", "bad_geometry", "other_format", "no_header_line", "empty"],
)
def test_a_damaged_header_is_one_line_naming_the_file(run_dir, damage, problem):
    writer = _write(run_dir, 2)
    part = run_dir / "live_maps.part"
    damage(part)
    for read in (lambda: read_live_maps(run_dir / "live_maps.nc"), lambda: live_map_at(run_dir / "live_maps.nc", 1e9), lambda: salvage_live_maps(run_dir / "live_maps.nc")):
        with pytest.raises(DatasetError) as caught:
            read()
        assert caught.value.path == str(part)
        assert str(caught.value).startswith(f"{part}: {problem}") and "\n" not in str(caught.value)
    assert part.is_file()  # a salvage that cannot read the part file keeps it
    assert len(writer) == 2


def test_a_part_file_with_no_whole_map_is_one_line(run_dir):
    writer = LiveMapWriter(GEOMETRY, SAVED_LAYERS, run_dir / "live_maps.nc")
    with pytest.raises(DatasetError, match=r"live_maps\.part: holds no whole live map: the run stopped before its first was written$"):
        read_live_maps(run_dir / "live_maps.nc")
    assert len(writer) == 0


CHILD = """
import sys, time
sys.path.insert(0, {tests!r})
from test_live_maps_part import GEOMETRY, known_dem
from dem_graph.io.live_maps import SAVED_LAYERS, LiveMapWriter
writer = LiveMapWriter(GEOMETRY, SAVED_LAYERS, {path!r})
for k in range({n}):
    writer.append(known_dem(k))
print("saved", len(writer), flush=True)
time.sleep(120)
"""


@pytest.fixture(scope="module", autouse=True)
def writing_child(tmp_path_factory):
    """A child process that makes a writer in a run folder, appends maps 0 to 5, says so and sleeps,
    with a temp folder of its own. Started with the module's first test, so that its start-up (the
    imports: seconds) overlaps the other tests; killed at the end if a test did not kill it."""
    base = tmp_path_factory.mktemp("killed")
    run, child_tmp = base / "run", base / "child_tmp"
    run.mkdir()
    child_tmp.mkdir()
    env = dict(os.environ, TMPDIR=str(child_tmp), PYTHONUNBUFFERED="1")
    code = CHILD.format(tests=str(Path(__file__).parent), path=str(run / "live_maps.nc"), n=6)
    child = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    yield child, run, child_tmp
    child.kill()
    child.communicate()


@pytest.mark.skipif(sys.platform == "win32", reason="POSIX signals")
def test_a_run_killed_outright_keeps_every_map_it_saved(writing_child, caplog):
    """The child's 6 maps, after a SIGKILL: read back, read by the run folder's reader (what
    `dem-graph dem RUN --at-s T` calls, with no poses.npz in a killed run's folder), and salvaged."""
    from dem_graph.pipeline.run_folder import live_map_of_run

    child, run_dir, child_tmp = writing_child
    line = child.stdout.readline()
    assert line == "saved 6\n", child.communicate()[1] if not line else line
    child.send_signal(signal.SIGKILL)
    assert child.wait(timeout=30) == -signal.SIGKILL
    assert sorted(p.name for p in run_dir.iterdir()) == ["live_maps.part"]
    assert not list(child_tmp.iterdir())  # no temporary file either
    caplog.set_level(logging.WARNING)
    assert_holds_known_maps(read_live_maps(run_dir / "live_maps.nc"), 6)
    assert_is_known_map(live_map_of_run(run_dir, known_time_s(4) + 0.05), 4)
    assert len(_warnings(caplog)) == 2  # one for each read
    assert salvage_live_maps(run_dir / "live_maps.nc") == run_dir / "live_maps.nc"
    assert sorted(p.name for p in run_dir.iterdir()) == ["live_maps.nc"]
    assert_holds_known_maps(read_live_maps(run_dir / "live_maps.nc"), 6)
