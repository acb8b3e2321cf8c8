"""The planner node: fuses perception (+ semantics) frames and serves next-best-view requests.

Subscribes area3d/perception/depth, area3d/perception/confidence, area3d/camera/pose and
area3d/camera/camera_info (paired by stamp), area3d/semantics/uncertainty. Publishes the latched
area3d/planner/uncertainty_grid (after every fused frame; during a backlog at most every
grid_period_s), area3d/planner/status and
area3d/planner/next_views (and their camera frustums on area3d/planner/view_markers); serves
area3d/planner/next_best_view (nav_msgs/srv/GetPlan). Names are
relative: `__ns` moves them all. The region of interest and workspace are parameters: the planner
knows only what a robot knows, never the simulator's scene.
"""

from __future__ import annotations

import json
import queue
import threading
import time
import traceback
from collections import OrderedDict, deque
from collections.abc import Sequence
from dataclasses import fields
from typing import Any

import numpy as np
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.executors import MultiThreadedExecutor
from rclpy.node import Node
from visualization_msgs.msg import MarkerArray

from area3d_msgs_py import codecs, msgs, qos
from area3d_msgs_py.errors import InputError
from area3d_msgs_py.guard import Rejections, guarded, reject
from area3d_msgs_py.inputs import (
    FLOAT_ENCODINGS,
    check_depth_values,
    check_frame_id,
    check_stamp,
    check_unit_range,
    decode_camera_info,
    decode_image,
)
from area3d_msgs_py.lifecycle import PublishGate, exit_process, run_node
from area3d_msgs_py.parameters import (
    MAX_STAMP_AHEAD_PARAM,
    WORLD_FRAME_PARAM,
    Param,
    declare_parameters,
    report_unknown_parameters,
)
from area3d_msgs_py.status import status_topic
from area3d_perception.frame_sync import StampSync
from area3d_planner.cloud import grid_to_msg
from area3d_planner.fusion import GEOMETRIC_RULES, NO_RETURN_RULES
from area3d_planner.greedy import DECAY_REGIONS
from area3d_planner.markers import view_markers
from area3d_planner.policies import POLICIES
from area3d_planner.server import LEVELS, MODES, NextBestViewServer, PlannerConfig, PlanRequest

DEPTH_TOPIC = "area3d/perception/depth"
CONFIDENCE_TOPIC = "area3d/perception/confidence"
POSE_TOPIC = "area3d/camera/pose"
INFO_TOPIC = "area3d/camera/camera_info"
SEMANTIC_TOPIC = "area3d/semantics/uncertainty"
GRID_TOPIC = "area3d/planner/uncertainty_grid"
STATUS_TOPIC = status_topic("planner")
VIEWS_TOPIC = "area3d/planner/next_views"
MARKERS_TOPIC = "area3d/planner/view_markers"
NBV_SERVICE = "area3d/planner/next_best_view"
CAMERA_INFO_CACHE = 64
POSES_PENDING = 2048
# Complete frames held while no camera info has arrived yet (oldest dropped beyond this).
MAX_FRAMES_WITHOUT_INFO = 64
# Service requests and frame callbacks run on separate threads: a request waits for the frame it
# names to be fused, which needs the frame callbacks to keep running.
EXECUTOR_THREADS = 3
# Whole frames waiting for the fusion worker at most (640x480 depth + confidence: 2.4 MB each).
FUSION_BACKLOG = 128
STATUS_AFTER_REQUEST_S = 0.05  # the status follows a request's answer this much later, seconds
# On shutdown a mask rebuild in flight gets this long to finish; the node exits regardless, so
# Ctrl-C stops it within ROS 2's usual couple of seconds (issue 13: within 2 s).
CLOSE_WAIT_S = 1.0


def _xyz(value: Any) -> str | None:
    return None if len(value) == 3 else "3 numbers [x, y, z] in metres"


def _positive(value: Any) -> str | None:
    return None if len(value) > 0 and min(value) > 0 else "one or more numbers > 0"


def _config_param(name: str, default: Any) -> Param:
    description = f"PlannerConfig.{name} (area3d_planner/server.py)"
    if name == "policy":
        return Param(name, default, "next-best-view policy", choices=tuple(sorted(POLICIES)))
    if name == "mode":
        return Param(
            name,
            default,
            "closed_loop: re-plan after each view; batch: all views at once",
            choices=MODES,
        )
    choices = {
        "level": LEVELS,
        "decay": DECAY_REGIONS,
        "geometric_rule": GEOMETRIC_RULES,
        "no_return": NO_RETURN_RULES,
    }
    if name in choices:
        return Param(name, default, description, choices=choices[name])
    if name == "shell_scales":
        return Param(name, tuple(float(v) for v in default), description, check=_positive)
    if name == "gamma":  # -1: the level's (paper: 0.01 object, 0.005 scene level)
        return Param(name, float(default), description + "; < 0 = the level's", range=(-1.0, 1e6))
    if isinstance(default, tuple):
        return Param(name, tuple(float(v) for v in default), description + ", metres", check=_xyz)
    if isinstance(default, bool) or isinstance(default, str):
        return Param(name, default, description)
    if isinstance(default, int):
        return Param(name, default, description, range=(0, 2**31 - 1))
    return Param(name, float(default), description, range=(0.0, 1e6))


PARAMS = (
    *(_config_param(f.name, getattr(PlannerConfig, f.name)) for f in fields(PlannerConfig)),
    Param(
        "sync_timeout_s",
        5.0,
        "how long a request waits for the frame it names to be fused, seconds",
        read_only=False,
        range=(0.0, 600.0),
    ),
    Param("eager_cache", True, "rebuild seeds and visibility masks right after each fused frame"),
    Param(
        "refresh_interval_s",
        0.5,
        "eager rebuilds start at most this often unless a request waits for one, seconds",
        range=(0.0, 60.0),
    ),
    Param(
        "mask_lag_s",
        0.0,
        "a request plans from masks built up to this long (in capture time) before its frame "
        "instead of waiting for a rebuild; 0 = masks that cover its frame (a streaming camera: "
        "0.5), seconds",
        range=(0.0, 60.0),
    ),
    Param(
        "grid_period_s",
        1.0,
        "while frames wait for fusion, the grid goes out at most this often (it goes out after "
        "every frame otherwise, and once fusion has caught up), seconds",
        range=(0.0, 3600.0),
    ),
    Param(
        "rebuild_nice",
        0,
        "the background rebuild runs this much nicer (lower CPU priority) than the node, so "
        "fusion comes first (a streaming camera with mask_lag_s > 0: 10); 0 = the same",
        range=(0, 19),
    ),
    # Perception's output for a frame can trail the camera's pose by seconds (first frames, a
    # feed-forward model on CPU), so parts wait this long for their partners.
    Param(
        "sync_max_age_s",
        60.0,
        "parts of a frame wait this long for their partners, seconds",
        range=(0.0, 3600.0),
    ),
    Param(
        "view_marker_range",
        0.0,
        "depth of the camera frustums drawn on view_markers, metres; 0 = a quarter of the "
        "region of interest's diagonal",
        range=(0.0, 1000.0),
    ),
    WORLD_FRAME_PARAM,
    MAX_STAMP_AHEAD_PARAM,
)


class PlannerNode(Node):
    """Wires parameters, subscriptions, publishers and the service around `NextBestViewServer`."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__("planner", **kwargs)
        p = declare_parameters(self, PARAMS)
        report_unknown_parameters(self)
        config = PlannerConfig(**{f.name: p[f.name] for f in fields(PlannerConfig)})
        self.gate = PublishGate()  # the rebuild worker publishes only while the node runs
        # Rebuild seeds and visibility masks in a worker right after each fused frame, so that a
        # request only waits for a rebuild in flight and then plans from the cached masks.
        self.server = NextBestViewServer(
            config,
            background=p["eager_cache"],
            on_refresh=self._on_refresh,
            refresh_interval_s=p["refresh_interval_s"],
            mask_lag_s=p["mask_lag_s"],
            rebuild_nice=p["rebuild_nice"],
        )
        self.sync = StampSync(
            ("depth", "confidence", "pose"),
            max_age_ns=int(p["sync_max_age_s"] * 1e9),
            # the camera's poses arrive ahead of perception's images, which trail by the
            # perception backlog: a minute of poses at 30 Hz may wait (they are small)
            pending_caps={"pose": POSES_PENDING},
        )
        self.camera_info: OrderedDict[int, np.ndarray] = OrderedDict()
        self.latest_K: np.ndarray | None = None
        self.waiting: deque[tuple[int, dict]] = deque(maxlen=MAX_FRAMES_WITHOUT_INFO)
        self.world_frame = p["world_frame"]
        roi = np.subtract(config.roi_max, config.roi_min)
        self.marker_range = p["view_marker_range"] or 0.25 * float(np.linalg.norm(roi))
        self.max_stamp_ahead_s = p["max_stamp_ahead_s"]
        # a rejection is announced by the status that follows requests (created below)
        self.rejections = Rejections(on_count=lambda: self._status_after_request.reset())
        self.dropped = 0
        self._fusion_queue: queue.Queue = queue.Queue(FUSION_BACKLOG)  # whole frames, in order
        self.backlog_dropped = 0
        self.grid_period_s = p["grid_period_s"]
        self._grid_sent = -np.inf  # time.monotonic() of the last grid published by fusion
        self._fusion_worker = threading.Thread(
            target=self._fusion_loop, name="planner-fusion", daemon=True
        )
        self._fusion_worker.start()
        self.last_fused_age_s: float | None = None  # age of the last frame fused, seconds
        # the last fused frame's age when its last part arrived (it entered the fusion queue),
        # and how long its fusion took, seconds: where a frame's age comes from
        self.last_paired_age_s: float | None = None
        self.last_fusion_s: float | None = None

        self.grid_pub = self.create_publisher(msgs.PointCloud2, GRID_TOPIC, qos.latched())
        self.status_pub = self.create_publisher(msgs.String, STATUS_TOPIC, qos.reliable(50))
        self.views_pub = self.create_publisher(msgs.Path, VIEWS_TOPIC, qos.reliable())
        self.markers_pub = self.create_publisher(MarkerArray, MARKERS_TOPIC, qos.latched())
        frames = MutuallyExclusiveCallbackGroup()
        # perception's and semantics' outputs are transient local (a late match still gets them);
        # the camera's topics are volatile, as a camera driver publishes them
        for msg_type, topic, callback, profile in (
            (msgs.Image, DEPTH_TOPIC, lambda m: self._part("depth", m), qos.graph_frames()),
            (
                msgs.Image,
                CONFIDENCE_TOPIC,
                lambda m: self._part("confidence", m),
                qos.graph_frames(),
            ),
            # the camera's small per-frame messages queue deep: they run ahead of perception's
            # images, and a reader queue that overflows loses the frame for good
            (
                msgs.PoseStamped,
                POSE_TOPIC,
                lambda m: self._part("pose", m),
                qos.reliable(POSES_PENDING),
            ),
            (msgs.CameraInfo, INFO_TOPIC, self._on_camera_info, qos.reliable(POSES_PENDING)),
            (msgs.Image, SEMANTIC_TOPIC, self._on_semantic, qos.graph_frames()),
        ):
            self.create_subscription(
                msg_type,
                topic,
                guarded(self, callback, topic, self.rejections),
                profile,
                callback_group=frames,
            )
        self.create_service(
            msgs.GetPlan,
            NBV_SERVICE,
            self._on_request,
            callback_group=MutuallyExclusiveCallbackGroup(),
        )
        # The status after a request goes out a moment after the answer, never just before it: a
        # client that also listens to the status (a mission manager, the runner) would otherwise
        # see the answer late (measured: 0.1-1.3 s round trips instead of 7 ms under rclpy).
        self._status_after_request = self.create_timer(
            STATUS_AFTER_REQUEST_S, self._publish_status_after_request
        )
        self._status_after_request.cancel()
        self.get_logger().info(
            f"planner ready: policy={config.policy} mode={config.mode} "
            f"voxels={self.server.grid.spec.num_voxels}"
        )

    def destroy_node(self) -> None:
        self._stop_fusion(CLOSE_WAIT_S)
        self.server.close(CLOSE_WAIT_S)
        super().destroy_node()

    def _status(self) -> msgs.String:
        status = {
            **self.server.status(),
            "parts_dropped_unpaired": self.dropped,
            "frames_dropped_backlog": self.backlog_dropped,
            **{
                key: None if value is None else round(value, 4)
                for key, value in (
                    ("last_paired_age_s", self.last_paired_age_s),
                    ("last_fused_age_s", self.last_fused_age_s),
                    ("last_fusion_s", self.last_fusion_s),
                )
            },
            "rejected": self.rejections.snapshot(),
        }
        return msgs.String(data=json.dumps(status))

    def _stamp(self, msg) -> int:
        return check_stamp(msg, self.get_clock().now().nanoseconds, self.max_stamp_ahead_s)

    def _on_refresh(self) -> None:
        with self.gate as running:  # called by the rebuild worker too
            if running:
                self.status_pub.publish(self._status())

    def stop(self) -> None:
        """Before the executor stops: no more publishing from the rebuild and fusion workers, and
        a request waiting for a mask rebuild returns at once instead of holding the executor's
        shutdown."""
        self.gate.close()
        self._stop_fusion(0.0)
        self.server.close(0.0)

    def _stop_fusion(self, timeout_s: float) -> None:
        """Stop the fusion worker after the frame in flight (frames still queued are not fused)."""
        if not self._fusion_worker.is_alive():
            return
        try:
            self._fusion_queue.put(None, timeout=max(timeout_s, 0.1))
        except queue.Full:  # a full backlog: the worker ends at the closed gate anyway
            pass
        if self._fusion_worker is not threading.current_thread():
            self._fusion_worker.join(timeout_s)

    def _publish_status_after_request(self) -> None:
        self._status_after_request.cancel()
        self._on_refresh()

    def _on_camera_info(self, msg) -> None:
        stamp = self._stamp(msg)
        K, _, _ = decode_camera_info(msg)
        self.latest_K = K
        self.camera_info[stamp] = K
        while len(self.camera_info) > CAMERA_INFO_CACHE:
            self.camera_info.popitem(last=False)
        while self.waiting:
            stamp, frame = self.waiting.popleft()
            self._fuse(stamp, frame, self.camera_info.get(stamp, K))

    def _decode(self, key: str, msg) -> np.ndarray:
        if key == "pose":
            check_frame_id(msg, self.world_frame)
            return codecs.pose_to_matrix(msg.pose)
        check_frame_id(msg)
        image = decode_image(msg, FLOAT_ENCODINGS)
        if key == "depth":
            return check_depth_values(image)
        return check_unit_range(image, key)

    def _part(self, key: str, msg) -> None:
        stamp = self._stamp(msg)
        frame = self.sync.add(key, stamp, self._decode(key, msg))
        for dropped in self.sync.pop_dropped():
            self.dropped += 1
            self.get_logger().warning(
                f"{dropped.key} at stamp {dropped.stamp_ns} dropped: {dropped.reason}"
            )
        if frame is None:
            return
        K = self.camera_info.get(stamp, self.latest_K)
        if K is None:
            if not self.waiting:
                self.get_logger().warning(
                    f"no camera_info on {INFO_TOPIC} yet; holding frames until it arrives"
                )
            self.waiting.append((stamp, frame))  # topics arrive in any order
            return
        self._fuse(stamp, frame, K)

    def _fuse(self, stamp: int, frame: dict, K: np.ndarray) -> None:
        """Hand a whole frame to the fusion worker, in arrival order; a frame that finds
        FUSION_BACKLOG frames waiting is dropped, logged and counted (`frames_dropped_backlog`):
        a camera that outruns the planner for good must not grow its memory without bound."""
        try:
            self._fusion_queue.put_nowait((stamp, frame, K, self._now_ns()))
        except queue.Full:
            self.backlog_dropped += 1
            self.get_logger().warning(
                f"frame at stamp {stamp} dropped: {FUSION_BACKLOG} frames wait for fusion already "
                "(the camera outruns the planner)"
            )

    def _fusion_loop(self) -> None:
        """Fuse frames one at a time, off the executor.

        A frame's fusion takes tens of milliseconds; run in the frames' callback group it kept
        the group busy while the camera's next messages were ready, and rclpy's multi-threaded
        executor polls such a group in a loop that holds the GIL (profiled: 79 % of the node's
        GIL time during a 10 Hz soak). The callbacks now only decode and pair."""
        while True:
            item = self._fusion_queue.get()
            if item is None:
                return
            stamp, frame, K, queued_ns = item
            t0 = time.perf_counter()
            try:
                fused = self.server.add_frame(
                    stamp, frame["depth"], frame["confidence"], K, frame["pose"]
                )
            except InputError as exc:
                reject(self, self.rejections, f"frame at stamp {stamp}", exc, topic=DEPTH_TOPIC)
                continue
            except Exception:  # noqa: BLE001 - the node keeps fusing the frames that follow
                self.get_logger().error(
                    f"frame at stamp {stamp}: fusion failed, frame dropped:\n"
                    f"{traceback.format_exc()}"
                )
                self.rejections.count(DEPTH_TOPIC, "exception")
                continue
            with self.gate as running:
                if not running:
                    return
                if fused:
                    self.last_fusion_s = time.perf_counter() - t0
                    self.last_paired_age_s = (queued_ns - stamp) / 1e9
                    # how old the frame was once fused, by this node's clock (capture stamps only)
                    self.last_fused_age_s = (self._now_ns() - stamp) / 1e9
                    # the grid after every frame while fusion keeps up; during a backlog at most
                    # every grid_period_s, and always once it has caught up (the last state)
                    now = time.monotonic()
                    if self._fusion_queue.empty() or now - self._grid_sent >= self.grid_period_s:
                        self._grid_sent = now
                        self._publish_state(stamp)
                    else:
                        self.status_pub.publish(self._status())
                else:
                    self.get_logger().info(
                        f"frame {stamp} is fused already; the repeat changes nothing"
                    )

    def _on_semantic(self, msg) -> None:
        stamp = self._stamp(msg)
        check_frame_id(msg)
        u_sem = check_unit_range(decode_image(msg, FLOAT_ENCODINGS), "semantic uncertainty")
        if self.server.add_semantic(stamp, u_sem):
            self._publish_state(stamp)

    def _publish_state(self, stamp_ns: int) -> None:
        self.grid_pub.publish(grid_to_msg(self.server.grid, stamp_ns, "world"))
        self.status_pub.publish(self._status())

    def _on_request(self, request: msgs.GetPlan_Request, response: msgs.GetPlan_Response):
        try:
            response.plan = self._plan(request)
        except Exception as exc:  # an empty plan, and the node keeps serving
            self.get_logger().error(f"next_best_view: request failed: {exc}")
            response.plan = msgs.Path(header=codecs.header(self._now_ns(), "world"))
        return response

    def _now_ns(self) -> int:
        return self.get_clock().now().nanoseconds

    def _plan(self, request: msgs.GetPlan_Request) -> msgs.Path:
        log = self.get_logger()
        sync_timeout_s = self.get_parameter("sync_timeout_s").value
        stamp = codecs.stamp_to_ns(request.start.header.stamp)
        try:
            start = codecs.pose_to_matrix(request.start.pose)
        except ValueError as exc:
            log.warning(f"next_best_view: start pose rejected ({exc}); planning without a start")
            start = None
        t0 = time.perf_counter()
        if not self.server.wait_fused(stamp, sync_timeout_s):
            log.warning(
                f"next_best_view: frame {stamp} not fused after {sync_timeout_s} s; planning with what is fused"
            )
        t1 = time.perf_counter()
        poses, reason = self.server.plan(
            PlanRequest(start, stamp, int(round(request.goal.pose.position.x)))
        )
        # where the last request's time went, in the status (a mission manager's latency budget)
        self.server.last_request_s = {
            "wait_fused": round(t1 - t0, 4),
            **{k: round(v, 4) for k, v in self.server.last_plan_s.items()},
        }
        if reason:
            log.warning(f"next_best_view: {reason}")
        now = self._now_ns()
        hdr = codecs.header(now, "world")
        path = msgs.Path(
            header=hdr,
            poses=[
                msgs.PoseStamped(header=codecs.header(now, "world"), pose=codecs.matrix_to_pose(T))
                for T in poses
            ],
        )
        self.views_pub.publish(path)
        c = self.server.config
        self.markers_pub.publish(
            view_markers(
                poses, self.world_frame, now, c.hfov_deg, c.width, c.height, self.marker_range
            )
        )
        self._status_after_request.reset()
        return path


def main(args: Sequence[str] | None = None) -> int:
    return run_node(
        PlannerNode,
        "planner",
        args,
        executor=lambda: MultiThreadedExecutor(num_threads=EXECUTOR_THREADS),
        on_stop=lambda node: node.stop(),
    )


if __name__ == "__main__":
    exit_process(main())
