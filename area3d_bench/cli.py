"""`area3d bench NAME`: the benchmarks' command line. The `area3d` command adds this typer app as
its `bench` group through the `area3d.cli` entry point group (pyproject.toml, setup.py), so the
product packages name no benchmark; `python -m area3d_bench.cli NAME` runs it alone."""

from __future__ import annotations

import importlib
from pathlib import Path

import typer
from rich.console import Console
from rich.markup import escape

from area3d_bringup.cli import PARAM_HELP

# Help texts are rich markup (typer's default): a literal `[word]` is written escape("[word]").
app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    help="Benchmarks: print measured figures beside their targets.",
)
console = Console(stderr=True)

# `area3d bench NAME` with no options: NAME -> (the module whose run_bench() prints the figures,
# what it measures: the help line, written here so that `area3d --help` imports none of them)
BENCHES = {
    "transport": ("area3d_bench.transport", "the graph's transport between two processes"),
    "tf": ("area3d_bench.tf", "a camera pose per frame from a robot's TF tree or odometry"),
    "render": ("area3d_bench.render", "frames per second of the simulated RGB-D camera"),
    "stereo": ("area3d_bench.stereo", "stereo depth per frame: time, error, confidence ranking"),
    "stereo-confidence": (
        "area3d_bench.stereo_confidence",
        "fit the stereo backend's calibrated confidence",
    ),
    "perception": ("area3d_bench.perception", "perception's whole frame and each of its steps"),
    "semantics": ("area3d_bench.semantics", "parse, weight maps and U_sem of a room-level query"),
    "planner": ("area3d_bench.planner", "visibility cache build and 40-view lazy greedy"),
    "reconstruction": (
        "area3d_bench.reconstruction",
        "a frame integrated, the mesh extracted; map save and load",
    ),
    "eval": ("area3d_bench.evaluation", "the evaluation of an object-level episode"),
    "foxglove": ("area3d_bench.foxglove", "what the Foxglove live view costs"),
}


def _fail(message: str) -> None:
    # one line, never wrapped by rich: a path or value in it stays whole (to copy, to grep)
    console.print(f"[bold red]error:[/] {escape(message)}", soft_wrap=True)
    raise typer.Exit(code=2)


def _bench_command(name: str, module: str, what: str) -> None:
    def command() -> None:
        importlib.import_module(module).run_bench()

    command.__doc__ = f"Benchmark: {what} (see {module})."
    app.command(name)(command)


for _name, (_module, _what) in BENCHES.items():
    _bench_command(_name, _module, _what)


@app.command("soak")
def bench_soak(
    frames: int = typer.Option(
        6000, help="frames to stream (the run ends at --frames or --duration)"
    ),
    duration: float = typer.Option(600.0, help="longest stream, seconds"),
    rate: float = typer.Option(10.0, help="camera rate, Hz"),
    scene: str = typer.Option("single_object"),
    mask_lag: float = typer.Option(
        1.0, help="the planner's mask_lag_s (0: every request waits for masks covering its frame)"
    ),
    rebuild_nice: int = typer.Option(
        10, help="the planner's rebuild_nice (0: its mask rebuilds compete with fusion for the CPU)"
    ),
    json_out: Path = typer.Option(
        None, "--json", help="also write every figure, and each request's times, to this file"
    ),
) -> None:
    """Benchmark: 640x480 RGB-D at 10 Hz through perception and the planner (see area3d_bench.soak)."""
    from area3d_bench.soak import run_bench

    run_bench(
        frames=frames,
        duration_s=duration,
        rate_hz=rate,
        scene_name=scene,
        mask_lag_s=mask_lag,
        rebuild_nice=rebuild_nice,
        json_out=json_out,
    )


@app.command("robot")
def bench_robot(
    runs: str = typer.Option(
        "triggered,stream,stream-default-dds",
        help="missions side by side: triggered (one frame per view, the reference), stream, "
        "stream-lossy (the driver loses a third of its parts), stream-default-dds (the driver "
        "on Fast DDS' default profile)",
    ),
    seeds: int = typer.Option(1, help="seeds per mission (mean and range are printed)"),
    planned: int = typer.Option(10, help="views asked for after the initial ones"),
    rate: float = typer.Option(30.0, help="the streaming camera's rate, Hz"),
    render_scale: float = typer.Option(1.0, help="the driver renders at this fraction of 848x480"),
    scene: str = typer.Option("single_object"),
    json_out: Path = typer.Option(None, "--json", help="also write every figure to this file"),
) -> None:
    """Benchmark: a mission beside a streaming robot driver (see area3d_bench.robot_bench)."""
    from area3d_bench.robot_bench import run_bench

    try:
        run_bench(runs, seeds, planned, rate, render_scale, scene, json_out)
    except ValueError as err:
        _fail(str(err))


@app.command("views-depth")
def bench_views_depth(
    root: Path = typer.Argument(
        ..., help="folder of run directories recorded with --depth-source estimated"
    ),
    workers: int = typer.Option(1, help="evaluate the runs in this many processes"),
) -> None:
    """Benchmark: estimated-depth runs rebuilt from the camera's depth at the same views: what
    the views cost and what the depth cost; also written to ROOT/views_depth.json (see
    area3d_bench.views_depth)."""
    from area3d_bench.views_depth import run_bench

    if workers < 1:
        _fail(f"workers: got {workers!r}, expected an int >= 1")
    try:
        run_bench(root, workers)
    except ValueError as err:
        _fail(str(err))


@app.command("map-truth")
def bench_map_truth(
    root: Path = typer.Argument(
        ..., help="folder of run directories recorded with --depth-source estimated"
    ),
    workers: int = typer.Option(1, help="replay the runs in this many processes"),
) -> None:
    """Benchmark: each estimated-depth run's frames fused again into a planner of its parameters;
    the share of the region's ground-truth surface its map holds free, unknown, occupied; also
    written to ROOT/map_truth.json (see area3d_bench.map_truth)."""
    from area3d_bench.map_truth import run_bench

    if workers < 1:
        _fail(f"workers: got {workers!r}, expected an int >= 1")
    try:
        run_bench(root, workers)
    except ValueError as err:
        _fail(str(err))


@app.command("episode")
def bench_episode(
    seeds: int = typer.Option(3),
    policies: str = typer.Option(
        "area3d,paper,random,uniform,vlm_naive,volumetric_ig,no_vlm,no_ff,gamma0"
    ),
    scenes_: str = typer.Option(
        "", "--scenes", help="comma list of names or MJCF paths (default: every bundled scene)"
    ),
    holdout: bool = typer.Option(
        True,
        help="also generate and run the hold-out scenes (tabletop, alcove room, shelf against a "
        "wall, thin objects, scanned objects on a counter; seed 0 of each)",
    ),
    holdout_kinds: str = typer.Option(
        "",
        help="comma list of the hold-out kinds to generate, e.g. tabletop,scanned_counter "
        "(default: every kind)",
    ),
    budget: int = typer.Option(
        None, help="view budget T per episode, O_0 included (default: the paper's, 25 / 40)"
    ),
    out: Path = typer.Option(Path("runs/bench")),
    in_process: bool = typer.Option(
        False, help="call the nodes' cores in one process (same views, no transport; faster)"
    ),
    param: list[str] = typer.Option([], "--param", "-p", help=PARAM_HELP),
    depth_source: str = typer.Option(
        "sensor",
        help="what the TSDF reconstructs from: sensor (the camera's depth) | estimated (perception's)",
    ),
    workers: str = typer.Option(
        "",
        help="run the episodes in this many worker processes on this machine (a local Dask "
        "cluster); a comma list such as 1,2 runs them once per count and prints the wall times "
        "side by side (default: one after another in this process)",
    ),
    cluster: str = typer.Option(
        None,
        help="run the episodes on the workers of the Dask cluster whose scheduler is at this "
        f"address, e.g. tcp://10.0.0.5:8786 (needs the {escape('[cluster]')} extra on every "
        "machine)",
    ),
) -> None:
    """Every policy on every scene with several seeds; prints the table."""
    from area3d_bench.episode import run_episode_bench
    from area3d_bringup.launch_description import parse_overrides

    counts: list[int] = []
    for text in (w.strip() for w in workers.split(",") if w.strip()):
        if not text.isdigit() or int(text) < 1:
            _fail(f"workers: got {text!r}, expected an int >= 1 or a comma list of them (1,2)")
        counts.append(int(text))
    if counts and cluster:
        _fail(
            f"workers, cluster: got --workers {workers} and --cluster {cluster}, expected one of "
            "them (a cluster has its own workers)"
        )
    try:
        result = run_episode_bench(
            seeds=seeds,
            policies=policies.split(","),
            scenes=[s for s in scenes_.split(",") if s],
            budget=budget,
            out=out,
            console=console,
            in_process=in_process,
            holdout=holdout,
            holdout_kinds=[k.strip() for k in holdout_kinds.split(",") if k.strip()] or None,
            overrides=parse_overrides(param),
            depth_source=depth_source,
            workers=counts or None,
            cluster=cluster,
        )
    except (RuntimeError, ValueError) as err:
        _fail(str(err))
    if result["failures"]:  # the table holds the rest; the command says that some failed
        console.print(f"[bold red]{len(result['failures'])} episodes failed[/] (above)")
        raise typer.Exit(code=1)


if __name__ == "__main__":
    app(prog_name="area3d bench")
