"""Shared helpers of the cross-package tests (the ROS environment is set in the root conftest)."""

from __future__ import annotations

import signal
import subprocess
from collections.abc import Callable
from pathlib import Path

import pytest


def _child_pids(pid: int) -> list[int]:
    """The direct children of process `pid`, read from /proc. Threads of the parent start and end
    while it is read (the runner's executor, its respawn timers), so a thread gone between the
    listing and the read is skipped, not an error."""
    out: list[int] = []
    try:
        tasks = list(Path(f"/proc/{pid}/task").iterdir())
    except FileNotFoundError:
        return out
    for task in tasks:
        try:
            out.extend(int(p) for p in (task / "children").read_text().split())
        except (FileNotFoundError, ProcessLookupError):
            continue
    return out


def _cmdline(pid: int) -> list[str]:
    """The arguments process `pid` was started with; empty when it has exited."""
    try:
        raw = Path(f"/proc/{pid}/cmdline").read_bytes()
    except (FileNotFoundError, ProcessLookupError):
        return []
    return [part.decode(errors="replace") for part in raw.split(b"\0") if part]


@pytest.fixture
def child_pids() -> Callable[[int], list[int]]:
    return _child_pids


@pytest.fixture
def cmdline() -> Callable[[int], list[str]]:
    return _cmdline


def _interrupt(proc: subprocess.Popen, timeout_s: float = 120.0) -> str:
    """Ctrl-C a process started with its output piped as text, as a user stops `area3d launch`;
    kill it if it has not ended within `timeout_s` (generous: a loaded machine). Its output."""
    proc.send_signal(signal.SIGINT)
    try:
        out, _ = proc.communicate(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, _ = proc.communicate()
    return out


@pytest.fixture
def interrupt() -> Callable[..., str]:
    return _interrupt
