"""A node process's life: configure the middleware, start rclpy, build the node, forward Python
`logging` to its ROS log, spin until Ctrl-C or shutdown, and tear everything down quietly; the one
`main` body every AREA3D node shares."""

from __future__ import annotations

import ctypes
import faulthandler
import logging
import os
import signal
import sys
import threading
import time
import traceback
from collections.abc import Callable, Sequence
from typing import Any, NoReturn

import rclpy
from rclpy.executors import Executor, ExternalShutdownException
from rclpy.node import Node

from area3d_msgs_py import middleware
from area3d_msgs_py.errors import InputError
from area3d_msgs_py.spinning import GuardedExecutor

# What a node's constructor raises for a configuration it cannot start with (bad parameters, a
# missing file, model or library): logged as fatal, exit code 1.
STARTUP_ERRORS: tuple[type[Exception], ...] = (InputError, FileNotFoundError)
# rclpy handles SIGINT and SIGTERM on a thread of its own: it triggers every executor's guard
# condition, then shuts the contexts down. The node is torn down only once that thread is done (or
# after this long): destroying the executor's guard condition while that thread still walks the
# list of them, or shutting the context down beside it, can crash the process (a planner exited
# with -11 on SIGINT on a loaded machine) or end it with a traceback (rcl_shutdown twice).
SIGNAL_SHUTDOWN_WAIT_S = 10.0
# Destroying the node and the context is the middleware's work. On a loaded 2-core machine, in runs
# of the test suite, a planner and a perception node stayed in rclpy's `destroy_node` (the node's
# last step, after its publishers, services and timers were gone), once until the launcher killed
# it 32 s after the Ctrl-C. The node's own work has stopped by then (`destroy_node` overrides stop
# their workers first, each within a second or two): past this long in one step of the teardown
# (stopping the node's work, the executor, destroying the node, the context), the process logs
# where its threads are and exits without the rest.
TEARDOWN_LIMIT_S = 10.0
# A teardown stuck in C code that holds the GIL never lets the Python watchdog run (so it was in
# the one such hang seen with both in place): faulthandler's own thread then prints the stacks
# this much later and ends the process with code 1.
TEARDOWN_GIL_FALLBACK_S = 5.0
# glibc gives each new thread an arena of its own, up to 8 per core, and memory freed in one arena
# is reused by that arena only. A node's executor, middleware and worker threads each take and
# free frames of megabytes, so each arena kept its own peak: in 2-minute soaks (`area3d bench
# soak`) a planner held 545-554 MB with the default arenas and 429-478 MB with two.
MALLOC_ARENAS = 2
M_ARENA_MAX = -8  # mallopt parameter, glibc's malloc.h
# glibc maps a block of at least M_MMAP_THRESHOLD bytes with mmap and returns it to the system
# when freed, but by default raises that threshold to the largest block freed so far (up to
# 32 MB): after the first frame, a node's per-frame arrays of megabytes (640x480 pixels as
# float64 or int64: 2.4 MB) all came from the heap, between longer-lived blocks, and the heap
# fragmented. A planner's resident memory rose by about 30 MB per 2 minutes of a 10 Hz stream
# (39 MB in 10 minutes) while its live data (tracemalloc) stayed flat. A fixed threshold of 2 MiB
# maps such arrays afresh each time: in a 2-minute soak the planner's anonymous memory stayed at
# 229-244 MB and its fusion took as long as before (p50 27 ms); in 10 minutes its RSS rose 25 MB
# (39 MB before). 1 MiB also mapped the 1.2 MB float32 images and made fusion 11 ms slower.
LARGE_BLOCK_BYTES = 2 * 1024 * 1024
M_MMAP_THRESHOLD = -3  # mallopt parameter, glibc's malloc.h
# How long a thread holding the GIL runs before a waiting thread gets it (CPython's default is
# 5 ms). A node's executor threads take each message in several short steps, each of which waited
# for the GIL behind fusion or a rebuild; at 1 ms, next-view round trips during a 10 Hz soak went
# from p95 327 ms to 191-242 ms (5 two-minute runs) and 220 ms over 10 minutes.
GIL_SWITCH_INTERVAL_S = 0.001


class PublishGate:
    """Lets a node's own worker threads publish until the node stops.

    A publish (or a timer reset) from a thread other than the executor's, on a node being destroyed,
    can crash the process in the middleware. Such a thread publishes inside `with gate as open_:`
    and only while `open_` is true; `close()` (from `run_node`'s `on_stop`) waits for a publish in
    progress to end and refuses every later one. A publish that raises because rclpy's signal
    handler shut the context down after the check is the node stopping: the gate swallows it,
    closes, and the code after the `with` block runs (a worker ends quietly there)."""

    def __init__(self, context_ok: Callable[[], bool] | None = None) -> None:
        self._lock = threading.Lock()
        self._open = True
        self._context_ok = context_ok  # the node's `context.ok`

    def __enter__(self) -> bool:
        self._lock.acquire()
        # closed too once rclpy's signal handler has shut the context down: a Ctrl-C lands
        # before `run_node` gets to `on_stop`, and a publish in between raises in the worker
        return self._open and (self._context_ok is None or self._context_ok())

    def __exit__(self, exc_type: type | None, *exc: object) -> bool:
        try:
            stopped = self._context_ok is not None and not self._context_ok()
            if exc_type is not None and issubclass(exc_type, Exception) and stopped:
                self._open = False
                return True
            return False
        finally:
            self._lock.release()

    def close(self) -> None:
        with self._lock:
            self._open = False


class RosLogHandler(logging.Handler):
    """Python `logging` records -> the node's ROS logger, so what our modules log (the semantics
    backends' retries, a parser's skipped lines, a library's warnings) reaches /rosout and the
    node's console log with the node's name: logger `area3d_semantics.backends` of node
    `semantics` logs as `semantics.area3d_semantics.backends`."""

    def __init__(self, ros_logger: Any) -> None:
        super().__init__()
        self._ros_logger = ros_logger
        self._children: dict[str, Any] = {}
        self._lock_children = threading.Lock()

    def _child(self, name: str) -> Any:
        with self._lock_children:
            child = self._children.get(name)
            if child is None:
                child = self._children[name] = self._ros_logger.get_child(name)
            return child

    def emit(self, record: logging.LogRecord) -> None:
        try:
            logger = self._child(record.name) if record.name != "root" else self._ros_logger
            message = self.format(record)
            if record.levelno >= logging.CRITICAL:
                logger.fatal(message)
            elif record.levelno >= logging.ERROR:
                logger.error(message)
            elif record.levelno >= logging.WARNING:
                logger.warning(message)
            elif record.levelno >= logging.INFO:
                logger.info(message)
            else:
                logger.debug(message)
        except Exception:  # noqa: BLE001 - logging must never end the node
            self.handleError(record)


def forward_python_logging(node: Node) -> RosLogHandler:
    """Install a RosLogHandler for `node` on the root logger, at the node's log level (rclpy's
    severities share Python's numbers: DEBUG 10 ... FATAL 50; `--ros-args --log-level debug`
    applies to both). Returns the handler, for `logging.getLogger().removeHandler`."""
    handler = RosLogHandler(node.get_logger())
    root = logging.getLogger()
    root.addHandler(handler)
    root.setLevel(int(node.get_logger().get_effective_level()))
    return handler


def _mallopt(parameter: int, value: int, env_var: str) -> bool:
    """glibc's mallopt(parameter, value), unless the user set `env_var` (glibc's own environment
    setting for it) or the C library is not glibc; True if done."""
    if env_var in os.environ:
        return False
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    return bool(mallopt(parameter, int(value)))


def limit_malloc_arenas(arenas: int = MALLOC_ARENAS) -> bool:
    """Cap glibc's malloc arenas for the threads this process starts from now on; True if done.
    A MALLOC_ARENA_MAX in the environment wins."""
    return _mallopt(M_ARENA_MAX, arenas, "MALLOC_ARENA_MAX")


def map_large_blocks(threshold: int = LARGE_BLOCK_BYTES) -> bool:
    """Fix glibc's mmap threshold at `threshold` bytes (see LARGE_BLOCK_BYTES); True if done.
    A MALLOC_MMAP_THRESHOLD_ in the environment wins."""
    return _mallopt(M_MMAP_THRESHOLD, threshold, "MALLOC_MMAP_THRESHOLD_")


def tune_process() -> None:
    """The process settings every node runs with: two malloc arenas, large blocks mapped, a 1 ms
    GIL switch interval. Called before rclpy and the node start their threads."""
    limit_malloc_arenas()
    map_large_blocks()
    sys.setswitchinterval(GIL_SWITCH_INTERVAL_S)


def run_node(
    make_node: Callable[[], Node],
    name: str,
    args: Sequence[str] | None = None,
    startup_errors: tuple[type[Exception], ...] = STARTUP_ERRORS,
    executor: Callable[[], Executor] = GuardedExecutor,
    on_stop: Callable[[Node], None] | None = None,
) -> int:
    """Run one node process: 0 after a clean stop (SIGINT, shutdown), 1 when it could not start.

    Ctrl-C is a clean stop wherever it lands: while the node is being built, between building
    and spinning, or while spinning. `on_stop(node)` runs first when the node stops, before the
    executor waits for the callbacks in flight: it lets a callback that waits on the node's own
    work (a request waiting for a rebuild) return at once. After a signal, the executor, node and
    context are torn down only once rclpy's signal thread has shut the context down."""
    # `kill -USR1 <pid>` prints where every thread of the node is (a node that hangs can be read)
    faulthandler.register(signal.SIGUSR1, all_threads=True)
    tune_process()  # before rclpy and the node start their threads
    middleware.configure()
    interrupt = _StopSignal()
    interrupt.install()  # before rclpy.init: rclpy's own handler calls this one after its own
    try:
        rclpy.init(args=args)
    except Exception as exc:  # rcl parses --ros-args: a params file missing or not YAML
        message = " ".join(str(exc).split())
        print(f"[FATAL] [{name}]: cannot start: {message}", file=sys.stderr, flush=True)
        return 1
    node: Node | None = None
    spinner: Executor | None = None
    signalled = False
    log_handler: logging.Handler | None = None
    try:
        spinner = executor()  # first: a Ctrl-C while the node is built finds it whole
        try:
            node = make_node()
        except startup_errors as exc:
            rclpy.logging.get_logger(name).fatal(f"cannot start: {exc}")
            return 1
        log_handler = forward_python_logging(node)
        spinner.add_node(node)
        interrupt.spinning = True
        with _ShutdownWatch(spinner, node.context):
            _spin(spinner, node)
        signalled = True  # spin returns only once the context is shut down: a signal
    except (KeyboardInterrupt, ExternalShutdownException):
        signalled = True
    except Exception:
        if rclpy.ok():
            raise
        signalled = True  # the context was shut down under the executor's wait: a signal
    finally:
        # Stopping: a second Ctrl-C (a terminal's reaches the launcher and every node, and the
        # launcher then stops each node with one of its own) would raise KeyboardInterrupt in
        # the middle of the teardown below (rclpy takes SIGTERM as a stop, too: a teardown that
        # hangs ends at the launcher's SIGKILL, its threads' stacks logged first).
        if threading.current_thread() is threading.main_thread():
            signal.signal(signal.SIGINT, signal.SIG_IGN)
        if log_handler is not None:
            logging.getLogger().removeHandler(log_handler)
        if signalled:
            _wait_for_signal_shutdown(SIGNAL_SHUTDOWN_WAIT_S)  # bounded itself
        # Each step below has TEARDOWN_LIMIT_S, and a step that overruns is named. A Ctrl-C raises
        # KeyboardInterrupt wherever the main thread is, also inside the executor between taking
        # a callback and marking it done, and then `shutdown` waits for it forever.
        with _bounded(name, TEARDOWN_LIMIT_S, "stopping the node's work") as bound:
            if on_stop is not None and node is not None:
                on_stop(node)
            bound.next_step("stopping the executor")
            if spinner is not None:
                spinner.shutdown()
            bound.next_step("destroying the node")
            if node is not None:
                node.destroy_node()
            bound.next_step("shutting down the context")
            rclpy.try_shutdown()
    return 0


class _StopSignal:
    """Python's side of Ctrl-C in a node process. While the node is built, Ctrl-C raises
    KeyboardInterrupt (a constructor that loads a model stops at once); once it spins, it raises
    nothing: rclpy's signal thread shuts the context down and the executor's `spin` returns. A
    KeyboardInterrupt raised inside the executor lands anywhere (in the suite, inside an rclpy
    Task's constructor, whose finaliser then printed a traceback as the node exited)."""

    def __init__(self) -> None:
        self.spinning = False

    def install(self) -> None:
        if threading.current_thread() is threading.main_thread():
            signal.signal(signal.SIGINT, self)

    def __call__(self, signum: int, frame: Any) -> None:
        if not self.spinning:
            raise KeyboardInterrupt


class _bounded:
    """Steps of a node process's teardown, each of which must end within `limit_s`: past it, the
    process logs the step, its threads' stacks and that it exits without the rest, and exits with
    code 0 (`exit_process`; the stop was asked for and the node's own work is done). If the step
    holds the GIL, faulthandler's thread (C, no GIL) prints the stacks TEARDOWN_GIL_FALLBACK_S
    later and exits with code 1; it stays armed while the watchdog reports, so that a report that
    blocks (on a full pipe, on a C stream's lock) ends too. For a node's own process only, as
    `run_node`."""

    def __init__(self, name: str, limit_s: float, step: str) -> None:
        self.name, self.limit_s, self.step = name, limit_s, step
        self._timer: threading.Timer | None = None

    def _arm(self) -> None:
        self._timer = threading.Timer(self.limit_s, self._expired, args=(self.step,))
        self._timer.daemon = True
        self._timer.start()
        faulthandler.dump_traceback_later(self.limit_s + TEARDOWN_GIL_FALLBACK_S, exit=True)

    def _disarm(self) -> None:
        if self._timer is not None:
            self._timer.cancel()
        faulthandler.cancel_dump_traceback_later()

    def next_step(self, step: str) -> None:
        """The step before ended in time: the next one gets `limit_s` of its own."""
        self._disarm()
        self.step = step
        self._arm()

    def __enter__(self) -> _bounded:
        self._arm()
        return self

    def __exit__(self, *exc) -> None:
        self._disarm()

    def _expired(self, step: str) -> None:
        if step != self.step:  # that step ended as the timer fired: the next one has its own
            return
        try:  # the output may go nowhere (a launcher gone, its pipe closed): exit all the same
            print(
                f"[WARN] [{self.name}]: {step} did not finish in {self.limit_s:g} s; "
                "the process exits without it. Its threads:",
                file=sys.stderr,
                flush=True,
            )
            faulthandler.dump_traceback(file=sys.stderr, all_threads=True)
        except (OSError, ValueError):
            pass
        exit_process(0)


def _spin(spinner: Executor, node: Node) -> None:
    """Spin until the context is shut down. A callback that raises (one no input guard covers: a
    timer's, a service's) is a fault of this node, not its end: rclpy's executor re-raises it
    from `spin`, which ended the process and with it everything the node held; its traceback is
    logged as an error and the node spins on."""
    while True:
        try:
            spinner.spin()
            return
        except Exception:
            if not rclpy.ok():  # the context was shut down under the callback: the stop
                raise
            node.get_logger().error(f"a callback raised; spinning on:\n{traceback.format_exc()}")


class _ShutdownWatch:
    """Wakes the executor once its context is shut down, for a Ctrl-C rclpy's signal thread
    did not end the spin with.

    That thread triggers the executors' guard conditions, then shuts the contexts down. An executor
    that wakes on the trigger before the shutdown finds its context up, takes the trigger with its
    wait, and waits again, with nothing left to wake it: a node with no timer of its own (one that
    waits for frames) then stays in that wait after the Ctrl-C, its context shut down. It was seen
    about once in 10 to 30 stops on a loaded machine. While the node spins, this thread looks at
    the context every PERIOD_S and wakes the executor once it is shut down; the executor then
    finds it shut down and `spin` returns."""

    PERIOD_S = 0.1

    def __init__(self, spinner: Executor, context: Any) -> None:
        self._spinner, self._context = spinner, context
        self._done = threading.Event()
        self._thread = threading.Thread(target=self._watch, name="shutdown-watch", daemon=True)

    def _watch(self) -> None:
        while not self._done.wait(self.PERIOD_S):
            if not self._context.ok():
                self._spinner.wake()
                return

    def __enter__(self) -> _ShutdownWatch:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._done.set()  # before the teardown destroys the executor's guard condition
        self._thread.join()


def _wait_for_signal_shutdown(timeout_s: float) -> None:
    """Wait until the default context is shut down, as rclpy's signal thread does last."""
    deadline = time.monotonic() + timeout_s
    while rclpy.ok() and time.monotonic() < deadline:
        time.sleep(0.005)


def exit_process(code: int) -> NoReturn:
    """End a node process that `run_node` has stopped: flush its output and exit at once.

    By then rclpy is shut down and its log is flushed; what is left is the interpreter's own
    teardown (unloading numba, OpenMP pools, MuJoCo, Open3D), which took 1-2 s of a node's exit
    after Ctrl-C on a busy 2-core machine. Only for a node's own process (`python -m ...node`),
    never for code that shares the process with others."""
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # a closed pipe: nothing left to say
            pass
    try:  # and C's stdio buffers (ROS logging to a piped stdout is buffered there)
        ctypes.CDLL(None).fflush(None)
    except (OSError, AttributeError):
        pass
    os._exit(code)
