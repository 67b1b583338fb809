"""The command line's one vocabulary (docs/guide/command_names.md): every old spelling of a renamed
option or command still parses to what the new one does, and is shown nowhere; the research
commands live under `dem-graph research`; `--out` left out writes under results/ with a `latest`
link; `run --help` lists its options under headings."""

from __future__ import annotations

import json
import os
import re
from pathlib import Path

import click
import pytest
from click.testing import CliRunner

from dem_graph.cli import main
from dem_graph.cli.options import Option
from dem_graph.cli.out_folder import new_results_folder

RESEARCH = ("ablate", "bench", "bench-dem", "bench-sim", "simulate-calibration", "study", "track-noise")
USER = ("bag-info", "calibrate", "compare", "config", "degrade", "dem", "evaluate", "ros2", "run", "scenarios", "simulate")
RESEARCH_ONLY = ("bench-ros2",)  # research tools that never had a top-level name


def parsed(path: list[str], args: list[str]) -> dict:
    """The parameters ``dem-graph PATH... ARGS...`` parses to, without running the command."""
    ctx = click.Context(main, info_name="dem-graph")
    command = main
    for name in path:
        command = command.get_command(ctx, name)
        assert command is not None, f"no command {' '.join(path)}"
        ctx = click.Context(command, info_name=name, parent=ctx)
    return command.make_context(path[-1], list(args), parent=ctx.parent).params


def help_of(*path: str) -> str:
    result = CliRunner().invoke(main, [*path, "--help"], terminal_width=80)
    assert result.exit_code == 0, result.output
    return result.output


# (command path, old spelling, new spelling): each must parse to the same parameters
RENAMES = [
    (["run"], ["D", "--lag", "1.5"], ["D", "--lag-s", "1.5"]),
    (["dem"], ["R", "--at", "30"], ["R", "--at-s", "30"]),
    (["dem"], ["R", "--resolution", "0.2"], ["R", "--resolution-m", "0.2"]),
    (["evaluate"], ["R", "--truth", "D"], ["R", "--dataset", "D"]),
    (["research", "bench"], ["--points", "150,500"], ["--max-points", "150,500"]),
    (["research", "bench"], ["--frames", "40"], ["--max-frames", "40"]),
    (["research", "bench-dem"], ["--points", "1000"], ["--measurements", "1000"]),
    (["research", "study"], ["--data", "W"], ["--work", "W"]),
    (["research", "study"], ["--work", "W", "--budgets", "default,150"], ["--work", "W", "--max-points", "default,150"]),
    (["research", "study"], ["--work", "W", "--length", "20"], ["--work", "W", "--length-m", "20"]),
    (["research", "study"], ["--work", "W", "--speeds", "1,2"], ["--work", "W", "--speeds-mps", "1,2"]),
    (["research", "track-noise"], ["D", "--frames", "60"], ["D", "--max-frames", "60"]),
    (["research", "simulate-calibration"], ["--margin-m", "0.1"], ["--board-margin-m", "0.1"]),
]


@pytest.mark.parametrize(("path", "old", "new"), RENAMES, ids=[f"{' '.join(p)} {o[-2]}" for p, o, _ in RENAMES])
def test_an_old_spelling_parses_to_the_same_value_as_the_new(path, old, new):
    assert parsed(path, old) == parsed(path, new)


@pytest.mark.parametrize("name", RESEARCH)
def test_an_old_top_level_research_command_is_the_research_one(name):
    args = {"ablate": ["D"], "bench-dem": [], "track-noise": ["D"]}.get(name, ["--work", "W"] if name == "study" else [])
    assert parsed([name], args) == parsed(["research", name], args)


def test_the_old_bench_line_of_the_docs_still_parses():
    old = parsed(["bench"], ["--estimators", "isam2-process", "--points", "150", "--scenario", "paper", "--frames", "1600", "--as-fast-as-possible"])
    assert old["max_points"] == "150" and old["max_frames"] == 1600 and old["realtime"] is False


def test_isam2_process_in_run_is_isam2_with_the_graph_process():
    from dem_graph.cli.commands import _run_overrides

    assert vars(_run_overrides("isam2-process", False)) == vars(_run_overrides("isam2", True))
    assert _run_overrides("isam2-process", False).estimator == "isam2"


def test_realtime_is_the_same_pair_on_every_command_that_replays_a_log():
    for path, default in ((["run"], False), (["research", "study"], False), (["research", "bench"], True)):
        assert parsed(path, ["--work", "W"] if "study" in path else ["D"] if path == ["run"] else [])["realtime"] is default
        text = " ".join(help_of(*path).split())  # the help's lines joined
        assert "--realtime / --as-fast-as-possible" in text
        assert "[default: realtime:" in text if default else "[default: as fast as possible:" in text


def _commands(group: click.Group, path=()):
    for name, command in group.commands.items():
        yield (*path, name), command
        if isinstance(command, click.Group):
            yield from _commands(command, (*path, name))


def _mentions(text: str, flag: str) -> bool:
    return re.search(rf"(?<![\w-]){re.escape(flag)}(?![\w-])", text) is not None


@pytest.mark.parametrize(("path", "command"), [(p, c) for p, c in _commands(main) if not c.hidden], ids=lambda x: " ".join(x) if isinstance(x, tuple) else "")
def test_no_old_spelling_shows_in_help(path, command):
    olds = [old for p in command.params if isinstance(p, Option) for old in p.old_spellings]
    text = help_of(*path)
    shown = [old for old in olds if _mentions(text, old)]
    assert not shown, f"{' '.join(path)} --help shows {shown}"


def test_a_mistyped_option_is_told_the_new_name_not_the_old():
    r = CliRunner().invoke(main, ["research", "bench", "--point", "5"])
    assert r.exit_code == 2 and "'--max-points'" in r.output and "'--points'" not in r.output


def test_research_commands_are_hidden_at_the_top_and_listed_under_research():
    top = help_of()
    listed = {line.split()[0] for line in top.split("Commands:")[1].splitlines() if line.strip()}
    assert listed == {*USER, "research"}
    assert all(main.commands[name].hidden for name in RESEARCH)
    research = help_of("research")
    assert {line.split()[0] for line in research.split("Commands:")[1].splitlines() if line.strip()} == {*RESEARCH, *RESEARCH_ONLY}


@pytest.mark.parametrize("path", [(), ("research",)], ids=["top", "research"])
def test_no_short_help_is_cut(path):
    listing = help_of(*path).split("Commands:")[1]
    assert "..." not in listing
    assert all(line.rstrip().endswith(".") for line in listing.splitlines() if line.strip())


def test_run_help_lists_its_options_under_headings():
    text = help_of("run")
    for heading in ("Input", "Estimator", "Output", "Viewer", "KITTI", "ROS bag"):
        assert re.search(rf"^{heading}:$", text, re.M), heading
    assert text.index("\nInput:") < text.index("\nEstimator:") < text.index("\nOutput:") < text.index("\nKITTI:") < text.index("\nROS bag:")
    assert _mentions(text.split("\nKITTI:")[1].split("\nROS bag:")[0], "--ring")
    assert _mentions(text.split("\nROS bag:")[1], "--image-topic")


def test_a_results_folder_per_call_and_latest_points_at_the_newest(tmp_path):
    from datetime import datetime

    now = datetime(2026, 1, 2, 3, 4, 5)
    first = new_results_folder("run", "paper", now, root=tmp_path / "results")
    second = new_results_folder("run", "paper", now, root=tmp_path / "results")  # the same second
    assert first.name == "run_paper_2026-01-02_03-04-05" and second.name == "run_paper_2026-01-02_03-04-05_2"
    latest = tmp_path / "results" / "latest"
    assert latest.is_symlink() and os.readlink(latest) == second.name and latest.resolve() == second.resolve()
    assert not [p for p in latest.parent.iterdir() if p.name.startswith(".")]  # no temporary link left


def test_out_left_out_writes_under_results_with_a_latest_link(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    runner = CliRunner()
    r = runner.invoke(main, ["--no-progress", "simulate", "--scenario", "smoke", "--length-m", "1", "--no-odometry"])
    assert r.exit_code == 0, r.output
    (folder,) = [p for p in (tmp_path / "results").iterdir() if p.name != "latest"]
    assert re.fullmatch(r"simulate_smoke_\d{4}-\d\d-\d\d_\d\d-\d\d-\d\d", folder.name)
    assert (folder / "dataset.yaml").exists() and f"output folder: {Path('results') / folder.name}" in r.output
    assert (tmp_path / "results" / "latest").resolve() == folder.resolve()

    r = runner.invoke(main, ["--no-progress", "run", "results/latest", "--estimator", "ptpm", "--max-frames", "3"])  # through the link
    assert r.exit_code == 0, r.output
    run = (tmp_path / "results" / "latest").resolve()
    assert run != folder.resolve() and run.name.startswith(f"run_{folder.name}_") and (run / "metrics.json").exists()
    assert json.loads((run / "metrics.json").read_text())["dataset"] == str(folder.resolve())  # the dataset, not where the link points now


def test_an_explicit_out_makes_no_results_folder(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    r = CliRunner().invoke(main, ["research", "simulate-calibration", "--views", "1", "--out", "rec"])
    assert r.exit_code == 0, r.output
    assert (tmp_path / "rec" / "truth.yaml").exists() and not (tmp_path / "results").exists()


def test_a_run_that_fails_before_writing_leaves_no_empty_results_folder(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "not_a_dataset").mkdir()
    r = CliRunner().invoke(main, ["--no-progress", "run", "not_a_dataset", "--estimator", "ptpm"])
    assert r.exit_code == 2 and "dem-graph: error:" in r.output
    assert [p.name for p in (tmp_path / "results").iterdir()] == []  # neither the empty folder nor a latest link to it
