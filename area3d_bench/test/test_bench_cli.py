"""`area3d bench` is the benchmarks' typer app, added to the `area3d` command by the `area3d.cli`
entry point that pip (pyproject.toml) and colcon (setup.py) install; every help text of the
whole command renders every word."""

from __future__ import annotations

import ast
import importlib.metadata
import tomllib
from pathlib import Path

import pytest
import typer
from typer.testing import CliRunner

from area3d_bench import cli as bench_cli
from area3d_bringup import cli

ROOT = Path(__file__).resolve().parents[2]
BENCH_ENTRY_POINT = importlib.metadata.EntryPoint(
    name="bench", value="area3d_bench.cli:app", group=cli.COMMAND_GROUP
)
BENCHES = (
    "transport", "tf", "render", "stereo", "stereo-confidence", "perception", "semantics", "planner",
    "reconstruction", "eval", "foxglove", "soak", "robot", "views-depth", "map-truth", "episode",
)  # fmt: skip
BOX = str.maketrans("", "", "│╭╮╰╯─")  # rich's panel borders


@pytest.fixture()
def area3d(monkeypatch):
    """The `area3d` command with the bench entry point installed (as pip and colcon install it);
    returns a function running it with arguments."""
    monkeypatch.setattr(cli, "command_entry_points", lambda: [BENCH_ENTRY_POINT])

    def invoke(args: list[str]):
        return CliRunner().invoke(cli.app, args, prog_name="area3d", env={"COLUMNS": "200"})

    return invoke


def _words(text: str) -> str:
    return " ".join(text.translate(BOX).split())


def test_pip_and_colcon_install_the_bench_entry_point_of_the_area3d_command():
    pyproject = tomllib.loads((ROOT / "pyproject.toml").read_text())
    declared = pyproject["project"]["entry-points"][cli.COMMAND_GROUP]
    assert declared == {"bench": BENCH_ENTRY_POINT.value}
    assert "area3d_bench*" in pyproject["tool"]["setuptools"]["packages"]["find"]["include"]
    assert "area3d_bench/test" in pyproject["tool"]["pytest"]["ini_options"]["testpaths"]
    setup = ast.parse((ROOT / "area3d_bench" / "setup.py").read_text())
    entry_points = next(
        ast.literal_eval(k.value)
        for n in ast.walk(setup)
        if isinstance(n, ast.Call)
        for k in n.keywords
        if k.arg == "entry_points"
    )
    assert entry_points[cli.COMMAND_GROUP] == [f"bench = {BENCH_ENTRY_POINT.value}"]
    assert BENCH_ENTRY_POINT.load() is bench_cli.app


def test_area3d_bench_lists_every_benchmark(area3d):
    result = area3d(["bench", "--help"])
    assert result.exit_code == 0, result.output
    rows = [line.translate(BOX).split() for line in result.output.splitlines()]
    listed = [row[0] for row in rows if row]
    assert [name for name in listed if name in BENCHES] == list(BENCHES)
    assert "Benchmarks: print measured figures beside their targets." in result.output


def test_area3d_bench_episode_checks_its_options_before_running_anything(area3d, tmp_path):
    result = area3d(["bench", "episode", "--out", str(tmp_path), "--workers", "0"])
    assert result.exit_code == 2
    assert "workers: got '0', expected an int >= 1" in _words(result.output)
    assert not any(tmp_path.iterdir())


def _command_paths(group, ctx, prefix=()) -> list[tuple[tuple[str, ...], object]]:
    """(path, command) of every command and group below `group`, the group's own first."""
    out = [(prefix, group)]
    for name in group.list_commands(ctx):
        command = group.get_command(ctx, name)
        if hasattr(command, "list_commands"):
            out += _command_paths(command, typer.Context(command, parent=ctx), (*prefix, name))
        else:
            out.append(((*prefix, name), command))
    return out


def test_every_help_of_area3d_shows_every_word_of_its_texts(area3d):
    root = typer.main.get_command(cli.app)
    paths = _command_paths(root, typer.Context(root, info_name="area3d"))
    own = ("run", "report", "export", "launch", "node", "rviz", "scenes", "middleware-profile")
    assert {path for path, _ in paths} == {
        (),
        *((name,) for name in (*own, "bench")),
        *(("bench", name) for name in BENCHES),
    }
    for path, command in paths:
        result = area3d([*path, "--help"])
        assert result.exit_code == 0, (path, result.output)
        shown = _words(result.output)
        texts = [command.help or ""]
        for param in command.params:
            texts += [getattr(param, "help", None) or "", param.metavar or ""]
        for text in texts:
            # a help text says `\[word]` where rich markup would read a tag: shown as `[word]`
            expected = " ".join(text.replace("\\[", "[").split())
            assert expected in shown, (path, expected)
    # the words rich markup used to eat, and a bracketed metavar
    assert "(needs the [cluster] extra on every machine)" in _words(
        area3d(["bench", "episode", "--help"]).output
    )
    assert "[PORT]" in area3d(["run", "--help"]).output
