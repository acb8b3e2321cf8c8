"""An executor spun on its own thread stops without its thread touching what shutdown destroyed;
the guarded executors survive a message they cannot take."""

import threading
import time

import pytest
import rclpy
import std_msgs.msg._string as string_module
import std_srvs.srv._trigger as trigger_module
from rclpy.executors import MultiThreadedExecutor, SingleThreadedExecutor
from rclpy.qos import QoSProfile
from std_msgs.msg import String
from std_srvs.srv import Trigger

from area3d_msgs_py import diagnostics, guard
from area3d_msgs_py.spinning import GuardedExecutor, GuardedMultiThreadedExecutor, Spinner
from area3d_msgs_py.status import StatusPublisher

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


@pytest.fixture
def context():
    """A context of the test's own, shut down after it."""
    context = rclpy.Context()
    rclpy.init(context=context)
    yield context
    context.try_shutdown()


class _Untakeable:
    """Makes the next `failures` messages of a type rclpy takes fail to build, as one the CI saw
    did: rclpy builds a taken message by calling the class its module names, and this puts a
    class there whose constructor raises."""

    def __init__(self, monkeypatch, failures: int, module=string_module, name="String") -> None:
        self.left = failures
        owner = self
        base = getattr(module, name)

        class Failing(base):
            def __init__(self, **kwargs):
                if owner.left > 0:
                    owner.left -= 1
                    raise RuntimeError("the message class raised")
                super().__init__(**kwargs)

        monkeypatch.setattr(module, name, Failing)


def _talk(context, name: str):
    """A node with a String subscription, a timer in the same (default) callback group, and a
    publisher to the subscription; what arrives and the ticks are recorded."""
    node = rclpy.create_node(name, context=context)
    got: list[str] = []
    ticks: list[int] = []
    node.create_subscription(String, "said", lambda m: got.append(m.data), QoSProfile(depth=10))
    node.create_timer(0.01, lambda: ticks.append(1))
    pub = node.create_publisher(String, "said", QoSProfile(depth=10))
    return node, pub, got, ticks


def _spin_until(executor, done, timeout_s: float = TIMEOUT_S) -> None:
    deadline = time.monotonic() + timeout_s
    while not done() and time.monotonic() < deadline:
        executor.spin_once(timeout_sec=0.05)


def test_rclpy_alone_stops_serving_a_node_after_a_message_it_cannot_take(context, monkeypatch):
    """Why the guarded executors exist: rclpy's own executor raises the CI's error from `spin`,
    and from then on serves neither the subscription nor the timer beside it."""
    node, pub, got, ticks = _talk(context, "plain")
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    messages = [String(data=str(i)) for i in range(3)]  # built before the class is swapped
    _Untakeable(monkeypatch, 1)
    pub.publish(messages[0])
    with pytest.raises(RuntimeError, match="Unable to convert call argument '0'"):
        _spin_until(executor, lambda: False)
    before = len(ticks)
    for message in messages[1:]:
        pub.publish(message)
    for _ in range(40):  # 2 s of spinning: enough for 200 ticks
        executor.spin_once(timeout_sec=0.05)
    assert got == [] and len(ticks) == before
    node.destroy_node()


@pytest.mark.parametrize("make", [GuardedExecutor, GuardedMultiThreadedExecutor])
def test_a_message_that_cannot_be_taken_is_dropped_counted_and_logged_and_the_node_serves_on(
    make, context, monkeypatch, capfd
):
    monkeypatch.setattr(guard, "LOG_PERIOD_S", 3600.0)  # one log line per topic, then counts
    node, pub, got, ticks = _talk(context, "guarded")
    executor = make(context=context)
    executor.add_node(node)
    status = StatusPublisher(node, None, lambda: {"frames": 0})
    assert status.publish() == {"frames": 0}
    messages = [String(data=str(i)) for i in range(5)]
    untakeable = _Untakeable(monkeypatch, 2)
    pub.publish(messages[0])
    _spin_until(executor, lambda: untakeable.left == 1)
    pub.publish(messages[1])
    _spin_until(executor, lambda: untakeable.left == 0)
    assert executor.untaken() == {"/said": 2}
    # the node's status says so, and its diagnostics warn
    state = status.publish()
    assert state == {"frames": 0, "messages_dropped_untaken": {"/said": 2}}
    assessment = diagnostics.assess(state, {"frames": 0})
    assert assessment.level == diagnostics.WARN
    assert "2 dropped (messages_dropped_untaken./said)" in assessment.message
    before = len(ticks)
    for message in messages[2:]:
        pub.publish(message)
    _spin_until(executor, lambda: len(got) == 3 and len(ticks) > before)
    assert got == ["2", "3", "4"]  # the two that could not be taken are lost, no other
    assert len(ticks) > before  # the timer in the same callback group still fires
    err = capfd.readouterr().err
    # the first is logged with the topic, the type and the error; the second only counted
    assert err.count("could not be taken") == 1, err
    assert "/said: a String message could not be taken (RuntimeError: Unable to convert" in err
    assert "dropped as a lost message (1 on this topic so far)" in err
    node.destroy_node()


def test_a_request_that_cannot_be_taken_is_dropped_and_the_service_answers_the_next(
    context, monkeypatch, capfd
):
    """The same for a service: the request that cannot be built is lost (its call gets no
    answer, as a lost request), the next one is answered."""
    server = rclpy.create_node("server", context=context)
    server.create_service(Trigger, "trigger", lambda _, r: setattr(r, "success", True) or r)
    caller = rclpy.create_node("caller", context=context)
    client = caller.create_client(Trigger, "trigger")
    executor = GuardedExecutor(context=context)
    executor.add_node(server)
    executor.add_node(caller)
    _spin_until(executor, client.service_is_ready)
    untakeable = _Untakeable(monkeypatch, 1, trigger_module, "Trigger_Request")
    lost = client.call_async(Trigger.Request())
    _spin_until(executor, lambda: untakeable.left == 0)
    answered = client.call_async(Trigger.Request())
    _spin_until(executor, answered.done)
    assert answered.result().success and not lost.done()
    assert executor.untaken() == {"/trigger": 1}
    err = capfd.readouterr().err
    # (rclpy's service take reports the class's error as the cause of its own)
    assert "/trigger: a Trigger request could not be taken (" in err, err
    assert "from RuntimeError: the message class raised)" in err, err
    assert "dropped as a lost request (1 on this service so far)" in err
    server.destroy_node()
    caller.destroy_node()


def test_a_status_change_from_a_worker_as_the_node_is_destroyed_raises_nothing(
    context, thread_errors
):
    """A worker thread (the semantics node's VLM thread scheduling a retry) may say its status
    changed just as the node is destroyed: rclpy raised InvalidHandle on that thread (its
    timer was gone) and the thread died with a traceback. Before the node goes, a change still
    publishes shortly after."""
    node = rclpy.create_node("status_at_the_end", context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    published = []
    status = StatusPublisher(node, None, lambda: published.append(1) or {"frames": 0})
    status.changed()
    deadline = time.monotonic() + 60
    while not published and time.monotonic() < deadline:
        executor.spin_once(timeout_sec=0.05)
    assert published  # the change was published by the node's timer
    node.destroy_node()
    worker = threading.Thread(target=status.changed)
    worker.start()
    worker.join(30)
    assert not worker.is_alive() and thread_errors == []
    executor.shutdown()
