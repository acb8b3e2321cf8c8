"""The mission manager: runs one active-reconstruction episode over the node graph.

It launches the graph, drives the camera through the initial views O_0, then asks the planner's
next-best-view service for views and drives the camera there until the view budget is spent.
Every captured frame is saved in the run directory as it arrives (and `episode.json` rewritten), so a
crash loses nothing and `--resume RUN_DIR` continues where the episode stopped: the saved frames are
replayed onto the camera topics for the new graph, then planning goes on with the remaining budget.

With `respawn` on, a node that dies is started again by the launcher and the episode goes on: the
step it interrupted (a capture for the camera, a plan or a wait for the planner) is retried once
the new process is up, and the graph is brought up to date from the same saved frames that
`--resume` replays, so the restarted planner fuses again everything it had fused (perception and
semantics recompute their outputs from the frames; the planner fuses each stamp once).
"""

from __future__ import annotations

import json
import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import rclpy
from rclpy.event_handler import PublisherEventCallbacks
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node

from area3d_bringup.launch_description import GRAPH_NODES, build_graph, load_parameters
from area3d_bringup.launcher import Launcher, NodeDied
from area3d_bringup.recorder import BagRecorder
from area3d_eval import rundir
from area3d_eval.rundir import Frame
from area3d_msgs_py import codecs, middleware, msgs, qos

#: policy name -> parameter overrides {node: {param: value}}; ablations are configurations.
POLICIES: dict[str, dict[str, dict]] = {
    "area3d": {"planner": {"policy": "area3d"}},
    "random": {"planner": {"policy": "random"}, "semantics": {"backend": "none"}},
    "uniform": {"planner": {"policy": "uniform"}, "semantics": {"backend": "none"}},
    "vlm_naive": {"planner": {"policy": "vlm_naive"}},
    "volumetric_ig": {"planner": {"policy": "volumetric_ig"}, "semantics": {"backend": "none"}},
    "no_vlm": {
        "planner": {"policy": "area3d", "semantic_weight": 0.0},
        "semantics": {"backend": "none"},
    },
    # uniform confidence on whatever depth the perception backend estimates (with rgbd: the same
    # output as the `uniform` backend)
    "no_ff": {"planner": {"policy": "area3d"}, "perception": {"uniform_confidence": True}},
    "gamma0": {"planner": {"policy": "area3d", "gamma": 0.0}},
}

# Relative names (the graph's namespace applies); {key: (topic, type)}.
CAMERA_TOPICS = {
    "color": ("area3d/camera/color/image_raw", msgs.Image),
    "depth": ("area3d/camera/depth/image_raw", msgs.Image),
    "info": ("area3d/camera/camera_info", msgs.CameraInfo),
    "pose": ("area3d/camera/pose", msgs.PoseStamped),
}
GOAL_TOPIC = "area3d/camera/goal_pose"
CAMERA_STATUS_TOPIC = "area3d/camera/status"
GRID_TOPIC = "area3d/planner/uncertainty_grid"
PLANNER_STATUS_TOPIC = "area3d/planner/status"
PERCEPTION_DEPTH_TOPIC = "area3d/perception/depth"
PERCEPTION_CONFIDENCE_TOPIC = "area3d/perception/confidence"
NBV_SERVICE = "area3d/planner/next_best_view"
TF_TOPIC, TF_STATIC_TOPIC = "/tf", "/tf_static"
# The grid is published after every fusion (in a burst, at most once a second and after the
# last); the runner's reader keeps a backlog of them.
GRID_READER_DEPTH = 100
#: what the bag holds besides the camera topics and the goals: {topic: (type, reader QoS)}.
#: Perception's and semantics' per-frame outputs are read transient local, as their writers
#: publish them: a reader that the writer matches only after a frame's output went out (its
#: discovery of this process finished late) still gets it, and the bag and the replay's count
#: of what perception answered miss nothing.
GRAPH_OUTPUTS = {
    CAMERA_STATUS_TOPIC: (msgs.String, qos.frames()),
    PERCEPTION_DEPTH_TOPIC: (msgs.Image, qos.graph_frames()),
    PERCEPTION_CONFIDENCE_TOPIC: (msgs.Image, qos.graph_frames()),
    "area3d/semantics/regions": (msgs.String, qos.latched(qos.FRAME_DEPTH)),
    "area3d/semantics/weight": (msgs.Image, qos.graph_frames()),
    "area3d/semantics/uncertainty": (msgs.Image, qos.graph_frames()),
    GRID_TOPIC: (msgs.PointCloud2, qos.latched(GRID_READER_DEPTH)),
    "area3d/planner/next_views": (msgs.Path, qos.frames()),
    PLANNER_STATUS_TOPIC: (msgs.String, qos.frames()),
}
# Readers each camera topic has once the graph is up (the runner's own included): volatile
# topics drop what is published before a reader has matched, so goals and replayed frames wait.
EXPECTED_READERS = {"goal": 1, "color": 3, "depth": 3, "info": 3, "pose": 3}
# The runner's topics each graph node reads: once a new process of a restarted node reads them
# all, and the runner's writers have matched every reader discovery lists, it is up (a dead
# process's readers linger in discovery for a while, and a reader discovery lists a moment
# before the writer has matched it would miss what is published in between).
READS = {
    "sim_bridge": ("goal",),
    "perception": ("color", "depth", "info", "pose"),
    "semantics": ("color", "depth"),
    "planner": ("info", "pose"),
}
# The nodes whose restart loses fused evidence until the saved frames are replayed.
FUSION_NODES = ("perception", "semantics", "planner")
# A replayed frame that perception has not answered within this long is published again (its
# first copy may have gone out before a restarted node's readers had matched).
REPLAY_RESEND_S = 10.0
# After the camera was restarted, a goal whose frame has not arrived whole is sent again this often
# (the camera answers a repeated stamp with the same frame; the graph fuses each stamp once).
CAPTURE_RESEND_S = 5.0


class EpisodeError(RuntimeError):
    """The episode could not go on; the message says why and what was kept."""


class NodeRespawned(RuntimeError):
    """A graph node was restarted while a step that depends on it was under way."""

    def __init__(self, name: str):
        self.name = name
        super().__init__(f"node {name!r} was restarted")


@dataclass
class EpisodeConfig:
    scene: str = "single_object"
    policy: str = "area3d"
    budget: int | None = None  # total views, O_0 included; None: the paper's T (25 object, 40 room)
    mode: str = "closed_loop"
    seed: int = 0
    out_dir: Path = Path("runs")
    run_name: str | None = None
    record: bool = True
    params_file: Path | None = None
    overrides: dict[str, dict] = field(default_factory=dict)
    domain_id: int | None = None  # None: $ROS_DOMAIN_ID, else a free domain
    namespace: str = ""  # ROS namespace of the graph and the runner, e.g. "/robot1"
    transport: str | None = None  # middleware.TRANSPORTS; None: $AREA3D_TRANSPORT or "shm"
    # graph nodes this runner starts (None: all); the others run elsewhere (`area3d launch --nodes`)
    nodes: tuple[str, ...] | None = None
    capture_timeout_s: float = 30.0
    plan_timeout_s: float = 120.0
    fuse_timeout_s: float = 30.0
    startup_timeout_s: float = 90.0
    # what the TSDF integrates (rundir.DEPTH_SOURCES): the camera's depth, or perception's estimate
    # (then kept in every frame file)
    depth_source: str = "sensor"
    # a node that dies is restarted (bounded) and the episode goes on, instead of stopping it
    respawn: bool = False
    respawn_delay_s: float = 1.0
    respawn_max_retries: int = 3  # per node
    min_free_mb: float = rundir.MIN_FREE_MB  # the output directory must have this much free
    # capture stamps in ns (None: the runner's ROS clock); tests inject time instead of sleeping
    clock: Callable[[], int] | None = None
    # serve every topic on a Foxglove WebSocket on this port (None: no live view)
    foxglove_port: int | None = None
    foxglove_address: str = "127.0.0.1"  # this machine only unless told otherwise


def paper_budget(level: str) -> int:
    """The paper's view budget T (total views, O_0 included): 25 object level, 40 scene level."""
    return 25 if level == "object" else 40


def _type_name(msg_type: type) -> str:
    return msgs.type_name_of(msg_type())


class MissionManager(Node):
    """The runner's node: sends goals, collects frames, records the graph, calls the planner."""

    def __init__(
        self,
        recorder: BagRecorder | None,
        launcher: Launcher | None = None,
        clock: Callable[[], int] | None = None,
        keep_estimates: bool = False,
        **kwargs: Any,
    ):
        super().__init__("mission_manager", **kwargs)
        # {stamp: {"depth" | "confidence": image}} of perception's outputs, when the run keeps them
        self.estimates: dict[int, dict[str, np.ndarray]] | None = {} if keep_estimates else None
        self.recorder = recorder
        self.launcher = launcher  # the graph's processes: who died, who was restarted when
        self.acknowledged: dict[str, int] = self.respawns()  # restarts already caught up with
        self.clock = clock or (lambda: self.get_clock().now().nanoseconds)
        self.perceived: dict[int, int] = {}  # stamp -> perception outputs seen for it
        self.known_readers: set[tuple] = set()
        # Per runner topic: every reader id discovery has listed, and how many readers the
        # writer has matched in all (a dead process's readers stay in both counts).
        self.listed: dict[str, set[tuple]] = {}
        self.matched_total: dict[str, int] = {}
        self.unlisted_matches: dict[str, int] = {}  # matched before the runner first looked
        self._lock = threading.Condition()
        self._parts: dict[int, dict[str, Any]] = {}
        self._status: dict[int, dict] = {}
        self.planner_status: dict = {}
        self.latest_grid: bytes | None = None
        self.received: dict[str, int] = {}
        self.goal_pub = self.create_publisher(
            msgs.PoseStamped, GOAL_TOPIC, qos.frames(), event_callbacks=self._on_match("goal")
        )
        self.replay_pubs = {
            key: self.create_publisher(
                msg_type, topic, qos.frames(), event_callbacks=self._on_match(key)
            )
            for key, (topic, msg_type) in CAMERA_TOPICS.items()
        }
        self.runner_pubs = {"goal": self.goal_pub, **self.replay_pubs}  # what graph nodes read
        for key, (topic, msg_type) in CAMERA_TOPICS.items():
            self._listen(topic, msg_type, qos.frames(), self._on_part(key, msg_type))
        for topic, (msg_type, profile) in GRAPH_OUTPUTS.items():
            self._listen(topic, msg_type, profile, self._on_output(topic))
        self.tf_from_graph = msgs.TFMessage is not None
        if self.tf_from_graph:
            self._listen(TF_TOPIC, msgs.TFMessage, qos.reliable(100), None)
            self._listen(TF_STATIC_TOPIC, msgs.TFMessage, qos.latched(), None)
        self.client = self.create_client(msgs.GetPlan, NBV_SERVICE)

    # -- callbacks (executor thread) ---------------------------------------------------------
    def _on_match(self, key: str) -> PublisherEventCallbacks:
        def matched(status) -> None:
            with self._lock:
                self.matched_total[key] = status.total_count

        return PublisherEventCallbacks(matched=matched)

    def _listen(self, topic: str, msg_type: type, profile, handle) -> None:
        type_name = _type_name(msg_type)
        resolved = self.resolve_topic_name(topic)

        def callback(cdr: bytes) -> None:
            msg = msgs.deserialize(cdr, type_name)
            stamp = codecs.stamp_to_ns(msg.header.stamp) if hasattr(msg, "header") else 0
            self.record(resolved, type_name, stamp, cdr)
            with self._lock:
                self.received[resolved] = self.received.get(resolved, 0) + 1
                if handle is not None:
                    handle(msg, cdr)
                self._lock.notify_all()

        self.create_subscription(msg_type, topic, callback, profile, raw=True)

    def record(self, topic: str, type_name: str, stamp_ns: int, cdr: bytes) -> None:
        if self.recorder is not None:
            stamp = stamp_ns or self.get_clock().now().nanoseconds
            self.recorder.write(topic, type_name, stamp, cdr)

    def _on_part(self, key: str, msg_type: type) -> Callable[[Any, bytes], None]:
        def handle(msg: Any, cdr: bytes) -> None:
            stamp = codecs.stamp_to_ns(msg.header.stamp)
            self._parts.setdefault(stamp, {})[key] = msg
            if key == "pose" and not self.tf_from_graph:
                self._record_tf(stamp, codecs.pose_to_matrix(msg.pose))

        return handle

    def _on_output(self, topic: str) -> Callable[[Any, bytes], None]:
        def handle(msg: Any, cdr: bytes) -> None:
            if topic == PERCEPTION_DEPTH_TOPIC:
                stamp = codecs.stamp_to_ns(msg.header.stamp)
                self.perceived[stamp] = self.perceived.get(stamp, 0) + 1
            elif topic == CAMERA_STATUS_TOPIC:
                status = json.loads(msg.data)
                self._status[int(status.get("stamp_ns", 0))] = status
            elif topic == PLANNER_STATUS_TOPIC:
                self.planner_status = json.loads(msg.data)
            elif topic == GRID_TOPIC:
                self.latest_grid = cdr
            if self.estimates is not None and topic in (
                PERCEPTION_DEPTH_TOPIC,
                PERCEPTION_CONFIDENCE_TOPIC,
            ):
                key = "depth" if topic == PERCEPTION_DEPTH_TOPIC else "confidence"
                stamp = codecs.stamp_to_ns(msg.header.stamp)
                self.estimates.setdefault(stamp, {})[key] = codecs.msg_to_image(msg)

        return handle

    def _record_tf(self, stamp_ns: int, T_world_opt: np.ndarray) -> None:
        """TF as sim_bridge would publish it, written to the bag (tf2_msgs does not import here)."""
        from area3d_bringup.tf_bag import static_tf_cdr, tf_cdr

        if self.recorder is None:
            return
        if not self.recorder.counts.get(TF_STATIC_TOPIC):
            self.recorder.write(
                TF_STATIC_TOPIC, "tf2_msgs/msg/TFMessage", stamp_ns, static_tf_cdr(stamp_ns)
            )
        self.recorder.write(
            TF_TOPIC, "tf2_msgs/msg/TFMessage", stamp_ns, tf_cdr(stamp_ns, T_world_opt)
        )

    # -- restarts -----------------------------------------------------------------------------
    def respawns(self) -> dict[str, int]:
        return {} if self.launcher is None else dict(self.launcher.respawns)

    def alive_check(self) -> None:
        """Raise `NodeDied` if a node of the graph has died for good."""
        if self.launcher is not None:
            self.launcher.check()

    def check(self, *nodes: str) -> None:
        """Raise `NodeDied` for a node dead for good, `NodeRespawned` if one of `nodes` was
        restarted since the runner last caught up with it."""
        self.alive_check()
        counts = self.respawns()
        for name in nodes:
            if counts.get(name, 0) != self.acknowledged.get(name, 0):
                raise NodeRespawned(name)

    def restarted(self) -> list[str]:
        """Nodes restarted since the runner last caught up with them."""
        counts = self.respawns()
        return [n for n, c in counts.items() if c != self.acknowledged.get(n, 0)]

    def acknowledge(self, names: list[str]) -> None:
        counts = self.respawns()
        with self._lock:
            for name in names:
                self.acknowledged[name] = counts.get(name, 0)
            if "planner" in names:
                self.planner_status = {}  # the new planner starts from nothing

    def _list(self, key: str) -> list:
        """The readers discovery lists on the runner's topic `key` (all remembered in `listed`)."""
        infos = self.get_subscriptions_info_by_topic(self.runner_pubs[key].topic_name)
        self.listed.setdefault(key, set()).update(tuple(i.endpoint_gid) for i in infos)
        return infos

    def _readers(self, name: str) -> set[tuple]:
        """(topic, reader id) of every reader `name` has on the runner's topics."""
        return {
            (key, tuple(info.endpoint_gid))
            for key in READS[name]
            for info in self._list(key)
            if info.node_name == name
        }

    def _all_matched(self, key: str) -> bool:
        """The writer has matched every reader ever listed on `key`. Exact where a live count
        is not: discovery can list a new reader before the writer has matched it, and drop a
        dead process's reader before (or after) the writer unmatches it."""
        with self._lock:
            matched = self.matched_total.get(key, 0) - self.unlisted_matches.get(key, 0)
        return matched >= len(self.listed.get(key, ()))

    def note_readers(self, names: list[str]) -> None:
        """Remember the readers the graph's nodes have now (a later new one is a new process)."""
        for name in names:
            self.known_readers |= self._readers(name)
        for key in self.runner_pubs:
            self._list(key)
            listed = len(self.listed[key])
            with self._lock:
                if key not in self.unlisted_matches:
                    self.unlisted_matches[key] = max(0, self.matched_total.get(key, 0) - listed)

    def _up(self, name: str) -> bool:
        """A new process of `name` reads every topic it reads from the runner, all matched."""
        new_on = {key for key, _ in self._readers(name) - self.known_readers}
        return new_on == set(READS[name]) and all(self._all_matched(k) for k in READS[name])

    def wait_new_readers(self, names: list[str], timeout_s: float) -> None:
        """Wait until each restarted node reads the runner's topics from its new process."""
        deadline = time.monotonic() + timeout_s
        for name in names:
            while not self._up(name):
                if time.monotonic() > deadline:
                    raise TimeoutError(
                        f"restarted node {name!r} did not come up within {timeout_s:.0f} s"
                    )
                self.check(*READS)
                time.sleep(0.05)
        self.note_readers(names)

    # -- episode steps (main thread) --------------------------------------------------------
    def wait_for_readers(self, timeout_s: float) -> list[str]:
        """Wait until the camera topics have their graph readers; the topics still short of them."""
        pubs = self.runner_pubs
        deadline = time.monotonic() + timeout_s
        while True:
            short = [
                k for k, pub in pubs.items() if pub.get_subscription_count() < EXPECTED_READERS[k]
            ]
            if not short or time.monotonic() > deadline:
                return short
            self.alive_check()
            time.sleep(0.05)

    def capture(
        self, T_world_cam: np.ndarray, timeout_s: float, stamp: int | None = None
    ) -> Frame | str:
        """Send the camera to `T_world_cam`; the frame, or the camera's reason for refusing.

        `stamp` (default: now) is the capture stamp; a capture repeated after the camera restarted
        keeps it, so if the dead camera had published the frame after all, the graph sees the same
        frame twice (and fuses it once) rather than one view as two. Once the camera has been
        restarted, a goal whose frame has not arrived whole is sent again every
        `CAPTURE_RESEND_S`: a new camera process's reader can be listed a moment before the
        runner's writer has matched it, and its writers can send the frame before they have
        matched the runner's readers (then some parts of the frame arrive, others never)."""
        stamp = self.clock() if stamp is None else stamp
        goal = msgs.PoseStamped(
            header=codecs.header(stamp, "world"), pose=codecs.matrix_to_pose(T_world_cam)
        )
        self.record(
            self.resolve_topic_name(GOAL_TOPIC), "geometry_msgs/msg/PoseStamped", stamp,
            msgs.serialize(goal),
        )  # fmt: skip
        self.goal_pub.publish(goal)
        deadline = time.monotonic() + timeout_s
        restarted = bool(self.respawns().get("sim_bridge"))
        resend_at = time.monotonic() + CAPTURE_RESEND_S
        with self._lock:
            while True:
                status = self._status.get(stamp)
                if status is not None and not status.get("ok", False):
                    return str(status.get("reason", "rejected"))
                parts = self._parts.get(stamp, {})
                if len(parts) == len(CAMERA_TOPICS):
                    del self._parts[stamp]
                    break
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise TimeoutError(
                        f"no frame from sim_bridge within {timeout_s:.0f} s for the goal stamped {stamp}"
                    )
                self._lock.wait(min(remaining, 0.1))
                self.check("sim_bridge")  # a restarted camera never got the goal: ask again
                if restarted and time.monotonic() > resend_at:
                    resend_at = time.monotonic() + CAPTURE_RESEND_S
                    self.goal_pub.publish(goal)
        K, _, _ = codecs.camera_info_to_intrinsics(parts["info"])
        return Frame(
            rgb=codecs.msg_to_image(parts["color"]),
            depth=codecs.msg_to_image(parts["depth"]),
            K=K,
            T_world_cam=codecs.pose_to_matrix(parts["pose"].pose),
            stamp_ns=stamp,
        )

    def replay(self, frame: Frame) -> None:
        """Publish a saved frame on the camera topics, as the camera did when it was captured."""
        h, w = frame.depth.shape
        header_args = (frame.stamp_ns, "camera_optical_frame")
        self.replay_pubs["color"].publish(codecs.image_to_msg(frame.rgb, "rgb8", *header_args))
        self.replay_pubs["depth"].publish(codecs.image_to_msg(frame.depth, "32FC1", *header_args))
        self.replay_pubs["info"].publish(
            codecs.intrinsics_to_camera_info(frame.K, w, h, *header_args)
        )
        self.replay_pubs["pose"].publish(
            msgs.PoseStamped(
                header=codecs.header(frame.stamp_ns, "world"),
                pose=codecs.matrix_to_pose(frame.T_world_cam),
            )
        )

    def estimates_received(self) -> dict[int, dict[str, np.ndarray]]:
        """{stamp: {"depth", "confidence"}} of what perception has published so far."""
        with self._lock:
            return dict(self.estimates or {})

    def wait_until(
        self,
        predicate: Callable[[], bool],
        timeout_s: float,
        interrupted_by: tuple = FUSION_NODES,
    ) -> bool:
        """Wait for `predicate` (lock held while it runs); a restart of `interrupted_by` raises:
        what the wait counts on may never come without the replay that follows a restart."""
        deadline = time.monotonic() + timeout_s
        with self._lock:
            while not predicate():
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return False
                self._lock.wait(min(remaining, 0.1))
                self.check(*interrupted_by)
        return True

    def replay_all(self, frames: list[Frame], timeout_s: float, log: Callable[[str], None]) -> None:
        """Replay saved frames so the graph knows them (after `--resume` or a restart).

        One frame at a time, each waited for until perception has answered it: parts of a later
        frame never overtake an earlier one, however far apart the saved stamps are. Then wait
        until the planner has fused every one; if it has not within `REPLAY_RESEND_S`, replay
        them all again (a restarted planner's reader can be listed by discovery a moment before
        the runner's writer has matched it; the planner fuses each stamp once, so frames it
        already has change nothing). Any restart meanwhile raises `NodeRespawned`: the caller
        starts over."""
        deadline = None
        while True:
            for i, frame in enumerate(frames):
                self._replay_one(i, frame, timeout_s, log)
            deadline = deadline or time.monotonic() + timeout_s
            if self.wait_until(
                lambda: int(self.planner_status.get("frames_fused", 0)) >= len(frames),
                min(REPLAY_RESEND_S, max(0.0, deadline - time.monotonic())),
                interrupted_by=tuple(READS),
            ):
                return
            fused = self.planner_status.get("frames_fused", 0)
            if time.monotonic() >= deadline:
                log(
                    f"[mission_manager] the planner has fused {fused} of {len(frames)} replayed "
                    f"frames after {timeout_s:.0f} s; going on"
                )
                return
            log(
                f"[mission_manager] the planner has fused {fused} of {len(frames)} replayed "
                "frames; replaying them again"
            )

    def _replay_one(
        self, index: int, frame: Frame, timeout_s: float, log: Callable[[str], None]
    ) -> None:
        """Replay one frame and wait until perception has answered it (publishing it again every
        `REPLAY_RESEND_S`: its first copy may have gone out before a new reader matched)."""
        deadline = time.monotonic() + timeout_s
        while True:
            seen = self.perceived.get(frame.stamp_ns, 0)
            self.replay(frame)
            if self.wait_until(
                lambda n=seen: self.perceived.get(frame.stamp_ns, 0) > n,
                min(REPLAY_RESEND_S, max(0.0, deadline - time.monotonic())),
                interrupted_by=tuple(READS),
            ):
                return
            if time.monotonic() >= deadline:
                log(
                    f"[mission_manager] replayed frame {index} (stamp {frame.stamp_ns}) not "
                    f"processed by perception after {timeout_s:.0f} s; going on"
                )
                return

    def wait_fused(self, count: int, timeout_s: float, key: str = "frames_fused") -> bool:
        """Wait until the planner reports at least `count` fused frames (or semantic maps, by `key`)."""
        return self.wait_until(lambda: int(self.planner_status.get(key, 0)) >= count, timeout_s)

    def plan(self, current: Frame, count: int, timeout_s: float) -> list[np.ndarray]:
        """Ask the planner for `count` views (0 = what the budget allows) from the current pose."""
        request = msgs.GetPlan_Request(
            start=msgs.PoseStamped(
                header=codecs.header(current.stamp_ns, "world"),
                pose=codecs.matrix_to_pose(current.T_world_cam),
            ),
            goal=msgs.PoseStamped(
                header=codecs.header(current.stamp_ns, "world"),
                pose=codecs.matrix_to_pose(np.eye(4)),
            ),
            tolerance=0.0,
        )
        request.goal.pose.position.x = float(count)
        future = self.client.call_async(request)
        done = threading.Event()
        future.add_done_callback(lambda _: done.set())
        deadline = time.monotonic() + timeout_s
        # Poll so that a planner dying mid-call is noticed at once.
        while not done.wait(0.1):
            try:
                self.check("planner")  # a restarted planner will never answer this call
            except (NodeRespawned, NodeDied):
                self.client.remove_pending_request(future)
                raise
            if time.monotonic() > deadline:
                self.client.remove_pending_request(future)
                raise TimeoutError(f"no answer from {NBV_SERVICE} within {timeout_s:.0f} s")
        response = future.result()
        return [codecs.pose_to_matrix(p.pose) for p in response.plan.poses]


def run_episode(
    config: EpisodeConfig, resume: Path | None = None, progress: object | None = None
) -> Path:
    """Run one episode; returns the run directory (frames, episode.json, bag, grids)."""
    from sim_bridge.scenes import load_scene

    if config.policy not in POLICIES:
        raise ValueError(f"policy: got {config.policy!r}, expected one of {sorted(POLICIES)}")
    graph_names = [name for name, _ in GRAPH_NODES]
    if config.nodes is not None and not set(config.nodes) <= set(graph_names):
        raise ValueError(f"nodes: got {list(config.nodes)}, expected names from {graph_names}")
    if config.mode not in ("closed_loop", "batch"):
        raise ValueError(f"mode: got {config.mode!r}, expected 'closed_loop' or 'batch'")
    scene = load_scene(config.scene)
    budget = paper_budget(scene.level) if config.budget is None else int(config.budget)
    if budget < len(scene.initial_views):
        raise ValueError(
            f"budget: got {budget}, expected the total number of views, at least |O_0| = {len(scene.initial_views)}"
        )

    timings: dict[str, float] = {}
    views: list[dict] = []
    frames: list[Frame] = []
    if resume is not None:
        run_dir = Path(resume)
        episode_path = run_dir / rundir.EPISODE_FILE
        if not episode_path.is_file():
            raise FileNotFoundError(
                f"resume: got {str(run_dir)!r}, expected a run directory with episode.json"
            )
        rundir.check_output_dir(run_dir, config.min_free_mb)
        saved = json.loads(episode_path.read_text())
        config.scene, config.policy, config.mode = saved["scene"], saved["policy"], saved["mode"]
        config.seed, budget = saved["seed"], saved["budget"]
        config.depth_source = saved.get("depth_source", config.depth_source)
        scene = load_scene(config.scene)
        views = saved["views"]
        frames = [rundir.read_frame(rundir.frame_path(run_dir, v["index"])) for v in views]
        timings = saved.get("timings_s", {})
    else:
        name = (
            config.run_name
            or f"{scene.name}_{config.policy}_s{config.seed}_{time.strftime('%Y%m%d-%H%M%S')}"
        )
        rundir.check_output_dir(config.out_dir, config.min_free_mb)
        run_dir = Path(config.out_dir) / name
        run_dir.mkdir(parents=True, exist_ok=False)
    n_init = len(scene.initial_views)
    rundir.check_depth_source(config.depth_source)

    overrides: dict[str, dict] = {}
    for node, values in POLICIES[config.policy].items():
        overrides.setdefault(node, {}).update(values)
    overrides.setdefault("sim_bridge", {}).update(
        {"scene": config.scene, "readers.all": ["mission_manager"]}
    )
    overrides.setdefault("planner", {}).update(
        {"budget": budget, "mode": config.mode, "seed": config.seed}
    )
    for node, values in config.overrides.items():
        overrides.setdefault(node, {}).update(values)
    specs = build_graph(load_parameters(config.params_file), overrides)

    recorded: dict[str, int] = dict(saved.get("recorded", {})) if resume is not None else {}
    lease = middleware.DomainLease(config.domain_id)
    domain_id = lease.domain_id

    def save_episode() -> None:
        counts = dict(recorded)
        if recorder is not None:
            for topic, n in recorder.counts.items():
                counts[topic] = counts.get(topic, 0) + n
        rundir.write_episode(
            run_dir,
            {
                "scene": config.scene,
                "policy": config.policy,
                "seed": config.seed,
                "budget": budget,
                "level": scene.level,
                "mode": config.mode,
                "depth_source": config.depth_source,
                "views": views,
                "timings_s": timings,
                "config": {spec.name: spec.parameters for spec in specs},
                "ros": {"domain_id": domain_id, "namespace": config.namespace},
                "recorded": counts,
                "respawns": dict(launcher.respawns),
                "planner_status": manager.planner_status,
            },
        )

    def add_time(stage: str, seconds: float) -> None:
        timings[stage] = timings.get(stage, 0.0) + seconds

    # Discovery stays on this machine unless the caller's environment says otherwise.
    discovery = os.environ.get("ROS_AUTOMATIC_DISCOVERY_RANGE") or "LOCALHOST"
    env = middleware.graph_env(domain_id, config.transport, discovery)
    os.environ.update(env)  # this process's own participant: same transport and discovery
    log_path = run_dir / rundir.LOG_FILE
    log_file = log_path.open("a")
    log_lock = threading.Lock()

    def log_sink(line: str) -> None:
        with log_lock:
            log_file.write(line + "\n")
            log_file.flush()

    recorder = BagRecorder(rundir.bag_path(run_dir)) if config.record else None
    t0 = time.monotonic()
    local = [spec for spec in specs if config.nodes is None or spec.name in config.nodes]
    if config.foxglove_port is not None:
        from area3d_bringup.foxglove_bridge import bridge_spec

        local.append(bridge_spec(config.foxglove_port, config.foxglove_address))
    launcher = Launcher(
        local,
        run_dir,
        env=env,
        log_sink=log_sink,
        namespace=config.namespace,
        respawn=config.respawn,
        respawn_delay_s=config.respawn_delay_s,
        respawn_max_retries=config.respawn_max_retries,
    )
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=domain_id)
    manager = MissionManager(
        recorder,
        launcher=launcher,
        clock=config.clock,
        keep_estimates=config.depth_source == "estimated",
        context=context,
        namespace=config.namespace or None,
    )
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(manager)
    spinner = threading.Thread(target=_spin, args=(executor,), name="mission-manager", daemon=True)
    spinner.start()
    log_sink(
        f"[mission_manager] graph on ROS_DOMAIN_ID={domain_id}"
        f"{' (picked: free)' if lease.picked else ''}, namespace {config.namespace or '/'}, "
        f"transport {env[middleware.TRANSPORT_ENV]}, discovery {discovery}"
    )
    task = None
    try:
        launcher.start()
        deadline = time.monotonic() + config.startup_timeout_s
        while not manager.client.wait_for_service(0.5):
            launcher.check()
            if time.monotonic() > deadline:
                raise EpisodeError(
                    f"the planner service {NBV_SERVICE} did not appear within {config.startup_timeout_s:.0f} s"
                )
        short = manager.wait_for_readers(config.startup_timeout_s)
        if short:
            log_sink(
                f"[mission_manager] topics {short} have fewer readers than the graph should give them"
            )
        manager.note_readers(list(READS))
        add_time("launch", time.monotonic() - t0)
        semantics = next(spec for spec in specs if spec.name == "semantics").parameters
        with_semantics = semantics.get("backend", "heuristic") != "none"
        if progress is not None:
            task = progress.add_task(f"{scene.name} / {config.policy}", total=budget)
            progress.update(task, completed=len(frames))

        def keep(frame: Frame, kind: str, stage_times: dict) -> None:
            index = len(frames)
            rundir.write_frame(run_dir, index, *frame, stamp_ns=frame.stamp_ns)
            frames.append(frame)
            views.append(
                {
                    "index": index,
                    "stamp_ns": frame.stamp_ns,
                    "T_world_cam": frame.T_world_cam.tolist(),
                    "kind": kind,
                    "stage_times_s": stage_times,
                }
            )
            save_episode()
            if progress is not None:
                status = manager.planner_status
                metric = status.get("uncertainty_total")
                extra = f" | U={metric:.1f}" if isinstance(metric, int | float) else ""
                progress.update(
                    task,
                    completed=len(frames),
                    description=f"{scene.name} / {config.policy}: view {len(frames)}/{budget} ({kind}){extra}",
                )

        catching_up: set[str] = set()  # restarted nodes whose new process is not up yet
        replay_due = False  # a restart lost fused evidence that the saved frames give back
        # After a restart, the camera's own writers may match the new process's readers only
        # after its next frame went out (discovery between two other processes is not something
        # the runner can wait on): the first frame captured after a restart is checked as fused,
        # and replayed through the runner's writers (matched, waited for) if it is not.
        check_next_capture = False

        def recover() -> None:
            """Bring restarted nodes up to date: wait for their new process, then replay every
            saved frame (not after the camera alone: it keeps no state). A restart meanwhile
            starts this over, with nothing of the earlier one forgotten."""
            nonlocal replay_due, check_next_capture
            while True:
                changed = manager.restarted()
                if changed:
                    log_sink(
                        f"[mission_manager] {', '.join(changed)} restarted; bringing the graph up to date"
                    )
                    manager.acknowledge(changed)
                    catching_up.update(changed)
                    replay_due = replay_due or bool(set(changed) - {"sim_bridge"})
                    check_next_capture = True
                if not catching_up and not replay_due:
                    return
                t = time.monotonic()
                try:
                    for name in sorted(catching_up):
                        manager.wait_new_readers([name], config.startup_timeout_s)
                        catching_up.discard(name)
                    if replay_due and frames:
                        manager.replay_all(frames, config.fuse_timeout_s, log_sink)
                        if with_semantics and len(frames) >= n_init:
                            semantic_maps_back()
                    replay_due = False
                except NodeRespawned:
                    continue
                add_time("recover", time.monotonic() - t)

        def all_fused(wait_s: float) -> bool:
            """The planner has fused every captured frame; where it has not within `wait_s`,
            replay them (it fuses each stamp once) and wait up to the fusion timeout."""
            if manager.wait_fused(len(frames), wait_s):
                return True
            log_sink(
                f"[mission_manager] the planner has fused {manager.planner_status.get('frames_fused', 0)} "
                f"of {len(frames)} captured frames; replaying them"
            )
            manager.replay_all(frames, config.fuse_timeout_s, log_sink)
            return manager.wait_fused(len(frames), 0.0)

        def captured() -> None:
            """After the first capture following a restart, make sure the graph has it."""
            nonlocal check_next_capture
            if check_next_capture:
                step(lambda: all_fused(REPLAY_RESEND_S))
                check_next_capture = False

        def semantic_maps_back() -> None:
            """The planner holds the semantic maps of O_0 again (a restarted semantics queries
            the initial views once it has them; replay them again until it has)."""
            deadline = time.monotonic() + config.plan_timeout_s
            while not manager.wait_fused(n_init, REPLAY_RESEND_S, key="semantic_frames_fused"):
                if time.monotonic() > deadline:
                    log_sink(
                        f"[mission_manager] no semantic maps of the initial views after "
                        f"{config.plan_timeout_s:.0f} s; going on without them"
                    )
                    return
                log_sink(
                    "[mission_manager] no semantic maps of the initial views yet; replaying them"
                )
                manager.replay_all(frames[:n_init], config.fuse_timeout_s, log_sink)

        def step(action: Callable[[], Any]) -> Any:
            """Run one episode step; a restart it depends on is caught up with and it runs again."""
            while True:
                recover()
                try:
                    return action()
                except NodeRespawned as err:
                    log_sink(f"[mission_manager] {err} during a step; repeating the step")

        # Replay what an interrupted episode had already captured, so the new graph knows it.
        if frames:
            t = time.monotonic()
            step(lambda: manager.replay_all(frames, config.fuse_timeout_s, log_sink))
            add_time("replay", time.monotonic() - t)

        for T in scene.initial_views[len(frames) : n_init] if len(frames) < n_init else []:
            t = time.monotonic()
            stamp = manager.clock()  # kept if the capture is repeated
            result = step(lambda T=T, s=stamp: manager.capture(T, config.capture_timeout_s, s))
            launcher.check()
            if isinstance(result, str):
                raise EpisodeError(f"the camera refused initial view {len(frames)}: {result}")
            add_time("capture", time.monotonic() - t)
            keep(result, "initial", {"capture": time.monotonic() - t})
            captured()
        if with_semantics and not step(
            lambda: manager.wait_fused(n_init, config.plan_timeout_s, key="semantic_frames_fused")
        ):
            log_sink(
                f"[mission_manager] no semantic maps for the initial views after "
                f"{config.plan_timeout_s:.0f} s; planning without them"
            )
        if not step(lambda: manager.wait_fused(n_init, config.fuse_timeout_s)):
            log_sink(
                f"[mission_manager] the planner has not fused all {n_init} initial views after "
                f"{config.fuse_timeout_s:.0f} s; planning with what it has"
            )
        initial_grid = run_dir / rundir.GRID_INITIAL_FILE
        if manager.latest_grid is not None and not initial_grid.exists():
            rundir.write_grid(initial_grid, _grid(manager.latest_grid))

        planned = len(frames) - n_init
        refused = 0
        to_plan = budget - n_init
        while planned < to_plan:
            t = time.monotonic()
            count = 1 if config.mode == "closed_loop" else to_plan - planned
            poses = step(lambda c=count: manager.plan(frames[-1], c, config.plan_timeout_s))
            plan_s = time.monotonic() - t
            add_time("plan", plan_s)
            launcher.check()
            if not poses:
                log_sink(
                    f"[mission_manager] the planner returned no view with {to_plan - planned} left; stopping early"
                )
                break
            for T in poses[: to_plan - planned]:
                t = time.monotonic()
                stamp = manager.clock()  # kept if the capture is repeated
                result = step(lambda T=T, s=stamp: manager.capture(T, config.capture_timeout_s, s))
                add_time("capture", time.monotonic() - t)
                if isinstance(result, str):
                    refused += 1
                    log_sink(f"[mission_manager] the camera refused a planned view: {result}")
                    if refused > budget:
                        raise EpisodeError(
                            "the camera refused more planned views than the budget; stopping"
                        )
                    continue
                planned += 1
                keep(
                    result,
                    "planned",
                    {"plan": plan_s / len(poses), "capture": time.monotonic() - t},
                )
                captured()
        if not step(lambda: all_fused(config.fuse_timeout_s)):
            log_sink(
                f"[mission_manager] the planner has fused "
                f"{manager.planner_status.get('frames_fused', 0)} of {len(frames)} frames at the end"
            )
        # Let the bag catch up with what the planner and perception published for the last frame.
        perception_depth = manager.resolve_topic_name(PERCEPTION_DEPTH_TOPIC)
        step(
            lambda: manager.wait_until(
                lambda: manager.received.get(perception_depth, 0) >= len(frames), 10.0
            )
        )
        if manager.estimates is not None:
            _attach_estimates(run_dir, frames, manager, log_sink)
        if manager.latest_grid is not None:
            rundir.write_grid(run_dir / rundir.GRID_FINAL_FILE, _grid(manager.latest_grid))
        add_time("episode_total", time.monotonic() - t0)
        save_episode()
    except NodeDied as err:
        save_episode()
        raise EpisodeError(
            f"{err}\nkept {len(frames)} captured views in {run_dir}; continue with --resume {run_dir}"
        ) from err
    except (TimeoutError, EpisodeError) as err:
        save_episode()
        raise EpisodeError(
            f"{err}\nkept {len(frames)} captured views in {run_dir}; continue with --resume {run_dir}"
        ) from err
    except OSError as err:  # the disk filled up or went away mid-run
        raise EpisodeError(
            f"writing the run directory failed: {err}\nkept {len(frames)} captured views in "
            f"{run_dir}; free space, then continue with --resume {run_dir}"
        ) from err
    finally:
        launcher.stop()
        executor.shutdown()
        spinner.join(timeout=2.0)
        manager.destroy_node()
        context.try_shutdown()
        try:
            if recorder is not None:
                recorder.close()
            save_episode()
        except OSError as err:  # a full disk: what was written before stays readable
            log_sink(f"[mission_manager] could not write the run directory at the end: {err}")
        lease.release()
        log_file.close()
    return run_dir


def _attach_estimates(
    run_dir: Path, frames: list[Frame], manager: MissionManager, log_sink: Callable[[str], None]
) -> None:
    """Rewrite each frame file with the depth and confidence perception published for it."""
    estimates = manager.estimates_received()
    for index, frame in enumerate(frames):
        got = estimates.get(frame.stamp_ns, {})
        if frame.estimated_depth is not None and "depth" not in got:
            continue  # kept from before a resume
        if "depth" not in got:
            log_sink(f"[mission_manager] no perception depth for view {index}; TSDF will refuse it")
            continue
        rundir.write_frame(
            run_dir,
            index,
            *frame,
            stamp_ns=frame.stamp_ns,
            estimated_depth=got["depth"],
            confidence=got.get("confidence"),
        )


def _spin(executor: SingleThreadedExecutor) -> None:
    try:
        executor.spin()
    except Exception:  # the context was shut down under it: the episode is over
        pass


def _grid(cdr: bytes) -> np.ndarray:
    return codecs.msg_to_pointcloud(msgs.deserialize(cdr, "sensor_msgs/msg/PointCloud2"))


def episode_summary(run_dir: Path) -> dict:
    data = json.loads((Path(run_dir) / rundir.EPISODE_FILE).read_text())
    return {k: data[k] for k in ("scene", "policy", "seed", "budget", "mode")} | {
        "views": len(data["views"])
    }
