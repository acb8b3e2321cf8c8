"""The `area3d` command: run episodes, launch the graph, write reports; and the command groups
that installed packages add through the `area3d.cli` entry point group (`area3d bench`)."""

from __future__ import annotations

import importlib
import importlib.metadata
import os
import shlex
import sys
from pathlib import Path

import typer
from rich.console import Console
from rich.markup import escape
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn
from typer.core import TyperCommand, TyperGroup

# Entry points of this group name a typer app each, added as `area3d NAME` (as ros2cli adds the
# verbs of its `ros2cli.command` group); pyproject.toml declares them.
COMMAND_GROUP = "area3d.cli"


def command_entry_points() -> list[importlib.metadata.EntryPoint]:
    """The installed entry points of `COMMAND_GROUP` (pyproject.toml, a colcon package's setup.py)."""
    return list(importlib.metadata.entry_points(group=COMMAND_GROUP))


class CommandGroup(TyperGroup):
    """The `area3d` group: its own commands, then those of the installed `COMMAND_GROUP` entry
    points, loaded only when listed (help) or asked for by a name of its own (`area3d run` loads
    none). One that does not load is left out with a warning on stderr, the others still run."""

    def _add_entry_point_commands(self, name: str | None = None) -> None:
        for entry_point in command_entry_points():
            if entry_point.name in self.commands or name not in (None, entry_point.name):
                continue
            try:
                command = typer.main.get_command(entry_point.load())
            except Exception as err:  # whatever a broken installation raises
                console.print(
                    escape(
                        f"warning: `area3d {entry_point.name}` is unavailable: {entry_point.value} "
                        f"did not load ({type(err).__name__}: {err})"
                    )
                )
                continue
            command.name = entry_point.name  # the help's list shows a command by its name
            self.add_command(command)

    def list_commands(self, ctx: typer.Context) -> list[str]:
        self._add_entry_point_commands()
        return super().list_commands(ctx)

    def get_command(self, ctx: typer.Context, cmd_name: str) -> TyperCommand | TyperGroup | None:
        if cmd_name not in self.commands:
            self._add_entry_point_commands(cmd_name)
        return super().get_command(ctx, cmd_name)


app = typer.Typer(
    cls=CommandGroup,
    add_completion=False,
    no_args_is_help=True,
    help="AREA3D: active 3D reconstruction over a ROS 2 node graph.",
)
console = Console(stderr=True)

PARAM_HELP = "NODE.NAME=VALUE parameter override, repeatable (e.g. planner.eta=0.3)"
FOXGLOVE_HELP = "serve every topic on a Foxglove WebSocket on PORT (alone: 8765), for Foxglove"
FOXGLOVE_ADDRESS_HELP = "address the Foxglove WebSocket listens on (0.0.0.0: every interface)"
DEFAULT_FOXGLOVE_PORT = 8765  # area3d_bringup/foxglove_bridge.py: DEFAULT_PORT


def _overrides(params: list[str]) -> dict[str, dict]:
    from area3d_bringup.launch_description import parse_overrides

    return parse_overrides(params)


def _camera_overrides(camera: str, params: list[str]) -> dict[str, dict]:
    """`--camera`'s parameters, then `-p`'s over them."""
    from area3d_bringup.launch_description import merge
    from area3d_bringup.presets import camera_preset

    try:
        return merge(camera_preset(camera), _overrides(params))
    except ValueError as err:
        _fail(str(err))


def _episode_nodes(text: str) -> tuple[str, ...] | None:
    """`area3d run --nodes`: None (every node), () for `none` (the mission manager alone, driving
    a graph started elsewhere), else the names listed."""
    names = tuple(n.strip() for n in text.split(",") if n.strip())
    if names == ("none",):
        return ()
    if "none" in names:
        _fail(f"nodes: got {list(names)}, expected `none` alone or names of graph nodes")
    return names or None


def _fail(message: str) -> None:
    # one line, never wrapped by rich: a path or value in it stays whole (to copy, to grep)
    console.print(f"[bold red]error:[/] {escape(message)}", soft_wrap=True)
    raise typer.Exit(code=2)


@app.command()
def run(
    ctx: typer.Context,
    scene: str = typer.Option(
        "single_object", help="bundled scene name or path to a MuJoCo MJCF file"
    ),
    policy: str = typer.Option(
        "area3d",
        help="area3d | paper | random | uniform | vlm_naive | volumetric_ig | no_vlm | no_ff | "
        "gamma0",
    ),
    camera: str = typer.Option(
        "ideal",
        help="the camera class the simulated camera, perception and the planner describe: ideal "
        "(no minimum range, 5 m) | kinect (structured light, 0.5-4.5 m) | d435 (active stereo, "
        "0.28-3 m); -p parameters override it",
    ),
    budget: int = typer.Option(
        None,
        help="view budget T: total views, the initial views O_0 included (default: the "
        "paper's, 25 object / 40 room)",
    ),
    mode: str = typer.Option(
        "closed_loop", help="closed_loop (re-plan after each view) | batch (paper)"
    ),
    seed: int = typer.Option(0),
    out: Path = typer.Option(Path("runs"), help="where run directories are created"),
    resume: Path = typer.Option(
        None,
        help="continue an interrupted run directory, with the run's own scene, policy, seed, "
        "budget, mode, depth source and node parameters (one of those given with another value "
        "is refused)",
    ),
    record: bool = typer.Option(True, help="record the episode as rosbag2 (MCAP)"),
    evaluate: bool = typer.Option(
        True, help="reconstruct, score and write the report after the episode"
    ),
    params: Path = typer.Option(None, help="ROS 2 parameter YAML replacing the bundled defaults"),
    param: list[str] = typer.Option([], "--param", "-p", help=PARAM_HELP),
    domain_id: int = typer.Option(
        None, help="ROS_DOMAIN_ID for the graph (default: $ROS_DOMAIN_ID, else a free domain)"
    ),
    namespace: str = typer.Option("", help="ROS namespace of the graph, e.g. /robot1"),
    nodes: str = typer.Option(
        "",
        help="comma list of the graph nodes to start here (default: all; others run elsewhere); "
        "none: start no node, drive a graph started elsewhere (`area3d launch`); a camera, "
        "planner and semantics started elsewhere are reset first",
    ),
    depth_source: str = typer.Option(
        "sensor",
        help="what the TSDF reconstructs from: sensor (the camera's depth) | estimated (perception's)",
    ),
    respawn: bool = typer.Option(
        False, help="restart a node that dies and go on with the episode (instead of stopping)"
    ),
    respawn_delay: float = typer.Option(1.0, help="seconds before a dead node is restarted"),
    respawn_retries: int = typer.Option(3, help="restarts allowed per node"),
    min_free_mb: float = typer.Option(
        None, help="refuse to start with less free space in --out, MiB (default: 1024)"
    ),
    foxglove: int = typer.Option(None, "--foxglove", metavar="[PORT]", help=FOXGLOVE_HELP),
    foxglove_address: str = typer.Option("127.0.0.1", help=FOXGLOVE_ADDRESS_HELP),
) -> None:
    """Run one episode over the node graph, then evaluate it and write the report."""
    from area3d_bringup.episode_config import RESUMED_FIELDS, EpisodeConfig, EpisodeError
    from area3d_bringup.runner import run_episode

    config = EpisodeConfig(
        scene=scene,
        policy=policy,
        budget=budget,
        mode=mode,
        seed=seed,
        out_dir=out,
        record=record,
        params_file=params,
        overrides=_camera_overrides(camera, param),
        domain_id=domain_id,
        namespace=namespace,
        nodes=_episode_nodes(nodes),
        depth_source=depth_source,
        respawn=respawn,
        respawn_delay_s=respawn_delay,
        respawn_max_retries=respawn_retries,
        foxglove_port=foxglove,
        foxglove_address=foxglove_address,
        # (typer's own click: its ParameterSource is not click's, so by name)
        given=frozenset(
            name
            for name in RESUMED_FIELDS
            if getattr(ctx.get_parameter_source(name), "name", "") == "COMMANDLINE"
        ),
        **({} if min_free_mb is None else {"min_free_mb": min_free_mb}),
    )
    columns = (
        TextColumn("{task.description}"),
        BarColumn(),
        TextColumn("{task.completed}/{task.total}"),
        TimeElapsedColumn(),
    )
    if foxglove is not None:
        from area3d_bringup.foxglove_bridge import url

        console.print(
            f"Foxglove live view on {url(foxglove_address, foxglove)} (open it in Foxglove)"
        )
    try:
        with Progress(*columns, console=console) as progress:
            run_dir = run_episode(config, resume=resume, progress=progress)
    except (EpisodeError, ValueError, FileNotFoundError, FileExistsError) as err:
        _fail(str(err))
    console.print(f"episode written to [bold]{escape(str(run_dir))}[/]")
    if evaluate:
        try:
            report_paths = _evaluate_and_report([run_dir], run_dir / "report")
        except KeyboardInterrupt:  # the episode is on disk: say how to finish the report
            console.print(  # one line, never folded: the command is copied from it
                "stopped while evaluating; the episode is complete: "
                f"`area3d report {escape(shlex.quote(str(run_dir)))}` evaluates it",
                soft_wrap=True,
            )
            raise typer.Exit(code=130) from None
        print(f"report: {report_paths[1]}")


def _evaluate_and_report(run_dirs: list[Path], out_dir: Path) -> tuple[Path, Path]:
    from area3d_eval.report import write_report

    with console.status("reconstructing, scoring and writing the report"):
        return write_report(run_dirs, out_dir)


@app.command()
def report(
    run_dirs: list[Path] = typer.Argument(..., help="run directories written by `area3d run`"),
    out: Path = typer.Option(
        None, help="report directory (default: RUN_DIR/report for one run, ./report otherwise)"
    ),
) -> None:
    """Evaluate run directories (if not yet) and write a Markdown + HTML report."""
    from area3d_eval.rundir import EPISODE_FILE
    from area3d_msgs_py.errors import InputError

    for run_dir in run_dirs:
        if not (run_dir / EPISODE_FILE).is_file():
            _fail(f"run dir: got {str(run_dir)!r}, expected a directory containing episode.json")
    out = out or (run_dirs[0] / "report" if len(run_dirs) == 1 else Path("report"))
    try:
        md, html = _evaluate_and_report(run_dirs, out)
    except (InputError, ValueError) as err:  # a damaged run directory, a scene that moved
        _fail(str(err))
    print(f"report: {html}\nmarkdown: {md}")


@app.command()
def export(
    map_file: Path = typer.Argument(
        ..., help="a saved reconstruction volume (a run's maps/reconstruction.a3map, or save_map's)"
    ),
    out: Path = typer.Argument(..., help="the mesh to write, a .ply file"),
) -> None:
    """Write the mesh of a saved reconstruction volume as PLY, with no graph running."""
    from area3d_msgs_py.errors import InputError
    from area3d_reconstruction import map_io

    try:
        written, size = map_io.export_mesh(map_io.mesh_of_file(map_file), out)
    except (InputError, OSError) as err:
        _fail(str(err))
    # one line, never wrapped: the paths stay whole (to copy)
    console.print(f"the mesh of {map_file} written to {written} ({size} bytes)", soft_wrap=True)


@app.command()
def launch(
    params: Path = typer.Option(None, help="ROS 2 parameter YAML replacing the bundled defaults"),
    param: list[str] = typer.Option([], "--param", "-p", help=PARAM_HELP),
    localhost: bool = typer.Option(
        False, help="keep discovery on this machine (ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST)"
    ),
    domain_id: int = typer.Option(None, help="ROS_DOMAIN_ID (default: $ROS_DOMAIN_ID or 0)"),
    namespace: str = typer.Option("", help="ROS namespace of the graph, e.g. /robot1"),
    nodes: str = typer.Option("", help="comma list of the graph nodes to start (default: all)"),
    respawn: bool = typer.Option(False, help="restart a node that dies instead of stopping all"),
    respawn_delay: float = typer.Option(1.0, help="seconds before a dead node is restarted"),
    respawn_retries: int = typer.Option(3, help="restarts allowed per node"),
    foxglove: int = typer.Option(None, "--foxglove", metavar="[PORT]", help=FOXGLOVE_HELP),
    foxglove_address: str = typer.Option("127.0.0.1", help=FOXGLOVE_ADDRESS_HELP),
    remap: list[str] = typer.Option(
        [],
        "--remap",
        "-r",
        help="FROM:=TO remapping for every node, e.g. area3d/odom:=/odom (a driver's topics)",
    ),
) -> None:
    """Start the node graph and keep it running (Ctrl-C stops every node)."""
    for rule in remap:
        source, sep, target = rule.partition(":=")
        if not (sep and source and target):
            _fail(f"--remap: got {rule!r}, expected FROM:=TO, e.g. area3d/odom:=/odom")
    import faulthandler
    import signal
    import tempfile

    # `kill -USR1` prints where every thread of the launcher is (a stop that hangs can be read)
    faulthandler.register(signal.SIGUSR1, all_threads=True)

    from area3d_bringup.launch_description import build_graph, load_parameters
    from area3d_bringup.launcher import Launcher, NodeDied
    from area3d_msgs_py import middleware

    env = middleware.graph_env(domain_id, discovery_range="LOCALHOST" if localhost else None)
    try:
        specs = build_graph(load_parameters(params), _overrides(param))
    except (ValueError, FileNotFoundError) as err:
        _fail(str(err))
    names = [n for n in nodes.split(",") if n]
    unknown = sorted(set(names) - {spec.name for spec in specs})
    if unknown:
        _fail(f"nodes: got {unknown}, expected names from {[spec.name for spec in specs]}")
    specs = [spec for spec in specs if not names or spec.name in names]
    if foxglove is not None:
        from area3d_bringup.foxglove_bridge import bridge_spec

        specs.append(bridge_spec(foxglove, foxglove_address))
    with tempfile.TemporaryDirectory(prefix="area3d-launch-") as workdir:
        launcher = Launcher(
            specs,
            Path(workdir),
            env=env,
            namespace=namespace,
            respawn=respawn,
            respawn_delay_s=respawn_delay,
            respawn_max_retries=respawn_retries,
            ros_args=[arg for rule in remap for arg in ("-r", rule)],
        )
        launcher.start()
        domain = env.get("ROS_DOMAIN_ID") or os.environ.get("ROS_DOMAIN_ID") or "0"
        reach = env.get("ROS_AUTOMATIC_DISCOVERY_RANGE") or os.environ.get(
            "ROS_AUTOMATIC_DISCOVERY_RANGE", "SUBNET (ROS 2's default)"
        )
        console.print(  # where a user's `ros2` tools find the graph, as `area3d run` says it
            f"started {', '.join(s.name for s in specs)} on ROS_DOMAIN_ID={domain}, namespace "
            f"{namespace or '/'}, transport {env.get(middleware.TRANSPORT_ENV)}, discovery "
            f"{reach}; Ctrl-C stops them"
        )
        code = 0
        try:
            launcher.wait()
        except NodeDied as err:
            console.print(f"[bold red]{escape(str(err))}[/]")
            code = 1
        finally:
            launcher.stop()
    raise typer.Exit(code)


@app.command(
    context_settings={"allow_extra_args": True, "ignore_unknown_options": True},
)
def node(
    ctx: typer.Context,
    name: str = typer.Argument(
        ..., help="sim_bridge | perception | semantics | planner | reconstruction"
    ),
) -> None:
    """Run a single node in the foreground; further arguments go to it, as with `ros2 run`
    (e.g. `area3d node planner --ros-args -p eta:=0.5 -r __ns:=/robot1`)."""
    from area3d_bringup.launch_description import GRAPH_NODES

    modules = dict(GRAPH_NODES)
    if name not in modules:
        _fail(f"node: got {name!r}, expected one of {sorted(modules)}")
    raise typer.Exit(importlib.import_module(modules[name]).main(list(ctx.args)) or 0)


@app.command()
def rviz(
    scene: str = typer.Option(None, help="the camera's scene (default: the parameters')"),
    params: Path = typer.Option(None, help="ROS 2 parameter YAML replacing the bundled defaults"),
    param: list[str] = typer.Option([], "--param", "-p", help=PARAM_HELP),
    out: Path = typer.Option(Path("area3d.rviz"), help="where to write the configuration"),
    namespace: str = typer.Option("", help="ROS namespace of the graph, e.g. /robot1"),
    start: bool = typer.Option(False, help="then start rviz2 with it (a sourced ROS 2)"),
) -> None:
    """Write the RViz configuration of a launch: the grid's boxes the size of its voxels."""
    from area3d_bringup.launch_description import build_graph, load_parameters
    from area3d_bringup.rviz import write_config

    overrides = _overrides(param)
    if scene:
        overrides.setdefault("sim_bridge", {})["scene"] = scene
    try:
        specs = build_graph(load_parameters(params), overrides)
    except ValueError as err:  # an unknown scene, a parameter file that does not fit
        _fail(str(err))
    voxel = write_config(out, next(s for s in specs if s.name == "planner").parameters)
    command = ["rviz2", "-d", str(out)]
    if namespace:
        command += ["--ros-args", "-r", f"__ns:={namespace}"]
    print(f"wrote {out} (grid boxes {voxel:g} m)\n{' '.join(command)}")
    if start:
        import shutil

        if shutil.which("rviz2") is None:
            _fail("rviz2: not found, expected a sourced ROS 2 (source /opt/ros/jazzy/setup.bash)")
        os.execvp("rviz2", command)


@app.command("middleware-profile")
def middleware_profile(
    transport: str = typer.Argument("shm", help="shm (shared memory + UDP) or udp"),
) -> None:
    """Print the path of the graph's Fast DDS profile, for a camera driver to load too, e.g.
    FASTRTPS_DEFAULT_PROFILES_FILE=$(area3d middleware-profile) ros2 launch ...: its 32 MB
    shared-memory segment carries a 848x480 frame whole (Fast DDS' default 0.5 MB does not, and
    such frames then cross fragmented UDP, where a 30 Hz stream loses most of them)."""
    from area3d_msgs_py.errors import InputError
    from area3d_msgs_py.middleware import profile_path

    try:
        print(profile_path(transport))
    except InputError as exc:
        _fail(str(exc))


@app.command()
def scenes() -> None:
    """List the bundled scenes."""
    from sim_bridge.scenes import list_scenes, load_scene

    for name in list_scenes():
        scene = load_scene(name)
        print(
            f"{name:16s} {scene.level:7s} |O_0|={len(scene.initial_views):2d} held-out={len(scene.eval_views)}"
        )


def with_foxglove_port(args: list[str]) -> list[str]:
    """`--foxglove` without a port (last, or before another option) means the default port."""
    out: list[str] = []
    for i, arg in enumerate(args):
        out.append(arg)
        if arg == "--foxglove" and (i + 1 == len(args) or args[i + 1].startswith("-")):
            out.append(str(DEFAULT_FOXGLOVE_PORT))
    return out


def main() -> None:
    app(args=with_foxglove_port(sys.argv[1:]), prog_name="area3d")


if __name__ == "__main__":
    sys.exit(main())
