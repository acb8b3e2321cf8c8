"""The mission manager of `area3d run`: the runner's own node on the graph.

It sends the camera its goals and collects each frame, records every topic of the graph into the
bag, calls the planner's next-best-view service, replays saved frames onto the camera topics (for
`--resume` and after a restart), and tracks the graph's readers so that it knows when a restarted
node's new process is up. Topics: `area3d_msgs_py/topics.py`.

This module is the node: its wiring, callbacks, discovery queries, publishing, and its calls over
the graph (a capture, a plan, a reset, a map file). The logic over what the callbacks collect (the
restarts caught up with, the readers of new processes, the waits on the planner's status, replays)
is its base `mission_sync.GraphSync`.
"""

from __future__ import annotations

import json
import re
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from rcl_interfaces.srv import GetParameters
from rclpy.event_handler import PublisherEventCallbacks
from rclpy.node import Node

from area3d_bringup.episode_config import GraphInUse
from area3d_bringup.launcher import Launcher, NodeDied
from area3d_bringup.mission_sync import (
    CAMERA_PARTS,
    EXPECTED_READERS,
    READS,
    RUNNER_TOPICS,
    GraphSync,
    NodeRespawned,
)
from area3d_bringup.recorder import BagRecorder
from area3d_eval.rundir import Frame
from area3d_msgs_py import codecs, msgs, qos, services, topics
from area3d_msgs_py.lens import camera_undistortion
from area3d_msgs_py.topics import Service, Topic

NAME = topics.MISSION_MANAGER
# On a domain in use already, the nodes of the graph a run starts are looked for this long, and
# those found must answer a parameter request within ANSWER_WAIT_S to count as running.
DISCOVERY_WAIT_S = 3.0
ANSWER_WAIT_S = 5.0
# The simulated camera's fixed frame: goals, replayed poses and requests are in it.
WORLD_FRAME = "world"
# The grid is published after every fusion (in a burst, at most once a second and after the
# last); the mission manager's reader keeps a backlog of them.
GRID_READER_DEPTH = 100
#: what the bag holds besides the camera topics and the goals: {topic: reader history depth}.
#: Perception's and semantics' per-frame outputs are read transient local, as their writers
#: publish them: a reader that the writer matches only after a frame's output went out (its
#: discovery of this process finished late) still gets it, and the bag and the replay's count
#: of what perception answered miss nothing.
GRAPH_OUTPUTS: dict[Topic, int] = {
    topics.CAMERA_STATUS: qos.FRAME_DEPTH,
    topics.PERCEPTION_DEPTH: qos.FRAME_DEPTH,
    topics.PERCEPTION_CONFIDENCE: qos.FRAME_DEPTH,
    topics.PERCEPTION_WEIGHT: qos.FRAME_DEPTH,
    topics.SEMANTIC_REGIONS: qos.FRAME_DEPTH,
    topics.SEMANTIC_WEIGHT: qos.FRAME_DEPTH,
    topics.SEMANTIC_UNCERTAINTY: qos.FRAME_DEPTH,
    topics.UNCERTAINTY_GRID: GRID_READER_DEPTH,
    topics.NEXT_VIEWS: qos.FRAME_DEPTH,
    topics.PLANNER_STATUS: qos.FRAME_DEPTH,
    topics.RECONSTRUCTION_STATUS: qos.FRAME_DEPTH,
}
#: the outputs stamped with the frame they come from: those of a frame this episode did not
#: capture or replay (a running graph's transient-local history of an earlier episode, the empty
#: grid of a reset) are neither recorded nor counted
FRAME_OUTPUTS = (
    topics.PERCEPTION_DEPTH, topics.PERCEPTION_CONFIDENCE, topics.PERCEPTION_WEIGHT,
    topics.SEMANTIC_WEIGHT, topics.SEMANTIC_UNCERTAINTY, topics.UNCERTAINTY_GRID,
)  # fmt: skip
#: what episode.json keeps of the semantic regions: where they came from
SEMANTICS_KEYS = ("backend", "fallback_used", "error")
#: perception's outputs a run directory keeps per frame (`area3d_eval.rundir.attach_estimates`)
ESTIMATE_KEYS = {
    topics.PERCEPTION_DEPTH: "depth",
    topics.PERCEPTION_CONFIDENCE: "confidence",
    topics.PERCEPTION_WEIGHT: "weight",
}
# After the camera was restarted, a goal whose frame has not arrived whole is sent again this often
# (the camera answers a repeated stamp with the same frame; the graph fuses each stamp once).
CAPTURE_RESEND_S = 5.0


class MissionManager(GraphSync, Node):
    """The runner's node: sends goals, collects frames, records the graph, calls the planner."""

    def __init__(
        self,
        recorder: BagRecorder | None,
        launcher: Launcher | None = None,
        clock: Callable[[], int] | None = None,
        keep_estimates: bool = False,
        **kwargs: Any,
    ):
        super().__init__(NAME, **kwargs)
        # {stamp: {"depth" | "confidence" | "weight": image}} of perception's outputs, when the
        # run keeps them
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
        self.reconstruction_status: dict = {}
        self.semantics: dict = {}  # the last regions' backend, fallback and error
        self.stamps: set[int] = set()  # the frames this episode captured or replayed
        self.latest_grid: bytes | None = None
        self.received: dict[str, int] = {}
        # what graph nodes read: the goals, and the camera topics for replayed frames
        self.runner_pubs = {
            key: self.create_publisher(
                topic.msg_type, topic.name, topic.qos(), event_callbacks=self._on_match(key)
            )
            for key, topic in RUNNER_TOPICS.items()
        }
        self.goal_pub = self.runner_pubs["goal"]
        for key in CAMERA_PARTS:
            self._listen(RUNNER_TOPICS[key], None, self._on_part(key))
        for topic, depth in GRAPH_OUTPUTS.items():
            self._listen(topic, depth, self._on_output(topic))
        self._listen(topics.TF, None, None)  # the graph's TF, recorded as the camera sent it
        self._listen(topics.TF_STATIC, None, None)
        self.plan_message = ""  # why the planner's last answer had no view
        self.client = self.create_client(topics.SELECT_VIEWS.srv_type, topics.SELECT_VIEWS.name)

    # -- callbacks (executor thread) ---------------------------------------------------------
    def _on_match(self, key: str) -> PublisherEventCallbacks:
        def matched(status) -> None:
            with self._lock:
                self.matched_total[key] = status.total_count

        return PublisherEventCallbacks(matched=matched)

    def _listen(self, topic: Topic, depth: int | None, handle) -> None:
        """Record `topic` (read with history `depth`, None: the topic's) and pass each message to
        `handle(msg, cdr)` under the lock."""
        type_name = topic.type_name
        resolved = self.resolve_topic_name(topic.name)
        of_frames = topic in FRAME_OUTPUTS

        def callback(cdr: bytes) -> None:
            msg = msgs.deserialize(cdr, type_name)
            stamp = codecs.stamp_to_ns(msg.header.stamp) if hasattr(msg, "header") else 0
            if of_frames and stamp not in self.stamps:
                return  # not of this episode
            self.record(resolved, type_name, stamp, cdr)
            with self._lock:
                self.received[resolved] = self.received.get(resolved, 0) + 1
                if handle is not None:
                    handle(msg, cdr)
                self._lock.notify_all()

        self.create_subscription(topic.msg_type, topic.name, callback, topic.qos(depth), raw=True)

    def record(self, topic: str, type_name: str, stamp_ns: int, cdr: bytes) -> None:
        if self.recorder is not None:
            stamp = stamp_ns or self.get_clock().now().nanoseconds
            self.recorder.write(topic, type_name, stamp, cdr)

    def _on_part(self, key: str) -> Callable[[Any, bytes], None]:
        def handle(msg: Any, cdr: bytes) -> None:
            stamp = codecs.stamp_to_ns(msg.header.stamp)
            self._parts.setdefault(stamp, {})[key] = msg

        return handle

    def _on_output(self, topic: Topic) -> Callable[[Any, bytes], None]:
        def handle(msg: Any, cdr: bytes) -> None:
            if topic in ESTIMATE_KEYS:
                stamp = codecs.stamp_to_ns(msg.header.stamp)
                key = ESTIMATE_KEYS[topic]
                if key == "depth":
                    self.perceived[stamp] = self.perceived.get(stamp, 0) + 1
                if self.estimates is not None:
                    self.estimates.setdefault(stamp, {})[key] = codecs.msg_to_image(msg)
            elif topic == topics.CAMERA_STATUS:
                status = json.loads(msg.data)
                self._status[int(status.get("stamp_ns", 0))] = status
            elif topic == topics.PLANNER_STATUS:
                self.planner_status = json.loads(msg.data)
            elif topic == topics.RECONSTRUCTION_STATUS:
                self.reconstruction_status = json.loads(msg.data)
            elif topic == topics.SEMANTIC_REGIONS:
                regions = json.loads(msg.data)
                self.semantics = {k: regions.get(k) for k in SEMANTICS_KEYS}
            elif topic == topics.UNCERTAINTY_GRID:
                self.latest_grid = cdr

        return handle

    # -- discovery -------------------------------------------------------------------------------
    def refuse_a_running_graph(self, names: set[str], domain_id: int) -> None:
        """Refuse (GraphInUse) when nodes of `names` run already in this node's namespace on its
        domain, looked for up to DISCOVERY_WAIT_S (discovery takes a moment): another graph,
        which a run would drive in place of the one it starts (its planner answers first)."""
        deadline = time.monotonic() + DISCOVERY_WAIT_S
        clash: list[str] = []
        settled = deadline  # until one is found; then until none more came for 0.5 s
        while time.monotonic() < min(settled, deadline + 0.5):
            if len(found := self._running(names)) > len(clash):
                clash, settled = found, time.monotonic() + 0.5
            time.sleep(0.1)
        clash = self._answering(clash, ANSWER_WAIT_S)  # none found: nothing asked
        if clash:
            raise GraphInUse(
                f"nodes {', '.join(clash)} run already on ROS_DOMAIN_ID={domain_id} in namespace "
                f"{self.get_namespace()}: this run would drive them, not its own graph. Stop "
                "them; drive them on purpose with --nodes none; or give this run a --namespace, "
                "--domain-id or no ROS_DOMAIN_ID (a free domain is picked)"
            )

    def _running(self, names: set[str]) -> list[str]:
        ns = self.get_namespace()
        found = {n for n, space in self.get_node_names_and_namespaces() if space == ns}
        return sorted(found & set(names))

    def _answering(self, names: list[str], wait_s: float) -> list[str]:
        """Of the nodes `names` (in this node's namespace), those that answer a parameter request
        within `wait_s`: discovery still lists a node whose process was killed (until its lease
        ends), and one created and never spun; neither answers, and neither would plan."""
        ns = self.get_namespace().rstrip("/")
        clients = {n: self.create_client(GetParameters, f"{ns}/{n}/get_parameters") for n in names}
        deadline = time.monotonic() + wait_s
        futures = {}
        for name, client in clients.items():  # a request sent before the match would be lost
            if client.wait_for_service(timeout_sec=max(deadline - time.monotonic(), 0.0)):
                futures[name] = client.call_async(GetParameters.Request(names=["use_sim_time"]))
        while not all(f.done() for f in futures.values()) and time.monotonic() < deadline:
            time.sleep(0.05)
        for client in clients.values():
            self.destroy_client(client)
        return sorted(n for n, f in futures.items() if f.done() and f.result() is not None)

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

    def _has_graph_readers(self, key: str) -> bool:
        pub = self.runner_pubs[key]
        infos = self.get_subscriptions_info_by_topic(pub.topic_name)
        readers = {info.node_name for info in infos}
        return set(RUNNER_TOPICS[key].readers) <= readers and pub.get_subscription_count() >= max(
            EXPECTED_READERS[key], len(infos)
        )

    # -- calls over the graph (main thread) ------------------------------------------------------
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
        self.stamps.add(stamp)  # before the goal: perception may answer before the camera's parts
        goal = msgs.PoseStamped(
            header=codecs.header(stamp, WORLD_FRAME), pose=codecs.matrix_to_pose(T_world_cam)
        )
        self.record(
            self.resolve_topic_name(topics.GOAL.name), topics.GOAL.type_name, stamp,
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
                if len(parts) == len(CAMERA_PARTS):
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
        info = parts["info"]
        K, width, height = codecs.camera_info_to_intrinsics(info)
        rgb, depth = codecs.msg_to_image(parts["color"]), codecs.msg_to_image(parts["depth"])
        # a camera with lens distortion: the frame is kept as the graph sees it, undistorted
        # into k (`area3d_msgs_py.lens`, as perception and semantics remap it), so that the
        # evaluation and a replay read a pinhole camera's
        lens, _ = camera_undistortion(K, width, height, info.distortion_model, info.d)
        if lens is not None and lens.fits(rgb) and lens.fits(depth):
            rgb, depth = lens.color(rgb), lens.depth(depth)
        return Frame(
            rgb=rgb,
            depth=depth,
            K=K,
            T_world_cam=codecs.pose_to_matrix(parts["pose"].pose),
            stamp_ns=stamp,
        )

    def replay(self, frame: Frame) -> None:
        """Publish a saved frame on the camera topics, as the camera did when it was captured."""
        self.stamps.add(frame.stamp_ns)
        h, w = frame.depth.shape
        header_args = (frame.stamp_ns, "camera_optical_frame")
        pubs = self.runner_pubs
        pubs["color"].publish(codecs.image_to_msg(frame.rgb, "rgb8", *header_args))
        pubs["depth"].publish(codecs.image_to_msg(frame.depth, "32FC1", *header_args))
        pubs["info"].publish(codecs.intrinsics_to_camera_info(frame.K, w, h, *header_args))
        pubs["pose"].publish(
            msgs.PoseStamped(
                header=codecs.header(frame.stamp_ns, WORLD_FRAME),
                pose=codecs.matrix_to_pose(frame.T_world_cam),
            )
        )

    def reset(self, service: Service, timeout_s: float) -> str:
        """Call a node's reset service (std_srvs/Trigger: `topics.CAMERA_RESET`,
        `topics.PLANNER_RESET`, `topics.SEMANTICS_RESET`) and return its answer's message; a
        planner's status is awaited until it shows the reset. TimeoutError when the service does
        not appear or answer within `timeout_s`, RuntimeError when it answers that the reset
        failed."""
        client = self.create_client(service.srv_type, service.name)  # once per episode
        try:
            if not client.wait_for_service(timeout_sec=timeout_s):
                raise TimeoutError(f"no service {service.name} within {timeout_s:.0f} s")
            # asked again while no reply comes (a server that has just appeared may lose the
            # reply): a second reset before the episode's first capture changes nothing
            answer = services.call(client, msgs.Trigger.Request(), timeout_s)
        finally:
            self.destroy_client(client)
        if not answer.success:
            raise RuntimeError(f"{service.name}: {answer.message}")
        if service is topics.PLANNER_RESET:  # its status after the reset: "(reset N)" or empty
            count = re.search(r"\(reset (\d+)\)", answer.message)
            if not self.wait_until(
                lambda: (
                    int(self.planner_status.get("resets", 0)) >= int(count.group(1))
                    if count
                    else self.planner_status.get("frames_fused") == 0
                ),
                timeout_s,
            ):
                raise TimeoutError(f"no planner status after the reset within {timeout_s:.0f} s")
        return answer.message

    def map_file(self, service: Service, path: Path, timeout_s: float) -> str:
        """Call a MapFile service (`topics.PLANNER_SAVE_MAP`, `RECONSTRUCTION_EXPORT_MESH`, ...)
        with `path`; its answer's message. TimeoutError when the service does not appear or
        answer within `timeout_s`, RuntimeError when it refuses."""
        client = self.create_client(service.srv_type, service.name)
        try:
            if not client.wait_for_service(timeout_sec=timeout_s):
                raise TimeoutError(f"no service {service.name} within {timeout_s:.0f} s")
            request = service.srv_type.Request(path=str(path))
            answer = services.call(client, request, timeout_s)
        finally:
            self.destroy_client(client)
        if not answer.success:
            raise RuntimeError(f"{service.name}: {answer.message}")
        return answer.message

    def plan(self, current: Frame, count: int, timeout_s: float) -> list[np.ndarray]:
        """Ask the planner for `count` views (0 = what the budget allows) from the current pose
        (area3d_interfaces/NextBestView); none, with the planner's reason in `plan_message`,
        when it has none."""
        request = codecs.view_request_to_msg(
            int(count), current.T_world_cam, current.stamp_ns, WORLD_FRAME
        )
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
                raise TimeoutError(
                    f"no answer from {topics.SELECT_VIEWS.name} within {timeout_s:.0f} s"
                )
        answer = codecs.msg_to_view_answer(future.result())
        self.plan_message = answer.message
        return list(answer.views) if answer.success else []
