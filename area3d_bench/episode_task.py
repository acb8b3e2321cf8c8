"""One benchmark episode as a task that any process can run: in this process, in a worker process
on this machine, or on another machine of a cluster (`episode_cluster.py`).

A task names everything the episode depends on (scene, policy, seed, budget, overrides), so the
episode it runs is the one `area3d bench episode` runs in one process: the same views and the same
metrics. The worker runs the episode, evaluates it (reconstruction and metrics, next to its frames)
and sends back the small files of its run directory; the frames stay on the worker's disk.

A worker writes into a folder of its own under `OUT/attempts/` and renames the run directory into
place only once it is evaluated: an episode whose worker died is run again from the start by
another worker, and what the dead one had written stays in `attempts/` without ever being taken
for a result.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import resource
import shutil
import socket
import time
import uuid
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from area3d_bringup.episode_config import EpisodeConfig, EpisodeError
from area3d_bringup.launch_description import merge
from area3d_bringup.presets import RUN_PRESETS
from area3d_bringup.runner import run_episode
from area3d_eval import rundir

__all__ = [
    "ATTEMPTS_DIR",
    "EpisodeResult",
    "EpisodeTask",
    "HoldoutScene",
    "episode_summary",
    "holdout_digest",
    "materialize",
    "run_episode_task",
    "with_policy",
    "write_holdout",
]

ATTEMPTS_DIR = "attempts"  # under the benchmark's output folder: each worker's own folder
# What a worker sends back of a run directory: everything the table and the report read, not the
# frames (tens of MB an episode) or the bag and the reconstructed mesh.
RESULT_FILES = (
    rundir.EPISODE_FILE,
    rundir.METRICS_FILE,
    f"{rundir.EVAL_DIR}/gt_sample.npy",
    rundir.GRID_INITIAL_FILE,
    rundir.GRID_FINAL_FILE,
    rundir.LOG_FILE,
)


@dataclass(frozen=True)
class HoldoutScene:
    """A generated hold-out scene (`sim_bridge.holdout_scenes`): a worker writes it itself from
    `kind` and `seed` and checks its files against `digest`, the client's copy."""

    kind: str
    seed: int
    digest: str


@dataclass(frozen=True)
class EpisodeTask:
    """One episode of the benchmark, as the client names it."""

    scene: (
        str  # a bundled scene's name or an MJCF path (a hold-out's: where each machine writes it)
    )
    policy: str
    seed: int
    budget: int | None
    out_dir: str  # the benchmark's output folder; a relative path is relative to each worker's cwd
    run_name: str
    in_process: bool = False
    overrides: dict[str, dict] = field(default_factory=dict)
    depth_source: str = "sensor"
    holdout: HoldoutScene | None = None


@dataclass
class EpisodeResult:
    """What came back of one task: the run directory's small files ({relative path: bytes}), or the
    error that stopped it. `worker`: host and pid of the process that ran it."""

    task: EpisodeTask
    files: dict[str, bytes] = field(default_factory=dict)
    worker: str = ""
    seconds: float = 0.0
    cpu_s: float = 0.0  # CPU time the episode and its evaluation took (every thread and child)
    error: str | None = None
    worker_scene: str | None = None  # an MJCF path scene, resolved on the worker

    def episode(self) -> dict[str, Any]:
        return json.loads(self.files[rundir.EPISODE_FILE])

    def metrics(self) -> dict[str, Any]:
        return json.loads(self.files[rundir.METRICS_FILE])


def with_policy(overrides: dict[str, dict] | None, policy: str) -> dict[str, dict]:
    """The bench's overrides for one policy: an ablation's own settings win over the command
    line's (no_ff keeps its uniform confidence whatever the backend)."""
    return merge(overrides, RUN_PRESETS.get(policy, {}))


# -- generated hold-out scenes -------------------------------------------------------------------
def holdout_digest(folder: Path) -> str:
    """sha256 over the relative names and bytes of every file in `folder`."""
    digest = hashlib.sha256()
    folder = Path(folder)
    for path in sorted(p for p in folder.rglob("*") if p.is_file()):
        digest.update(path.relative_to(folder).as_posix().encode() + b"\0")
        digest.update(path.read_bytes())
    return digest.hexdigest()


def write_holdout(kind: str, seed: int, folder: Path) -> tuple[Path, HoldoutScene]:
    """Write a hold-out scene into `folder` (the client's copy); returns its MJCF path and what a
    worker needs to write the same files."""
    from sim_bridge.holdout_scenes import write_holdout_scene

    path = write_holdout_scene(kind, folder, seed)
    return path, HoldoutScene(kind, seed, holdout_digest(folder))


def _ensure_holdout(task: EpisodeTask) -> Path:
    """The task's hold-out scene on this machine, at the task's path: written if absent (into a
    folder of its own, then renamed, so two workers never read a half-written scene), and
    refused if its files differ from the client's."""
    from sim_bridge.holdout_scenes import write_holdout_scene

    spec = task.holdout
    assert spec is not None
    path = Path(task.scene)
    folder = path.parent
    if not folder.is_dir():
        # the generator names the scene's file after its folder: stage it under the same name
        staging = folder.parent / f".staging-{socket.gethostname()}-{os.getpid()}" / folder.name
        shutil.rmtree(staging.parent, ignore_errors=True)
        written = write_holdout_scene(spec.kind, staging, spec.seed)
        if written.name != path.name:
            shutil.rmtree(staging.parent, ignore_errors=True)
            raise ValueError(
                f"scene: got {task.scene!r}, but the hold-out generator names its file "
                f"{written.name!r}; pass the path write_holdout returned"
            )
        with contextlib.suppress(OSError):  # another worker put it there first
            staging.rename(folder)
        shutil.rmtree(staging.parent, ignore_errors=True)
    digest = holdout_digest(folder)
    if digest != spec.digest:
        raise ValueError(
            f"hold-out scene {spec.kind} (seed {spec.seed}) at {str(folder)!r} on "
            f"{socket.gethostname()}: got files with digest {digest[:12]}, expected "
            f"{spec.digest[:12]} (the client's); install the same version of the project on every "
            f"machine, and remove a stale {str(folder)!r}"
        )
    return path.resolve()


def _is_path(scene: str) -> bool:
    """As `sim_bridge.scenes.load_scene` tells a path from a bundled scene's name."""
    return "/" in scene or scene.endswith(".xml")


# -- one episode -----------------------------------------------------------------------------------
@contextlib.contextmanager
def _own_domain() -> Iterator[int]:
    """A ROS domain for one graph episode, leased (`middleware.DomainLease`) for as long as it
    runs: a free one, never the environment's ROS_DOMAIN_ID, which every worker process on this
    machine inherits alike. This process's ROS_DOMAIN_ID is as before afterwards."""
    from area3d_msgs_py import middleware

    before = os.environ.pop("ROS_DOMAIN_ID", None)
    try:
        lease = middleware.DomainLease()
    finally:
        if before is not None:
            os.environ["ROS_DOMAIN_ID"] = before
    try:
        yield lease.domain_id
    finally:
        lease.release()
        if before is None:
            os.environ.pop("ROS_DOMAIN_ID", None)
        else:
            os.environ["ROS_DOMAIN_ID"] = before


def run_episode_task(task: EpisodeTask, progress: Any = None) -> EpisodeResult:
    """Run one episode, evaluate it and return its result files; an episode that cannot be run
    (a bad scene, the graph failing) returns its error. `progress`: a rich Progress for a graph
    episode's views (in this process only)."""
    from area3d_bringup.inprocess import run_inprocess_episode
    from area3d_eval.evaluate import evaluate_run

    t0, cpu0 = time.monotonic(), _cpu_seconds()
    worker = f"{socket.gethostname()}:{os.getpid()}"
    result = EpisodeResult(task, worker=worker)
    attempt = (
        Path(task.out_dir) / ATTEMPTS_DIR / f"{worker.replace(':', '-')}-{uuid.uuid4().hex[:8]}"
    )
    try:
        scene = task.scene
        if task.holdout is not None:
            _ensure_holdout(task)
        if _is_path(scene):
            result.worker_scene = str(Path(scene).resolve())
        if task.in_process:
            run_dir = run_inprocess_episode(
                scene,
                task.policy,
                task.seed,
                attempt,
                task.budget,
                overrides=task.overrides,
                run_name=task.run_name,
                depth_source=task.depth_source,
            )
            episode = json.loads((run_dir / rundir.EPISODE_FILE).read_text())
            episode["timings_s"]["episode_total"] = time.monotonic() - t0
            rundir.write_episode(run_dir, episode)
        else:
            with _own_domain() as domain_id:
                config = EpisodeConfig(
                    scene=scene,
                    policy=task.policy,
                    budget=task.budget,
                    seed=task.seed,
                    out_dir=attempt,
                    record=False,
                    run_name=task.run_name,
                    domain_id=domain_id,
                    overrides=task.overrides,
                    depth_source=task.depth_source,
                )
                run_dir = run_episode(config, progress=progress)
        evaluate_run(run_dir)
        final = Path(task.out_dir) / task.run_name
        shutil.rmtree(final, ignore_errors=True)  # an earlier run of the same name
        run_dir.rename(final)
        with contextlib.suppress(OSError):
            attempt.rmdir()
        for name in RESULT_FILES:
            if (final / name).is_file():
                result.files[name] = (final / name).read_bytes()
    except (EpisodeError, ValueError) as err:
        result.error = str(err)
    result.seconds = time.monotonic() - t0
    result.cpu_s = _cpu_seconds() - cpu0
    return result


def _cpu_seconds() -> float:
    """User and system CPU seconds of this process (all its threads) and of its children that
    have ended (a graph episode's nodes)."""
    own = resource.getrusage(resource.RUSAGE_SELF)
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


def materialize(result: EpisodeResult, run_dir: Path) -> Path:
    """Write a result's files into `run_dir` on this machine (unchanged files are left alone:
    on the worker's own machine they are already there). A scene file's path on the worker is
    replaced by its path here (a hold-out's copy here, checked identical), so that the runs of
    one scene group under one name wherever they ran."""
    run_dir = Path(run_dir)
    files = dict(result.files)
    task = result.task
    if result.worker_scene is not None:
        here = str(Path(task.scene).resolve())
        for name in (rundir.EPISODE_FILE, rundir.METRICS_FILE):
            if name in files and result.worker_scene != here:
                data = json.loads(files[name])
                if data.get("scene") == result.worker_scene:
                    data["scene"] = here
                    files[name] = json.dumps(data, indent=1).encode()
    for name, data in files.items():
        path = run_dir / name
        if path.is_file() and path.read_bytes() == data:
            continue
        path.parent.mkdir(parents=True, exist_ok=True)
        rundir.write_atomic(path, lambda tmp, data=data: tmp.write_bytes(data))
    return run_dir


def episode_summary(result: EpisodeResult) -> dict[str, Any]:
    """What must be the same wherever the episode ran: the views chosen (poses, in order, and their
    kind) and the metrics (final and after each checkpoint)."""
    episode = result.episode()
    metrics = result.metrics()
    views = sorted(episode["views"], key=lambda v: int(v["index"]))
    return {
        "views": [(v.get("kind"), v["T_world_cam"]) for v in views],
        "final": metrics["final"],
        "curve": metrics["curve"],
    }
