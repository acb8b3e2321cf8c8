"""The episode benchmark on two hosts: a Dask scheduler and worker (started with Dask's own
`dask scheduler` / `dask worker`) in one network namespace, working in a folder of their own, and
`area3d bench episode --cluster` in another, joined by a veth pair with addresses of their own.
The worker writes the generated hold-out scenes itself and keeps the frames; the client gets the
results. Needs root and `ip netns` (CI runs as root); the namespaces are created and removed here.
Without them the same code is covered by the local-cluster tests
(`test_bench_episode_cluster.py`)."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from area3d_bench.episode_task import holdout_digest


def _ip(*args: str, check: bool = True) -> subprocess.CompletedProcess:
    return subprocess.run(["ip", *args], capture_output=True, text=True, check=check)


@pytest.fixture()
def two_hosts():
    if shutil.which("ip") is None or os.geteuid() != 0:
        pytest.skip("ip netns unavailable: needs root and the `ip` command (iproute2)")
    tag = os.getpid() % 10000
    subnet = 10 + (os.getpid() + 101) % 200
    hosts = {"client": f"a3dc{tag}c", "worker": f"a3dc{tag}w"}
    links = {"client": f"a3dw{tag}c", "worker": f"a3dw{tag}w"}
    addresses = {"client": f"10.201.{subnet}.1", "worker": f"10.201.{subnet}.2"}
    probe = _ip("netns", "add", hosts["client"], check=False)
    if probe.returncode != 0:
        pytest.skip(f"ip netns unavailable: `ip netns add` failed: {probe.stderr.strip()}")
    try:
        _ip("netns", "add", hosts["worker"])
        _ip("link", "add", links["client"], "type", "veth", "peer", "name", links["worker"])
        for side in ("client", "worker"):
            ns, link = hosts[side], links[side]
            _ip("link", "set", link, "netns", ns)
            _ip("-n", ns, "addr", "add", f"{addresses[side]}/24", "dev", link)
            _ip("-n", ns, "link", "set", link, "up")
            _ip("-n", ns, "link", "set", "lo", "up")
        yield hosts, addresses
    finally:
        for ns in hosts.values():
            _ip("netns", "delete", ns, check=False)


def _stop(process: subprocess.Popen) -> None:
    process.terminate()
    try:
        process.wait(timeout=30)
    except subprocess.TimeoutExpired:
        process.kill()
        process.wait()


# two episodes through one worker (the bundled scene and the scanned counter, whose meshes and
# textures the worker writes beside its MJCF; every kind is written on a worker as on the client
# in test_bench_episode_cluster.py, a room's episodes run in tests/test_unseen_scenes.py): a
# minute or more on a loaded 2-core machine, so the bound is the subprocess's
KINDS = ["scanned_counter"]


@pytest.mark.timeout(1500)
def test_the_benchmark_runs_on_the_worker_of_another_host(two_hosts, tmp_path):
    hosts, addresses = two_hosts
    dask = str(Path(sys.executable).parent / "dask")
    client_dir, worker_dir = tmp_path / "client", tmp_path / "worker"
    client_dir.mkdir()
    worker_dir.mkdir()
    address = f"tcp://{addresses['worker']}:{20000 + os.getpid() % 20000}"
    port = address.rsplit(":", 1)[1]
    host = ["ip", "netns", "exec", hosts["worker"]]
    log = (worker_dir / "dask.log").open("w")
    scheduler = subprocess.Popen(
        [*host, dask, "scheduler", "--host", addresses["worker"], "--port", port, "--no-dashboard"],
        cwd=worker_dir, stdout=log, stderr=subprocess.STDOUT,
    )  # fmt: skip
    worker = subprocess.Popen(
        [*host, dask, "worker", address, "--nthreads", "1", "--nworkers", "1",
         "--host", addresses["worker"], "--no-dashboard"],
        cwd=worker_dir, stdout=log, stderr=subprocess.STDOUT,
    )  # fmt: skip
    try:
        bench = subprocess.run(
            ["ip", "netns", "exec", hosts["client"], sys.executable, "-m", "area3d_bench.cli",
             "episode", "--in-process", "--scenes", "single_object", "--policies",
             "uniform", "--seeds", "1", "--budget", "5", "--holdout", "--holdout-kinds", ",".join(KINDS),
             "--cluster", address,
             "--out", "runs"],
            cwd=client_dir, capture_output=True, text=True, timeout=1200,
            env=dict(os.environ, COLUMNS="200"),
        )  # fmt: skip
    finally:
        _stop(worker)
        _stop(scheduler)
        log.close()
    output = bench.stdout + bench.stderr
    assert bench.returncode == 0, output[-4000:] + (worker_dir / "dask.log").read_text()[-4000:]
    assert "failed" not in output
    (client_root,) = (client_dir / "runs").iterdir()
    worker_root = worker_dir / "runs" / client_root.name  # the same relative path, elsewhere
    kinds = [f"{kind}_s0" for kind in KINDS]
    names = ["single_object_uniform_s0", *(f"{kind}_uniform_s0" for kind in kinds)]
    for name in names:
        # the client has the results; the frames stay on the worker
        assert (client_root / name / "metrics.json").is_file()
        assert not (client_root / name / "frames").exists()
        assert list((worker_root / name / "frames").glob("*.npz"))
        mine = json.loads((client_root / name / "metrics.json").read_text())
        theirs = json.loads((worker_root / name / "metrics.json").read_text())
        assert mine["final"] == theirs["final"]
    # the worker wrote the hold-out scenes itself, file for file as the client did, and the
    # client's table names them by its own copy
    for kind in kinds:
        here, there = client_root / "holdout" / kind, worker_root / "holdout" / kind
        assert holdout_digest(here) == holdout_digest(there)
        episode = json.loads((client_root / f"{kind}_uniform_s0" / "episode.json").read_text())
        assert episode["scene"] == str((here / f"{kind}.xml").resolve())
    assert (client_root / "report" / "report.html").is_file()
    assert f"{1 + len(kinds)} scenes x 1 policies x 1 seeds" in output
