"""What one episode of `area3d run` is asked to do (`EpisodeConfig`), and how it fails."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from area3d_bringup.graph import GRAPH_NODES
from area3d_bringup.presets import preset
from area3d_eval import rundir

MODES = ("closed_loop", "batch")


def episode_budget(scene, budget: int | None) -> int:
    """The view budget T of an episode on `scene` (O_0 included): the paper's for its level when
    None; ValueError when it does not hold the initial views."""
    from area3d_planner.levels import paper_budget

    total = paper_budget(scene.level) if budget is None else int(budget)
    if total < len(scene.initial_views):
        raise ValueError(
            f"budget: got {total}, expected the total number of views, at least "
            f"|O_0| = {len(scene.initial_views)}"
        )
    return total


class EpisodeError(RuntimeError):
    """The episode could not go on; the message says why and what was kept."""


class GraphInUse(EpisodeError):
    """Nodes of the graph a run would start run already on its domain and namespace."""


# what a resumed run reads from its own episode.json, not from the config
RESUMED_FIELDS = ("scene", "policy", "mode", "seed", "budget", "depth_source")


@dataclass
class EpisodeConfig:
    scene: str = "single_object"
    policy: str = "area3d"  # a run preset (area3d_bringup/presets.py)
    budget: int | None = None  # total views, O_0 included; None: the paper's T (25 object, 40 room)
    mode: str = "closed_loop"
    seed: int = 0
    out_dir: Path = Path("runs")
    run_name: str | None = None
    record: bool = True
    params_file: Path | None = None
    overrides: dict[str, dict] = field(default_factory=dict)
    domain_id: int | None = None  # None: $ROS_DOMAIN_ID, else a free domain
    namespace: str = ""  # ROS namespace of the graph and the runner, e.g. "/robot1"
    transport: str | None = None  # middleware.TRANSPORTS; None: $AREA3D_TRANSPORT or "shm"
    # graph nodes this runner starts (None: all, (): none); the others run elsewhere (`area3d launch`)
    nodes: tuple[str, ...] | None = None
    # generous: every wait ends as soon as what it waits for arrives, and a node's first frame
    # on a fresh install compiles its kernels (tens of seconds on a busy 2-core machine)
    capture_timeout_s: float = 120.0
    plan_timeout_s: float = 120.0
    fuse_timeout_s: float = 120.0
    startup_timeout_s: float = 90.0
    # what the TSDF integrates (rundir.DEPTH_SOURCES): the camera's depth, or perception's estimate
    # (then kept in every frame file)
    depth_source: str = "sensor"
    # a node that dies is restarted (bounded) and the episode goes on, instead of stopping it
    respawn: bool = False
    respawn_delay_s: float = 1.0
    respawn_max_retries: int = 3  # per node
    min_free_mb: float = rundir.MIN_FREE_MB  # the output directory must have this much free
    # capture stamps in ns (None: the runner's ROS clock); tests inject time instead of sleeping
    clock: Callable[[], int] | None = None
    # serve every topic on a Foxglove WebSocket on this port (None: no live view)
    foxglove_port: int | None = None
    foxglove_address: str = "127.0.0.1"  # this machine only unless told otherwise
    # the fields of RESUMED_FIELDS the user gave (the CLI's options on the command line): a
    # resumed run keeps its own and refuses one of these that differs from it
    given: frozenset[str] = frozenset()

    def validate(self) -> None:
        """Raise ValueError naming the first field that cannot run."""
        preset(self.policy)
        graph_names = [name for name, _ in GRAPH_NODES]
        if self.nodes is not None and not set(self.nodes) <= set(graph_names):
            raise ValueError(f"nodes: got {list(self.nodes)}, expected names from {graph_names}")
        if self.mode not in MODES:
            raise ValueError(f"mode: got {self.mode!r}, expected 'closed_loop' or 'batch'")
        rundir.check_depth_source(self.depth_source)
        if self.domain_id is not None:  # before the run directory is made
            from area3d_msgs_py.middleware import check_domain_id

            check_domain_id(self.domain_id)
