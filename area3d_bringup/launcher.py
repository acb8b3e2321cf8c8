"""Start every node of a launch description as its own OS process and stop them all together.

Each node runs `python -m MODULE --ros-args --params-file FILE -r __node:=NAME [-r __ns:=NS]`, the
same arguments `ros2 run` and `ros2 launch` give a node. Output lines are prefixed with `[name]` and forwarded. Ctrl-C, SIGTERM or
the death of any node stops all of them: SIGINT first, then SIGTERM, then SIGKILL, and every child
also gets SIGKILL from the kernel if the launcher itself dies (PR_SET_PDEATHSIG), so no orphans remain.
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
    """

    def __init__(
        self,
        specs: list[NodeSpec],
        workdir: Path,
        env: dict[str, str] | None = None,
        log_sink: Callable[[str], None] | None = None,
        namespace: str = "",
        ros_args: list[str] | None = None,
    ):
        self.specs = specs
        self.namespace = namespace
        self.ros_args = list(ros_args or [])
        self.workdir = Path(workdir)
        self.env = {**os.environ, **(env or {}), "PYTHONUNBUFFERED": "1"}
        self.log_sink = log_sink or (lambda line: print(line, file=sys.stderr, flush=True))
        self.processes: dict[str, subprocess.Popen] = {}
        self.output: dict[str, list[str]] = {}
        self._threads: list[threading.Thread] = []
        self._stopping = False

    def start(self) -> None:
        params_file = write_params_file(self.specs, self.workdir / "params.yaml")
        for spec in self.specs:
            cmd = [
                sys.executable,
                "-m",
                spec.module,
                "--ros-args",
                "--params-file",
                str(params_file),
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
            self.output[spec.name] = []
            thread = threading.Thread(target=self._forward, args=(spec.name, proc), daemon=True)
            thread.start()
            self._threads.append(thread)

    def _forward(self, name: str, proc: subprocess.Popen) -> None:
        lines = self.output[name]
        for line in proc.stdout:
            line = line.rstrip("\n")
            lines.append(line)
            if len(lines) > 200:
                del lines[:100]
            self.log_sink(f"[{name}] {line}")

    def check(self) -> None:
        """Raise `NodeDied` if any node has exited."""
        if self._stopping:
            return
        for name, proc in self.processes.items():
            code = proc.poll()
            if code is not None:
                raise NodeDied(name, code, self.output.get(name, []))

    def wait(self, poll_s: float = 0.2) -> None:
        """Block until Ctrl-C / SIGTERM or until a node dies (then raise `NodeDied`)."""
        stop = threading.Event()
        previous = signal.signal(signal.SIGTERM, lambda *_: stop.set())
        try:
            while not stop.is_set():
                self.check()
                time.sleep(poll_s)
        except KeyboardInterrupt:
            pass
        finally:
            signal.signal(signal.SIGTERM, previous)

    def stop(self, grace_s: float = 5.0) -> dict[str, int]:
        """Stop every node (SIGINT, then SIGTERM, then SIGKILL); returns their exit codes."""
        self._stopping = True
        for sig, wait_s in ((signal.SIGINT, grace_s), (signal.SIGTERM, 2.0), (signal.SIGKILL, 2.0)):
            alive = [p for p in self.processes.values() if p.poll() is None]
            if not alive:
                break
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

    def __enter__(self) -> Launcher:
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop()
