"""Start every node of a launch description as its own OS process and stop them all together.

Each node runs `python -m MODULE --ros-args --params-file FILE -r __node:=NAME [-r __ns:=NS]`, the
same arguments `ros2 run` and `ros2 launch` give a node. Output lines are prefixed with `[name]` and forwarded. Ctrl-C, SIGTERM or
the death of any node stops all of them: SIGINT first, then SIGTERM, then SIGKILL, and every child
also gets SIGKILL from the kernel if the launcher itself dies (PR_SET_PDEATHSIG), so no orphans remain.

With `respawn=True` a node that exits is started again after `respawn_delay_s`, at most
`respawn_max_retries` times per node (ROS 2 launch's `respawn`, `respawn_delay` and
`respawn_max_retries`); only a node that has used up its retries counts as dead. `respawns` counts
the restarts per node, so a caller can bring a restarted node up to date.
"""

from __future__ import annotations

import ctypes
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

from area3d_bringup.launch_description import NodeSpec, write_params_file

_PR_SET_PDEATHSIG = 1


def _die_with_parent() -> None:  # runs in the child between fork and exec
    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(_PR_SET_PDEATHSIG, signal.SIGKILL)
    except OSError:
        pass


class NodeDied(RuntimeError):
    """A node process exited while the graph was meant to be running."""

    def __init__(self, name: str, returncode: int, last_lines: list[str]):
        self.name, self.returncode, self.last_lines = name, returncode, last_lines
        tail = "\n".join(last_lines[-10:])
        super().__init__(f"node {name!r} exited with code {returncode}; its last output:\n{tail}")


class Launcher:
    """Runs a list of `NodeSpec` as child processes.

    log_sink: called with each prefixed output line (default: write to stderr).
    env: extra environment for the children (e.g. ROS_DOMAIN_ID, `middleware.graph_env()`).
    namespace: ROS namespace of every node (`-r __ns:=NAMESPACE`), e.g. "/robot1".
    ros_args: more `--ros-args` arguments for every node, e.g. ["-r", "from:=to"].
    respawn, respawn_delay_s, respawn_max_retries: start a node that exited again, after this many
    seconds, at most this many times per node.
    """

    def __init__(
        self,
        specs: list[NodeSpec],
        workdir: Path,
        env: dict[str, str] | None = None,
        log_sink: Callable[[str], None] | None = None,
        namespace: str = "",
        ros_args: list[str] | None = None,
        respawn: bool = False,
        respawn_delay_s: float = 1.0,
        respawn_max_retries: int = 3,
    ):
        if respawn_delay_s < 0:
            raise ValueError(f"respawn_delay_s: got {respawn_delay_s}, expected seconds >= 0")
        if respawn_max_retries < 0:
            raise ValueError(f"respawn_max_retries: got {respawn_max_retries}, expected >= 0")
        self.specs = specs
        self.namespace = namespace
        self.ros_args = list(ros_args or [])
        self.workdir = Path(workdir)
        self.env = {**os.environ, **(env or {}), "PYTHONUNBUFFERED": "1"}
        self.log_sink = log_sink or (lambda line: print(line, file=sys.stderr, flush=True))
        self.processes: dict[str, subprocess.Popen] = {}
        self.output: dict[str, list[str]] = {}
        self._lines_read: dict[str, int] = {spec.name: 0 for spec in specs}
        self._threads: list[threading.Thread] = []
        self._stopping = False
        self._interrupted = False  # Ctrl-C: no node is started again
        self.respawn = respawn
        self.respawn_delay_s = float(respawn_delay_s)
        self.respawn_max_retries = int(respawn_max_retries)
        self.respawns: dict[str, int] = {spec.name: 0 for spec in specs}
        self._spawn_lock = threading.Lock()  # a respawn never races stop()
        self._stop_event = threading.Event()
        self._params_file: Path | None = None

    def start(self) -> None:
        self._params_file = write_params_file(self.specs, self.workdir / "params.yaml")
        for spec in self.specs:
            self.output[spec.name] = []
            self._spawn(spec)
        if self.respawn:
            monitor = threading.Thread(target=self._monitor, name="launcher-respawn", daemon=True)
            monitor.start()
            self._threads.append(monitor)

    def _spawn(self, spec: NodeSpec) -> None:
        cmd = [
            sys.executable,
            "-m",
            spec.module,
            "--ros-args",
            "--params-file",
            str(self._params_file),
            "-r",
            f"__node:={spec.name}",
            *(["-r", f"__ns:={self.namespace}"] if self.namespace else []),
            *self.ros_args,
        ]
        proc = subprocess.Popen(
            cmd,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
            env=self.env,
            text=True,
            bufsize=1,
            preexec_fn=_die_with_parent,
        )
        self.processes[spec.name] = proc
        thread = threading.Thread(target=self._forward, args=(spec.name, proc), daemon=True)
        thread.start()
        self._threads.append(thread)

    def _can_respawn(self, name: str) -> bool:
        return (
            self.respawn
            and not self._interrupted
            and self.respawns[name] < self.respawn_max_retries
        )

    def interrupt(self, send: bool = True) -> None:
        """Ctrl-C as a terminal gives it to the whole process group: no node is respawned from
        now on, and with `send` SIGINT goes to every node still running; their exits then read
        as `NodeDied` (the caller knows it was interrupted). For a caller that was sent SIGINT
        alone (`kill -INT`, `timeout`)."""
        with self._spawn_lock:
            self._interrupted = True
            alive = [p for p in self.processes.values() if p.poll() is None]
        for proc in alive if send else ():
            proc.send_signal(signal.SIGINT)

    def _monitor(self, poll_s: float = 0.1) -> None:
        """Start nodes that exited again, each after the delay, while retries are left."""
        while not self._stop_event.wait(poll_s):
            for spec in self.specs:
                code = self.processes[spec.name].poll()
                if code is None or not self._can_respawn(spec.name):
                    continue
                attempt = self.respawns[spec.name] + 1
                self.log_sink(
                    f"[launcher] {spec.name} exited with code {code}; respawning in "
                    f"{self.respawn_delay_s:g} s ({attempt}/{self.respawn_max_retries})"
                )
                if self._stop_event.wait(self.respawn_delay_s):
                    return
                with self._spawn_lock:
                    if self._stopping:
                        return
                    self._spawn(spec)
                    self.respawns[spec.name] = attempt
                self.log_sink(f"[launcher] {spec.name} respawned")

    def _forward(self, name: str, proc: subprocess.Popen) -> None:
        lines = self.output[name]
        for line in proc.stdout:
            line = line.rstrip("\n")
            lines.append(line)
            self._lines_read[name] += 1
            if len(lines) > 200:
                del lines[:100]
            self.log_sink(f"[{name}] {line}")

    def check(self) -> None:
        """Raise `NodeDied` if a node has exited for good (with respawn: no retries left)."""
        if self._stopping:
            return
        for name, proc in list(self.processes.items()):
            code = proc.poll()
            if code is not None and not self._can_respawn(name):
                raise NodeDied(name, code, self.output.get(name, []))

    def wait_for(
        self, predicate: Callable[[], bool], timeout_s: float, poll_s: float = 0.05
    ) -> bool:
        """Poll `predicate` until it holds (True) or timeout (False); a node that dies for good
        meanwhile raises `NodeDied` instead of letting the caller wait it out."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            self.check()
            if predicate():
                return True
            time.sleep(poll_s)
        return False

    def wait(self, poll_s: float = 0.2) -> None:
        """Block until Ctrl-C / SIGTERM or until a node dies (then raise `NodeDied`)."""
        stop = threading.Event()
        previous = signal.signal(signal.SIGTERM, lambda *_: stop.set())
        # Ctrl-C always stops the graph, even where this process was started with SIGINT ignored
        # (a parent that ignores it passes that on, and Python then installs no handler)
        previous_int = signal.signal(signal.SIGINT, signal.default_int_handler)
        try:
            while not stop.is_set():
                self.check()
                time.sleep(poll_s)
        except KeyboardInterrupt:
            pass
        finally:
            signal.signal(signal.SIGTERM, previous)
            signal.signal(signal.SIGINT, previous_int)

    def stop(self, grace_s: float = 5.0, dump_wait_s: float = 2.0) -> dict[str, int]:
        """Stop every node (SIGINT, then SIGTERM, then SIGKILL); returns their exit codes. Before
        the SIGKILL, a node still running is asked where its threads are (SIGUSR1) and given up
        to `dump_wait_s` to say it."""
        with self._spawn_lock:
            self._stopping = True
            self._stop_event.set()
        for sig, wait_s in ((signal.SIGINT, grace_s), (signal.SIGTERM, 2.0), (signal.SIGKILL, 2.0)):
            alive = [p for p in self.processes.values() if p.poll() is None]
            if not alive:
                break
            if sig == signal.SIGKILL:
                self._dump_threads(alive, dump_wait_s)
            for proc in alive:
                proc.send_signal(sig)
            deadline = time.monotonic() + wait_s
            for proc in alive:
                try:
                    proc.wait(timeout=max(0.0, deadline - time.monotonic()))
                except subprocess.TimeoutExpired:
                    pass
        for thread in self._threads:
            thread.join(timeout=1.0)
        return {name: proc.poll() for name, proc in self.processes.items()}

    def _dump_threads(self, alive: list[subprocess.Popen], wait_s: float) -> None:
        """Before a node is killed: where its threads hang, into its log (every node prints its
        threads' stacks on SIGUSR1, `run_node`); waits until each has said something more."""
        names = {proc.pid: name for name, proc in self.processes.items()}
        read = {name: self._lines_read[name] for name in names.values()}
        for proc in alive:
            self.log_sink(f"[launcher] {names[proc.pid]} did not stop; its threads:")
            proc.send_signal(signal.SIGUSR1)
        deadline = time.monotonic() + wait_s
        while time.monotonic() < deadline:
            if all(self._lines_read[names[p.pid]] > read[names[p.pid]] for p in alive):
                return  # the rest of a dump begun is in the pipe, read after the kill too
            time.sleep(0.05)

    def __enter__(self) -> Launcher:
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop()
