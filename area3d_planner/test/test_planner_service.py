"""The planner node in-process, its callbacks called directly: the NextBestView service's answers
and refusals, poses from odometry, every output in world_frame."""

import numpy as np
import pytest
import rclpy
from rclpy.parameter import Parameter

from area3d_msgs_py import codecs, msgs
from area3d_msgs_py.camera_pose import look_at
from area3d_msgs_py.rotations import invert, matrix
from area3d_planner.node import PlannerNode

S = 1_000_000_000
T0 = 1_700_000_000 * S
K = np.array([[32.0, 0, 32], [0, 32.0, 24], [0, 0, 1]])
FRAME = "cam_optical"
MOUNT = matrix(np.array([0.1, 0.0, 0.3]), np.array([-0.5, 0.5, -0.5, 0.5]))
WAIT_S = 120.0
PARAMETERS = {
    "workspace_min": [0.0, 0.0, 0.0],
    "workspace_max": [1.0, 1.0, 1.0],
    "roi_min": [0.3, 0.0, 0.0],
    "roi_max": [1.0, 1.0, 1.0],
    "voxel_size": 0.05,
    "level": "room",
    "seed_spacing": 0.2,
    "yaw_bins": 6,
    "pitch_bins": 2,
    "face_res": 32,
    "budget": 4,
    "mode": "closed_loop",
    "eager_cache": False,
    "world_frame": "odom",
    "pose_source": "odometry",
    "camera_mount": "parameters",
    "mount_translation": [0.1, 0.0, 0.3],
    "mount_rotation": [-0.5, 0.5, -0.5, 0.5],
}


class Pub:
    def __init__(self):
        self.sent = []

    def publish(self, msg):
        self.sent.append(msg)


@pytest.fixture()
def planner():
    context = rclpy.Context()
    rclpy.init(context=context)
    overrides = [Parameter(k, value=v) for k, v in PARAMETERS.items()]
    node = PlannerNode(context=context, parameter_overrides=overrides)
    node.grid_pub, node.views_pub, node.markers_pub = Pub(), Pub(), Pub()
    try:
        yield node
    finally:
        node.stop()
        node.destroy_node()
        context.try_shutdown()


def odometry(stamp: int, T_odom_base: np.ndarray):
    msg = msgs.Odometry(header=codecs.header(stamp, "odom"), child_frame_id="base_link")
    msg.pose.pose = codecs.matrix_to_pose(T_odom_base)
    return msg


def feed_frame(node: PlannerNode, stamp: int, T_odom_cam: np.ndarray) -> None:
    """Odometry 10 ms before and after the frame, the camera info, perception's outputs."""
    base = T_odom_cam @ invert(MOUNT)
    for t in (stamp - S // 100, stamp + S // 100):
        node.inputs.poses._on_odometry(odometry(t, base))
    depth = np.full((48, 64), 0.525, np.float32)
    node.inputs._on_camera_info(codecs.intrinsics_to_camera_info(K, 64, 48, stamp, FRAME))
    node.inputs._part("depth", codecs.image_to_msg(depth, "32FC1", stamp, FRAME))
    node.inputs._part(
        "confidence", codecs.image_to_msg(np.full_like(depth, 0.8), "32FC1", stamp, FRAME)
    )


def ask(node: PlannerNode, count: int, T: np.ndarray, stamp: int, frame_id="odom", mode=""):
    request = codecs.view_request_to_msg(count, T, stamp, frame_id, mode)
    return node._on_select_views(request, msgs.NextBestView.Response())


def test_next_best_view_answers_views_with_gains_in_world_frame_or_says_why_not(planner):
    T = look_at(np.array([0.1, 0.5, 0.5]), np.array([1.0, 0.5, 0.5]))
    refused = ask(planner, 1, T, T0)
    assert not refused.success and refused.message.startswith("no frame fused yet")
    assert refused.views.poses == [] and list(refused.gains) == []
    assert refused.views.header.frame_id == "odom"

    feed_frame(planner, T0, T)
    assert planner.scheduler.wait_fused(T0, WAIT_S)
    # the frame's pose is the odometry composed with the mount
    np.testing.assert_allclose(planner.scheduler.core.context.camera_poses[0], T, atol=1e-9)
    answer = codecs.msg_to_view_answer(ask(planner, 2, T, T0))
    assert answer.success and answer.message == "" and answer.frame_id == "odom"
    assert answer.stamp_ns == T0 and len(answer.views) == 2
    assert np.all(np.isfinite(answer.gains)) and answer.gains[0] >= answer.gains[1] > 0
    for view in answer.views:
        assert np.all(view[:3, 3] >= 0.0) and np.all(view[:3, 3] <= 1.0)  # the workspace
    (path,) = planner.views_pub.sent[-1:]
    assert path.header.frame_id == "odom" and len(path.poses) == 2
    assert all(p.header.frame_id == "odom" for p in path.poses)
    assert {m.header.frame_id for m in planner.markers_pub.sent[-1].markers} == {"odom"}
    assert planner.grid_pub.sent and planner.grid_pub.sent[-1].header.frame_id == "odom"

    wrong_frame = ask(planner, 1, T, T0, frame_id="world")
    assert not wrong_frame.success
    assert "current.header.frame_id: got 'world', expected 'odom'" in wrong_frame.message
    named = ask(planner, 0, T, T0, mode="closed_loop")  # count 0 in closed loop: one view
    assert named.success and len(named.views.poses) == 1
    # asked again from the same frame, nothing fused since: that view was not captured and no
    # longer counts against the budget (4 = the frame + this view + the 2 batch views below)
    again = ask(planner, 0, T, T0, mode="closed_loop")
    assert again.success and len(again.views.poses) == 1
    rest = ask(planner, 0, T, T0, mode="batch")  # batch, count 0: the rest of the budget
    assert rest.success and len(rest.views.poses) == 2
    spent = ask(planner, 0, T, T0)
    assert not spent.success
    assert spent.message == "budget: all 4 views are spent (1 initial, 3 handed out)"
    status = planner._status()
    assert status["frames_dropped_no_pose"] == {} and status["frames_waiting_for_pose"] == 0


def test_a_request_with_an_unknown_mode_or_a_bad_pose_is_refused_by_field(planner):
    T = look_at(np.array([0.1, 0.5, 0.5]), np.array([1.0, 0.5, 0.5]))
    feed_frame(planner, T0, T)
    assert planner.scheduler.wait_fused(T0, WAIT_S)
    request = codecs.view_request_to_msg(1, T, T0, "odom")
    request.mode = "sideways"
    refused = planner._on_select_views(request, msgs.NextBestView.Response())
    assert not refused.success and "mode: got 'sideways'" in refused.message
    request = codecs.view_request_to_msg(1, T, T0, "odom")
    request.current.pose.orientation.w = 2.0
    refused = planner._on_select_views(request, msgs.NextBestView.Response())
    assert not refused.success and "current.pose.orientation: got" in refused.message
    # a frame stamped an hour ahead of the planner's clock is refused, not waited for
    ahead = planner.get_clock().now().nanoseconds + 3600 * S
    refused = ask(planner, 1, T, ahead)
    assert not refused.success
    assert refused.message.startswith(f"request rejected: current.header.stamp: got {ahead}")
    get_plan = msgs.GetPlan.Request()
    get_plan.start.header = codecs.header(ahead, "odom")
    get_plan.start.pose = codecs.matrix_to_pose(T)
    get_plan.goal.pose.position.x = 1.0
    assert planner._on_request(get_plan, msgs.GetPlan.Response()).plan.poses == []
    get_plan.start.header = codecs.header(T0, "odom")
    get_plan.goal.pose.position.x = -1.0  # refused as a request, as NaN and 2.7 are
    assert planner._on_request(get_plan, msgs.GetPlan.Response()).plan.poses == []
    assert planner.scheduler.core.committed == 0  # nothing was planned for them
    get_plan.goal.pose.position.x = 1.0  # and the node serves on
    assert len(planner._on_request(get_plan, msgs.GetPlan.Response()).plan.poses) == 1


def test_a_frame_without_odometry_is_dropped_and_counted_not_fused(planner):
    # pose_wait_s 0: a frame whose pose has not come is dropped
    planner.inputs.poses.core.wait_ns = 0
    depth = np.full((48, 64), 0.525, np.float32)
    planner.inputs._on_camera_info(codecs.intrinsics_to_camera_info(K, 64, 48, T0, FRAME))
    planner.inputs._part("depth", codecs.image_to_msg(depth, "32FC1", T0, FRAME))
    planner.inputs._part(
        "confidence", codecs.image_to_msg(np.full_like(depth, 0.8), "32FC1", T0, FRAME)
    )
    planner.inputs.poses.release()
    status = planner._status()
    assert status["frames_dropped_no_pose"] == {"no_transform": 1}
    assert status["frames_fused"] == 0


def test_a_request_with_an_empty_frame_id_is_read_in_world_frame(planner):
    """`ros2 service call area3d/planner/select_views ... "{count: 1}"` sends no frame_id."""
    T = look_at(np.array([0.1, 0.5, 0.5]), np.array([1.0, 0.5, 0.5]))
    feed_frame(planner, T0, T)
    assert planner.scheduler.wait_fused(T0, WAIT_S)
    answer = codecs.msg_to_view_answer(ask(planner, 1, T, T0, frame_id=""))
    assert answer.success and answer.frame_id == "odom" and len(answer.views) == 1


def test_a_streaming_camera_fuses_keyframes_and_an_answer_without_its_frame_says_how_old(planner):
    """30 Hz at rest: one keyframe a second, the rest skipped and counted; a request naming a
    frame that never came is answered from the map after sync_timeout_s, and says so."""
    T = look_at(np.array([0.1, 0.5, 0.5]), np.array([1.0, 0.5, 0.5]))
    period = S // 30
    for i in range(40):
        feed_frame(planner, T0 + i * period, T)
    status = planner._status()
    assert status["frames_integrated"] == 2 and status["frames_skipped"] == 38
    assert status["frames_paired"] == 40 and status["pairing_rate"] == 1.0
    assert planner.scheduler.wait_fused(T0 + 31 * period, WAIT_S)
    # a skipped frame from where the camera stands is covered at once
    covered = codecs.msg_to_view_answer(ask(planner, 1, T, T0 + 35 * period))
    assert covered.success and covered.message == ""
    planner.set_parameters([Parameter("sync_timeout_s", value=0.05)])
    far = look_at(np.array([0.2, 0.1, 0.9]), np.array([1.0, 0.5, 0.5]))
    late = T0 + 60 * S  # the frame of this pose never arrives
    answer = codecs.msg_to_view_answer(ask(planner, 1, far, late))
    assert answer.success and len(answer.views) == 1
    assert answer.message.startswith(f"frame {late} not fused within 0.05 s: planned from the map")
    assert f"frame {T0 + 31 * period}, " in answer.message
    assert planner._status()["budget"]["handed_out"] == 2
