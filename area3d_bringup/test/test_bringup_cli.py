"""The `area3d` command adds the command groups of installed `area3d.cli` entry points: listed in
its help, run by name, and left out with a warning when one does not load; a command of its own
loads none of them."""

from __future__ import annotations

import pytest
import typer
from typer.testing import CliRunner

from area3d_bringup import cli


class _EntryPoint:
    """An installed entry point as `importlib.metadata` gives it: a name, a value, load()."""

    def __init__(self, name: str, value: str, load) -> None:
        self.name, self.value, self.group = name, value, cli.COMMAND_GROUP
        self.load = load


def _greetings() -> typer.Typer:
    group = typer.Typer(help="Greetings from an installed package.")

    @group.command()
    def hello(name: str = typer.Option("robot", help="whom to greet")) -> None:
        """Say hello."""
        print(f"hello {name}")

    @group.command()
    def bye() -> None:
        """Say bye."""
        print("bye")

    return group


def _broken() -> typer.Typer:
    raise ImportError("No module named 'greetings_missing'")


def _invoke(args: list[str]):
    return CliRunner().invoke(cli.app, args, prog_name="area3d", env={"COLUMNS": "200"})


def test_an_entry_points_group_is_listed_and_runs_under_its_name(monkeypatch):
    monkeypatch.setattr(
        cli, "command_entry_points", lambda: [_EntryPoint("greet", "greetings:app", _greetings)]
    )
    listing = _invoke(["--help"])
    assert listing.exit_code == 0, listing.output
    assert "greet" in listing.output and "Greetings from an installed package." in listing.output
    assert "run" in listing.output and "launch" in listing.output  # its own commands stay
    result = _invoke(["greet", "hello", "--name", "rover"])
    assert result.exit_code == 0, result.output
    assert result.output.strip() == "hello rover"
    assert _invoke(["greet", "bye"]).output.strip() == "bye"


def test_a_group_that_does_not_load_is_left_out_with_a_warning_and_the_others_still_run(
    monkeypatch,
):
    monkeypatch.setattr(
        cli,
        "command_entry_points",
        lambda: [
            _EntryPoint("broken", "greetings_missing:app", _broken),
            _EntryPoint("greet", "greetings:app", _greetings),
        ],
    )
    listing = _invoke(["--help"])
    assert listing.exit_code == 0
    text = " ".join(listing.output.split())
    assert "warning: `area3d broken` is unavailable: greetings_missing:app did not load" in text
    assert "ImportError: No module named 'greetings_missing'" in text
    assert "greet" in listing.output
    assert _invoke(["greet", "bye"]).output.strip() == "bye"
    missing = _invoke(["broken"])
    assert missing.exit_code == 2 and "No such command 'broken'" in missing.output


def test_a_command_of_its_own_loads_no_entry_point(monkeypatch):
    def loaded() -> typer.Typer:
        raise AssertionError("an entry point was loaded for `area3d scenes`")

    monkeypatch.setattr(
        cli, "command_entry_points", lambda: [_EntryPoint("greet", "greetings:app", loaded)]
    )
    result = _invoke(["scenes"])
    assert result.exit_code == 0, result.output
    assert "single_object" in result.output and "warning" not in result.output


def test_an_error_message_with_brackets_is_printed_whole(tmp_path):
    # rich markup would take `[cluster]` for a tag and drop it
    run_dir = tmp_path / "[cluster]"
    result = _invoke(["report", str(run_dir)])
    assert result.exit_code == 2
    assert "[cluster]" in result.output and "expected a directory containing episode.json" in (
        " ".join(result.output.split())
    )


def test_a_report_of_a_damaged_run_directory_is_one_line_naming_the_file(tmp_path):
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    (run_dir / "episode.json").write_text('{"scene": "single_object", "policy": "area3d", "vi')
    result = _invoke(["report", str(run_dir)])
    assert result.exit_code == 2, result.output
    assert result.output.startswith("error: ") and "Traceback" not in result.output
    assert f"{run_dir / 'episode.json'}: got 'not JSON" in " ".join(result.output.split())


def _refused_run(tmp_path, *args: str):
    out = tmp_path / "runs"
    result = _invoke(["run", "--out", str(out), *args])
    assert result.exit_code == 2, result.output
    assert not out.exists() or not any(out.iterdir())  # refused before a run directory was made
    return " ".join(result.output.split())


def test_a_parameter_no_node_declares_is_refused_by_name_before_anything_starts(tmp_path):
    text = _refused_run(tmp_path, "-p", "foo.eta=1")
    assert "--param foo.*: got node 'foo', expected one of" in text and "'planner'" in text
    text = _refused_run(tmp_path, "-p", "planner.etaa=0.5")
    assert "--param planner.etaa: got a name that planner does not declare" in text
    assert "(did you mean 'eta'?)" in text
    text = _refused_run(tmp_path, "-p", "planner.eta=abc")
    assert "planner.eta: got 'abc', expected a float" in text
    text = _refused_run(tmp_path, "-p", "planner.eta=[1,")
    assert "--param planner.eta: got '[1,', expected a YAML value" in text and "column 4" in text


def test_a_parameter_file_with_a_typo_or_broken_yaml_is_refused_by_name(tmp_path):
    typo = tmp_path / "typo.yaml"
    typo.write_text(
        "planner:\n  ros__parameters:\n    gama: 0.01\n"
        "mission_planner:\n  ros__parameters:\n    anything: 1\n"  # another node's: not ours
    )
    text = _refused_run(tmp_path, "--params", str(typo))
    assert (
        "params file planner.gama: got a name that planner does not declare" in text
        and "(did you mean 'gamma'?)" in text
    )
    broken = tmp_path / "broken.yaml"
    broken.write_text("planner:\n  ros__parameters:\n    eta: [1,\n")
    text = _refused_run(tmp_path, "--params", str(broken))
    assert f"params file {broken}: not valid YAML" in text and "line 4, column 1" in text


def test_a_graph_that_cannot_start_suggests_no_resume(tmp_path):
    # perception's vggt backend without torch or weights: the node stops at once, no view is
    # captured, and there is nothing a --resume could go on with
    out = tmp_path / "runs"
    result = _invoke(["run", "--out", str(out), "--no-evaluate", "--no-record",
                      "-p", "perception.backend=vggt"])  # fmt: skip
    text = " ".join(result.output.split())
    assert result.exit_code == 2, text
    assert "perception" in text and "no view was captured" in text, text
    assert "--resume" not in text, text


def test_a_stop_while_evaluating_names_the_command_that_finishes_the_report(tmp_path, monkeypatch):
    import area3d_bringup.runner as runner

    run_dir = tmp_path / "runs" / "episode one"  # a space: the command is quoted for a shell
    run_dir.mkdir(parents=True)
    monkeypatch.setattr(runner, "run_episode", lambda config, resume, progress: run_dir)

    def interrupted(run_dirs, out_dir):
        assert run_dirs == [run_dir]
        raise KeyboardInterrupt  # Ctrl-C while the reconstruction is scored

    monkeypatch.setattr(cli, "_evaluate_and_report", interrupted)
    result = _invoke(["run", "--out", str(tmp_path / "runs"), "--no-record"])
    assert result.exit_code == 130, result.output
    # on one line, whatever the terminal's width: a folded path would not paste as one
    line = next(row for row in result.output.splitlines() if "episode is complete" in row)
    assert f"`area3d report '{run_dir}'` evaluates it" in line, result.output


def _saved_run(tmp_path, **fields):
    """A run directory whose episode.json is what a run that stopped before its first view
    wrote (what --resume reads first)."""
    import json

    run_dir = tmp_path / "stopped"
    run_dir.mkdir()
    saved = {"scene": "single_object", "policy": "area3d", "mode": "closed_loop", "seed": 0}
    saved |= {"budget": 10, "depth_source": "sensor", "views": []} | fields
    (run_dir / "episode.json").write_text(json.dumps(saved))
    return run_dir


def test_resume_refuses_a_run_option_that_differs_from_the_runs_own(tmp_path):
    run_dir = _saved_run(tmp_path)
    for option, value, theirs in (
        ("--seed", "3", "0"),
        ("--policy", "uniform", "'area3d'"),
        ("--scene", "five_objects", "'single_object'"),
        ("--depth-source", "estimated", "'sensor'"),
        ("--budget", "12", "10"),
    ):
        text = _refused_run(tmp_path, "--resume", str(run_dir), option, value)
        shown = value if option in ("--seed", "--budget") else f"'{value}'"
        assert f"{option}: got {shown}, expected the resumed run's own {theirs}" in text, text
        assert "leave the option out" in text


def test_resume_takes_the_runs_own_options_and_those_given_with_the_same_values():
    from pathlib import Path

    from area3d_bringup.episode_config import EpisodeConfig
    from area3d_bringup.episode_record import _check_given
    from sim_bridge.scenes import load_scene

    saved = {"scene": "single_object", "policy": "area3d", "mode": "closed_loop", "seed": 0}
    saved |= {"budget": 10, "depth_source": "estimated"}
    bundled = str(Path(load_scene("single_object").mjcf_path))  # the same scene by its file
    given = frozenset({"scene", "policy", "mode", "seed", "budget", "depth_source"})
    same = EpisodeConfig(scene=bundled, budget=10, depth_source="estimated", given=given)
    _check_given(same, saved)  # nothing refused
    # options not given are never compared (they are the CLI's defaults, not the user's)
    _check_given(EpisodeConfig(seed=5, policy="uniform"), saved)
    # an older run's episode.json without depth_source ran on the camera's depth
    older = {k: v for k, v in saved.items() if k != "depth_source"}
    _check_given(EpisodeConfig(given=frozenset({"depth_source"})), older)


def _resumed(run_dir, **config):
    from area3d_bringup.episode_config import EpisodeConfig
    from area3d_bringup.episode_record import EpisodeRecord

    return EpisodeRecord(EpisodeConfig(**config), run_dir)


def test_a_resumed_run_goes_on_with_the_parameters_it_began_with(tmp_path):
    """A run begun with stereo perception and a planner's eta of 0.5, resumed without them: the
    graph starts with the run's own parameters, not the defaults; given again with the same
    values they are accepted, with other values or as a parameter file they are refused by
    name before anything starts."""
    from area3d_bringup.presets import episode_specs

    began = {"perception": {"backend": "stereo"}, "planner": {"eta": 0.5}}
    camera = {"sim_bridge": {"readers.all": ["mission_manager"]}}  # as the runner adds it
    specs = episode_specs("single_object", "area3d", 0, 10, "closed_loop", began | camera)
    saved_config = {spec.name: spec.parameters for spec in specs}
    run_dir = _saved_run(tmp_path, config=saved_config)

    def parameters(record):
        return {spec.name: spec.parameters for spec in record.specs}

    resumed = parameters(_resumed(run_dir))
    assert resumed["perception"]["backend"] == "stereo" and resumed["planner"]["eta"] == 0.5
    assert resumed == saved_config  # every node's, nothing from the defaults
    assert parameters(_resumed(run_dir, overrides=began)) == saved_config
    with pytest.raises(ValueError, match=r"planner.eta \(-p, --camera\): got 0.3, expected the "
                       r"resumed run's own 0.5"):  # fmt: skip
        _resumed(run_dir, overrides={"planner": {"eta": 0.3}})
    with pytest.raises(ValueError, match=r"perception.sensor.max_range .*the node's default"):
        _resumed(run_dir, overrides={"perception": {"sensor.max_range": 3.0}})  # --camera d435
    with pytest.raises(ValueError, match="--params: got .*, expected none with --resume"):
        _resumed(run_dir, params_file=tmp_path / "any.yaml")
    # a run directory from before the parameters were saved resumes with what is given now
    (tmp_path / "older").mkdir()
    older = _saved_run(tmp_path / "older")
    assert parameters(_resumed(older))["perception"]["backend"] == "rgbd"
