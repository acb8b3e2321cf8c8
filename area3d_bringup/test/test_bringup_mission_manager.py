"""The mission manager waits for the graph's own readers of its topics before it sends a goal (a
reader of another program, a Foxglove client through the bridge, does not stand in for them), and
ends a wait once its ROS context is shut down."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
import rclpy
from rclpy.executors import MultiThreadedExecutor

from area3d_bringup.episode_config import EpisodeError
from area3d_bringup.mission_manager import MissionManager
from area3d_eval.rundir import Frame
from area3d_msgs_py import middleware, topics
from area3d_msgs_py.spinning import Spinner

TIMEOUT_S = 120.0


@pytest.fixture()
def manager(monkeypatch):
    """A mission manager on a context and a ROS domain of its own: a camera node of an earlier
    test may still be listed on the session's (discovery keeps a participant until its lease
    ends), and it would read the goals."""
    monkeypatch.delenv("ROS_DOMAIN_ID")
    lease = middleware.DomainLease()
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=lease.domain_id)
    try:
        yield MissionManager(None, context=context)
    finally:
        context.try_shutdown()
        lease.release()


def test_a_reader_that_is_not_the_camera_does_not_make_the_goal_topic_ready(manager):
    context = manager.context
    viewer = rclpy.create_node("foxglove_bridge", context=context)
    executor = MultiThreadedExecutor(context=context)
    for node in (manager, viewer):
        executor.add_node(node)
    spinner = Spinner(executor)
    goal = topics.GOAL
    try:
        # the viewer reads the goals first: the writer has one matched reader, not the camera's
        viewer.create_subscription(goal.msg_type, goal.name, lambda m: None, goal.qos())
        deadline = time.monotonic() + TIMEOUT_S
        while manager.goal_pub.get_subscription_count() < 1 and time.monotonic() < deadline:
            time.sleep(0.02)
        assert manager.goal_pub.get_subscription_count() == 1
        assert "goal" in manager.wait_for_readers(0.5)
        # the camera subscribes: the goal topic is ready (the camera topics still wait for theirs)
        camera = rclpy.create_node("sim_bridge", context=context)
        camera.create_subscription(goal.msg_type, goal.name, lambda m: None, goal.qos())
        executor.add_node(camera)
        deadline = time.monotonic() + TIMEOUT_S
        short = ["goal"]
        while "goal" in short and time.monotonic() < deadline:
            short = manager.wait_for_readers(0.5)
        assert "goal" not in short
        assert {"color", "depth", "info", "pose"} <= set(short)
    finally:
        spinner.stop(10)


def test_a_plan_awaited_ends_when_the_runners_context_is_shut_down(manager):
    # `area3d run --nodes none` (a graph started elsewhere) given SIGINT alone: its handler shuts
    # the runner's context down, and the request in flight ends with the user's stop instead of
    # waiting out its timeout for a planner that is not there
    frame = Frame(
        rgb=np.zeros((4, 4, 3), np.uint8), depth=np.ones((4, 4), np.float32), K=np.eye(3),
        T_world_cam=np.eye(4), stamp_ns=1_000,
    )  # fmt: skip
    outcome: list = []

    def ask() -> None:
        try:
            outcome.append(manager.plan(frame, 1, timeout_s=TIMEOUT_S))
        except Exception as err:  # noqa: BLE001 - the test reads what ended the wait
            outcome.append(err)

    asking = threading.Thread(target=ask)
    asking.start()
    time.sleep(0.5)  # the request is out, no planner answers it
    manager.context.try_shutdown()
    asking.join(TIMEOUT_S / 2)  # ends long before the request's own timeout
    assert not asking.is_alive()
    assert isinstance(outcome[0], EpisodeError) and "shut down" in str(outcome[0])
    with pytest.raises(EpisodeError):
        manager.check("planner")
