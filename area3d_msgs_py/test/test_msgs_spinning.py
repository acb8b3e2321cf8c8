"""An executor spun on its own thread stops without its thread touching what shutdown destroyed."""

import threading
import time

import pytest
import rclpy
from rclpy.executors import MultiThreadedExecutor, SingleThreadedExecutor

from area3d_msgs_py.spinning import Spinner

TIMEOUT_S = 60.0


@pytest.fixture
def thread_errors(monkeypatch):
    errors: list[str] = []
    monkeypatch.setattr(threading, "excepthook", lambda a: errors.append(repr(a.exc_value)))
    return errors


@pytest.mark.parametrize("make", [SingleThreadedExecutor, MultiThreadedExecutor])
def test_stopping_a_busy_spinner_over_and_over_raises_nothing_on_any_thread(
    make, thread_errors, capfd
):
    """A timer at 1 kHz keeps the executor in and out of its wait; each round stops the spinner
    as the timer fires and destroys the node at once. With the executor's own ``spin`` on the
    thread and ``shutdown`` from outside, about one round in twenty raised on the spinning
    thread (the destroyed guard condition), and the pool's callbacks used the destroyed timer."""
    context = rclpy.Context()
    rclpy.init(context=context)
    try:
        for i in range(60):
            node = rclpy.create_node(f"spun_{i}", context=context)
            ticks = []
            node.create_timer(0.001, lambda ticks=ticks: ticks.append(1))
            executor = make(context=context)
            executor.add_node(node)
            spinner = Spinner(executor, name=f"spin-{i}")
            assert spinner.alive
            deadline = time.monotonic() + TIMEOUT_S
            while not ticks and time.monotonic() < deadline:
                time.sleep(0.001)
            assert ticks, "the timer never fired: the executor did not spin"
            assert spinner.stop(TIMEOUT_S)
            assert not spinner.alive
            node.destroy_node()
    finally:
        context.try_shutdown()
    assert thread_errors == []
    assert "never retrieved" not in capfd.readouterr().err


def test_a_spinner_ends_when_its_context_is_shut_down_under_it(thread_errors):
    context = rclpy.Context()
    rclpy.init(context=context)
    node = rclpy.create_node("spun", context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    spinner = Spinner(executor)
    context.try_shutdown()  # a signal handler does this
    deadline = time.monotonic() + TIMEOUT_S
    while spinner.alive and time.monotonic() < deadline:
        time.sleep(0.01)
    assert not spinner.alive
    assert spinner.stop(TIMEOUT_S)
    assert thread_errors == []


def test_an_idle_spinner_stops_without_waiting_out_its_timeout(thread_errors):
    """Nothing wakes an executor whose node has no timer and gets no message; stop must end the
    wait itself (a plain wake of the executor only makes rclpy wait again, and the stop would
    have taken its whole timeout)."""
    context = rclpy.Context()
    rclpy.init(context=context)
    try:
        node = rclpy.create_node("idle", context=context)
        executor = MultiThreadedExecutor(context=context)
        executor.add_node(node)
        spinner = Spinner(executor)
        time.sleep(0.2)  # into its wait
        started = time.monotonic()
        assert spinner.stop(TIMEOUT_S)
        assert time.monotonic() - started < TIMEOUT_S / 2  # not the timeout (loose: a busy machine)
        assert not spinner.alive
        node.destroy_node()
    finally:
        context.try_shutdown()
    assert thread_errors == []
