"""`area3d bench episode` spread over worker processes (Dask distributed): the same episodes as in
one process, an episode whose worker dies run again, graph episodes on domains of their own."""

from __future__ import annotations

import io
import json
import os
import time
from pathlib import Path

import distributed
import pytest
from rich.console import Console

from area3d_bench.episode import run_episode_bench
from area3d_bench.episode_task import (
    EpisodeResult,
    EpisodeTask,
    HoldoutScene,
    _ensure_holdout,
    holdout_digest,
    materialize,
    run_episode_task,
    write_holdout,
)
from sim_bridge.holdout_scenes import HOLDOUT_WRITERS

SMALL = {"seeds": 1, "policies": ["area3d", "uniform"], "scenes": ["single_object"], "budget": 6}
NAMES = {"single_object_area3d_s0", "single_object_uniform_s0"}


def _console() -> Console:
    return Console(file=io.StringIO(), width=200)


@pytest.fixture(scope="module")
def one_process(tmp_path_factory) -> dict:
    """The small benchmark in this process, one episode after another."""
    out = tmp_path_factory.mktemp("one_process")
    result = run_episode_bench(**SMALL, out=out, console=_console(), in_process=True)
    assert result["failures"] == []
    (run,) = result["runs"]
    assert run["workers"] is None and set(run["episodes"]) == NAMES
    return run


def test_episodes_on_two_local_workers_equal_those_run_in_one_process(tmp_path, one_process):
    console = _console()
    result = run_episode_bench(**SMALL, out=tmp_path, console=console, in_process=True, workers=[2])
    assert result["failures"] == []
    (run,) = result["runs"]
    assert run["workers"] == 2
    for name in NAMES:
        # the same views in the same order, the same metrics after every checkpoint
        assert run["episodes"][name] == one_process["episodes"][name], name
        assert not run["ran_on"][name].endswith(f":{os.getpid()}")  # in a worker process
    # the table and the report read the run directories written here from what came back
    assert {row["policy"] for row in result["rows"]} == {"area3d", "uniform"}
    assert all(row["runs"] == 1 for row in result["rows"])
    assert Path(result["report"]).is_file()
    assert not (run["out_dir"] / "attempts").exists()  # no worker died: nothing left there
    # and how many views each policy took to reach uniform's final completion, uniform's own too
    printed = console.file.getvalue()
    assert "views to reach uniform's final completion" in printed
    (line,) = [
        line for line in printed.splitlines() if "single_object" in line and " of 6 " in line
    ]
    assert line.count(" of 6 (") + line.count("not reached (") == 2, line


def _dies_at_its_first_frame(out: Path, marker: Path):
    """A worker plugin: the first worker process to have written a frame of an episode exits at
    once (os._exit: no clean-up, as a killed process), once in the whole cluster (`marker`)."""
    import threading

    from distributed import WorkerPlugin

    class DiesOnce(WorkerPlugin):
        def setup(self, worker) -> None:
            pid = os.getpid()

            def watch() -> None:
                while not marker.exists():
                    if any(out.glob(f"*/attempts/*-{pid}-*/*/frames/*.npz")):
                        try:
                            fd = os.open(marker, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
                        except FileExistsError:
                            return
                        os.write(fd, str(pid).encode())
                        os.close(fd)
                        os._exit(1)
                    time.sleep(0.02)

            threading.Thread(target=watch, daemon=True).start()

    return DiesOnce()


def test_an_episode_whose_worker_dies_mid_episode_is_run_again(tmp_path, one_process):
    marker = tmp_path / "killed"
    out = tmp_path / "bench"
    with (
        distributed.LocalCluster(
            n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0"
        ) as cluster,
        distributed.Client(cluster) as client,
    ):
        client.register_plugin(_dies_at_its_first_frame(out, marker))
        result = run_episode_bench(
            **SMALL,
            out=out,
            console=_console(),
            in_process=True,
            cluster=cluster.scheduler_address,
        )
    killed = int(marker.read_text())  # a worker did die, with a frame of its episode written
    assert result["failures"] == []
    (run,) = result["runs"]
    for name in NAMES:
        assert run["episodes"][name] == one_process["episodes"][name], name
        assert not run["ran_on"][name].endswith(f":{killed}")
    # what the dead worker had written is kept aside, never taken for the episode's result
    assert run["lost_attempts"] == 1
    (lost,) = (run["out_dir"] / "attempts").iterdir()
    assert f"-{killed}-" in lost.name
    (lost_run,) = lost.iterdir()
    assert lost_run.name in NAMES and list((lost_run / "frames").glob("*.npz"))
    assert not (lost_run / "metrics.json").exists()


def test_graph_episodes_in_parallel_each_lease_a_ros_domain_of_their_own(tmp_path):
    result = run_episode_bench(
        seeds=1,
        policies=["area3d", "uniform"],
        scenes=["single_object"],
        budget=5,
        out=tmp_path,
        console=_console(),
        in_process=False,
        workers=[2],
    )
    assert result["failures"] == []
    (run,) = result["runs"]
    assert len(set(run["ran_on"].values())) == 2  # one episode on each worker, at once
    domains = set()
    for name in NAMES:
        episode = json.loads((run["out_dir"] / name / "episode.json").read_text())
        assert len(episode["views"]) == 5
        domains.add(episode["ros"]["domain_id"])
    assert len(domains) == 2
    assert int(os.environ["ROS_DOMAIN_ID"]) not in domains  # this session's lease is its own


def test_a_hold_out_scene_is_written_on_the_worker_as_the_client_wrote_it(tmp_path):
    here, spec = write_holdout("tabletop", 3, tmp_path / "client" / "tabletop_s3")
    elsewhere = tmp_path / "worker" / "tabletop_s3" / here.name  # not there yet
    task = EpisodeTask("", "uniform", 0, 4, str(tmp_path / "runs"), "tabletop_uniform_s0")
    ok = run_episode_task(
        EpisodeTask(**{**task.__dict__, "scene": str(elsewhere), "holdout": spec, "budget": 4})
    )
    assert ok.error is None, ok.error
    assert ok.worker_scene == str(elsewhere.resolve())
    assert ok.episode()["scene"] == str(elsewhere.resolve())
    # a worker whose generator writes other files refuses rather than run another scene
    stale = HoldoutScene("tabletop", 3, "0" * 64)
    refused = run_episode_task(
        EpisodeTask(**{**task.__dict__, "scene": str(elsewhere), "holdout": stale})
    )
    assert refused.error is not None and "digest" in refused.error and "tabletop" in refused.error


@pytest.mark.parametrize("kind", list(HOLDOUT_WRITERS))
def test_every_hold_out_kind_a_worker_writes_has_the_clients_files(tmp_path, kind):
    here, spec = write_holdout(kind, 0, tmp_path / "client" / f"{kind}_s0")
    elsewhere = tmp_path / "worker" / f"{kind}_s0" / here.name
    task = EpisodeTask(str(elsewhere), "uniform", 0, 5, str(tmp_path / "runs"), "x", holdout=spec)
    assert _ensure_holdout(task) == elsewhere.resolve()
    assert holdout_digest(elsewhere.parent) == spec.digest
    assert not list((tmp_path / "worker").glob(".staging-*"))  # the staging folder is gone


def test_a_result_from_another_machine_names_the_scene_as_this_machine_does(tmp_path):
    here = tmp_path / "holdout" / "tabletop_s0" / "tabletop_s0.xml"
    task = EpisodeTask(str(here), "area3d", 0, 5, str(tmp_path), "tabletop_area3d_s0")
    episode = {"scene": "/elsewhere/holdout/tabletop_s0/tabletop_s0.xml", "policy": "area3d"}
    metrics = {"scene": episode["scene"], "final": {"completion": 0.5}}
    result = EpisodeResult(
        task,
        files={
            "episode.json": json.dumps(episode).encode(),
            "metrics.json": json.dumps(metrics).encode(),
            "eval/gt_sample.npy": b"\x93NUMPY",
        },
        worker_scene=episode["scene"],
    )
    run_dir = materialize(result, tmp_path / "tabletop_area3d_s0")
    assert json.loads((run_dir / "episode.json").read_text())["scene"] == str(here.resolve())
    written = json.loads((run_dir / "metrics.json").read_text())
    assert written["scene"] == str(here.resolve()) and written["final"] == {"completion": 0.5}
    assert (run_dir / "eval" / "gt_sample.npy").read_bytes() == b"\x93NUMPY"


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--workers", "two"], "workers: got 'two', expected an int >= 1"),
        (["--workers", "0"], "workers: got '0', expected an int >= 1"),
        (["--workers", "2", "--cluster", "tcp://127.0.0.1:8786"], "expected one of them"),
        (["--holdout-kinds", "tabletop,kitchen"], "holdout_kinds: got ['kitchen'], expected"),
        # each of these failed every episode, and the command ended 'done' with exit 0
        (["--scenes", "single_object,nosuch"], "scenes: got ['nosuch'], expected bundled"),
        (["--policies", "area3d,foo"], "policies: got ['foo'], expected names among"),
        (["--seeds", "0"], "seeds: got 0, expected an int >= 1"),
        (["--budget", "0"], "budget: got 0, expected the total number of views"),
    ],
)
def test_the_bench_command_refuses_bad_worker_options_before_running_anything(
    tmp_path, args, message
):
    from typer.testing import CliRunner

    from area3d_bench.cli import app

    result = CliRunner().invoke(app, ["episode", "--out", str(tmp_path), *args])
    assert result.exit_code == 2
    assert message in " ".join(result.output.split())
    assert not any(tmp_path.iterdir())  # nothing was started or written


def test_the_bench_command_exits_non_zero_when_episodes_failed(tmp_path):
    """A scene file that exists and does not load: its episode fails; the command says how many
    failed and exits 1 (it printed 'failed' and exited 0, as a run of good episodes does)."""
    from typer.testing import CliRunner

    from area3d_bench.cli import app

    scene = tmp_path / "broken.xml"
    scene.write_text("<mujoco><worldbody><geom type='box' size='0.1 0.1'")
    args = ["episode", "--in-process", "--no-holdout", "--scenes", str(scene), "--policies"]
    args += ["uniform", "--seeds", "1", "--budget", "5", "--out", str(tmp_path / "runs")]
    result = CliRunner().invoke(app, args)
    text = " ".join(result.output.split())
    assert result.exit_code == 1, text
    assert "failed" in text and "1 episodes failed" in text
