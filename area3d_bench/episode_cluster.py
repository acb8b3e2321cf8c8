"""Where `area3d bench episode` runs its episodes: in this process one after another (the default,
no engine), or as tasks on Dask distributed workers: a local cluster of N worker processes on this
machine (`--workers N`) or a cluster already running (`--cluster ADDRESS`).

Why Dask distributed: it is pure Python (installs from wheels on Python 3.11 and 3.12 with a
dozen small dependencies; Ray is an 80 MB binary wheel per Python version that brings its own
object store and services), its workers are plain processes started with `dask scheduler` and
`dask worker` on any machine with the project installed, and it already does what a benchmark
needs and no more: futures collected as they finish, and a task whose worker dies is given to
another worker (`distributed.scheduler.allowed-failures`, 3 by default; then it is reported as
failed), while the nanny process starts a new worker in place of the dead one.

Each worker process runs one episode at a time (`--nthreads 1`): the episodes are CPU-bound, and a
graph episode sets this process's ROS environment while it runs.
"""

from __future__ import annotations

import logging
import os
import socket
from collections.abc import Iterable, Iterator
from typing import Any, Protocol

from area3d_bench.episode_task import EpisodeResult, EpisodeTask, run_episode_task

INSTALL_HINT = 'pip install -e ".[cluster]" (Dask distributed)'
CONNECT_TIMEOUT_S = 30.0
WORKERS_TIMEOUT_S = 120.0  # a cluster without a worker after this long is an error


class Engine(Protocol):
    description: str
    slots: int  # episodes that run at once

    def run(self, tasks: Iterable[EpisodeTask], progress: Any = None) -> Iterator[EpisodeResult]:
        """Every task's result, in the order they finish."""
        ...

    def close(self) -> None: ...


class InThisProcess:
    """The episodes one after another in this process (a graph episode shows its views on
    `progress`)."""

    description = "this process, one episode at a time"
    slots = 1

    def run(self, tasks: Iterable[EpisodeTask], progress: Any = None) -> Iterator[EpisodeResult]:
        for task in tasks:
            yield run_episode_task(task, progress)

    def close(self) -> None:
        pass


def _distributed():
    try:
        import distributed
    except ImportError as err:
        raise RuntimeError(
            f"--workers and --cluster need the cluster extra: {INSTALL_HINT}"
        ) from err
    return distributed


def worker_info() -> dict[str, Any]:
    """Run on each worker before the episodes (and before the clock starts): the modules an
    episode needs import there (as they have in this process), and from where."""
    import area3d_bringup
    import area3d_bringup.inprocess
    import area3d_eval.evaluate  # noqa: F401

    return {
        "host": socket.gethostname(),
        "pid": os.getpid(),
        "package": os.path.dirname(area3d_bringup.__file__),
    }


class DaskEngine:
    """Episodes as tasks of a Dask distributed cluster, collected as they finish."""

    def __init__(self, client: Any, cluster: Any = None, description: str = "") -> None:
        self.client = client
        self.cluster = cluster  # a LocalCluster this engine started (closed with it)
        workers = client.scheduler_info().get("workers", {})
        self.slots = sum(int(w.get("nthreads", 1)) for w in workers.values()) or 1
        hosts = {w.get("host") for w in workers.values()}
        threads = sorted({int(w.get("nthreads", 1)) for w in workers.values()})
        self.description = (
            f"{description}: {len(workers)} worker process(es) on {len(hosts)} host(s), "
            f"{'/'.join(map(str, threads))} thread(s) each"
        )
        self.warnings: list[str] = []
        if any(n > 1 for n in threads):
            self.warnings.append(
                "workers with more than one thread run several episodes at once in one process; "
                "start them with `dask worker ADDRESS --nthreads 1`"
            )

    @classmethod
    def local(cls, n_workers: int) -> DaskEngine:
        """A cluster of `n_workers` processes on this machine, one thread each."""
        distributed = _distributed()
        if n_workers < 1:
            raise ValueError(f"workers: got {n_workers}, expected an int >= 1")
        import dask

        # An episode goes to a worker only when it is free: none waits behind a long episode on
        # one worker while another worker idles.
        with dask.config.set({"distributed.scheduler.worker-saturation": 1.0}):
            cluster = distributed.LocalCluster(
                n_workers=n_workers,
                threads_per_worker=1,
                processes=True,
                # the scheduler's HTTP server on a free port: with none given it takes 8787,
                # and warns when another cluster (a second benchmark) holds it
                dashboard_address=":0",
                silence_logs=logging.ERROR,
            )
        client = distributed.Client(cluster)
        client.wait_for_workers(n_workers, timeout=WORKERS_TIMEOUT_S)
        engine = cls(client, cluster, f"Dask local cluster {cluster.scheduler_address}")
        engine._check_workers()
        return engine

    @classmethod
    def connect(cls, address: str) -> DaskEngine:
        """The Dask cluster whose scheduler listens at `address` (e.g. tcp://10.0.0.5:8786)."""
        distributed = _distributed()
        try:
            client = distributed.Client(address, timeout=CONNECT_TIMEOUT_S)
        except (OSError, TimeoutError, ValueError) as err:
            raise RuntimeError(
                f"cluster: got {address!r}, could not reach a Dask scheduler there within "
                f"{CONNECT_TIMEOUT_S:.0f} s ({err}); start one with `dask scheduler` and pass the "
                "address it prints"
            ) from err
        try:
            client.wait_for_workers(1, timeout=WORKERS_TIMEOUT_S)
        except TimeoutError as err:
            client.close()
            raise RuntimeError(
                f"cluster: the scheduler at {address!r} has no worker after "
                f"{WORKERS_TIMEOUT_S:.0f} s; start workers with `dask worker {address} --nthreads 1`"
            ) from err
        engine = cls(client, None, f"Dask cluster {address}")
        engine._check_workers()
        return engine

    def _check_workers(self) -> None:
        try:
            self.client.run(worker_info)
        except Exception as err:  # the function's module does not import on some worker
            self.close()
            raise RuntimeError(
                f"a Dask worker cannot import the project ({type(err).__name__}: {err}); install "
                f"it on every worker machine: {INSTALL_HINT}"
            ) from err

    def run(self, tasks: Iterable[EpisodeTask], progress: Any = None) -> Iterator[EpisodeResult]:
        distributed = _distributed()
        futures = {}
        for task in tasks:
            future = self.client.submit(
                run_episode_task, task, key=f"episode-{task.run_name}-{os.urandom(4).hex()}"
            )
            futures[future] = task
        for future in distributed.as_completed(futures):
            task = futures[future]
            try:
                yield future.result()
            except distributed.KilledWorker as err:
                yield EpisodeResult(
                    task, error=f"its worker died each time it ran it, so it was given up: {err}"
                )
            except Exception as err:  # raised on the worker: reported with the episode
                yield EpisodeResult(task, error=f"{type(err).__name__}: {err}")

    def close(self) -> None:
        self.client.close()
        if self.cluster is not None:
            self.cluster.close()


def open_engine(workers: int | None = None, cluster: str | None = None) -> Engine:
    """In this process (neither), a local cluster of `workers` processes, or the cluster at
    `cluster`."""
    if workers is not None and cluster is not None:
        raise ValueError(
            f"workers, cluster: got {workers} and {cluster!r}, expected one of them (a cluster "
            "already has its workers)"
        )
    if cluster is not None:
        return DaskEngine.connect(cluster)
    if workers is not None:
        return DaskEngine.local(workers)
    return InThisProcess()
