"""The mission manager waits for the graph's own readers of its topics before it sends a goal: a
reader of another program (a Foxglove client through the bridge) does not stand in for them."""

from __future__ import annotations

import time

import rclpy
from rclpy.executors import MultiThreadedExecutor

from area3d_bringup.mission_manager import MissionManager
from area3d_msgs_py import middleware, topics
from area3d_msgs_py.spinning import Spinner

TIMEOUT_S = 120.0


def test_a_reader_that_is_not_the_camera_does_not_make_the_goal_topic_ready(monkeypatch):
    # a domain of its own: a camera node of an earlier test may still be listed on the session's
    # (discovery keeps a participant until its lease ends), and it would read the goals
    monkeypatch.delenv("ROS_DOMAIN_ID")
    lease = middleware.DomainLease()
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=lease.domain_id)
    manager = MissionManager(None, context=context)
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
        context.try_shutdown()
        lease.release()
