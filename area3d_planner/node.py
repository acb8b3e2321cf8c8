"""The planner node: fuses perception (+ semantics) frames and serves next-best-view requests.

Subscribes area3d/perception/depth, area3d/perception/confidence, area3d/camera/camera_info
and the camera pose of its `pose_source` (area3d/camera/pose paired by stamp, or TF or odometry
interpolated to the frame's stamp: `area3d_msgs_py/pose_inputs.py`), area3d/semantics/uncertainty.
Publishes, in `world_frame`, the latched area3d/planner/uncertainty_grid (after every fused frame;
during a backlog at most every grid_period_s) and with every grid the latched
area3d/planner/hard_regions (HardRegionArray) and their boxes on area3d/planner/hard_region_markers,
area3d/planner/status and area3d/planner/next_views (and their camera frustums on
area3d/planner/view_markers); serves area3d/planner/select_views
(area3d_interfaces/srv/NextBestView), area3d/planner/next_best_view (nav_msgs/srv/GetPlan), and
save_map / load_map (area3d_interfaces/srv/MapFile: the whole map, `map_io.py`) and reset.
Topics: `area3d_msgs_py/topics.py`; names are relative: `__ns` moves them all. The region of
interest and workspace are parameters: the planner knows only what a robot knows, never the
simulator's scene; the candidate views' camera is the one whose frames it fuses.
"""

from __future__ import annotations

import time
import traceback
from collections.abc import Sequence
from dataclasses import fields
from functools import partial
from typing import Any

import numpy as np
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.node import Node

from area3d_msgs_py import codecs, map_files, msgs, qos, topics
from area3d_msgs_py.errors import InputError
from area3d_msgs_py.guard import Rejections, reject, subscribe
from area3d_msgs_py.inputs import decode_frame_part
from area3d_msgs_py.keyframes import KeyframeConfig
from area3d_msgs_py.lifecycle import PublishGate, exit_process, run_node
from area3d_msgs_py.parameters import (
    CAMERA_QOS_PARAM,
    MAX_STAMP_AHEAD_PARAM,
    MIN_PAIRING_RATE_PARAM,
    SYNC_SLOP_PARAM,
    WORLD_FRAME_PARAM,
    Param,
    declare_parameters,
    params_of,
    report_unknown_parameters,
)
from area3d_msgs_py.pose_source import PoseSourceConfig
from area3d_msgs_py.posed_frames import PosedFrames
from area3d_msgs_py.scheduling import FrameWorker
from area3d_msgs_py.spinning import GuardedMultiThreadedExecutor
from area3d_msgs_py.status import StatusPublisher
from area3d_planner import map_io
from area3d_planner.config import PlannerConfig
from area3d_planner.markers import grid_messages, view_markers, views_path
from area3d_planner.requests import Plan, PlanRequest, check_request_stamp, get_plan_request
from area3d_planner.scheduler import PlannerScheduler, SchedulerConfig
from area3d_planner.server import NextBestViewServer

# Service requests and frame callbacks run on separate threads: a request waits for the frame it
# names to be fused, which needs the frame callbacks to keep running.
EXECUTOR_THREADS = 3
# On shutdown a mask rebuild in flight gets this long to finish; the node exits regardless, so
# Ctrl-C stops it within ROS 2's usual couple of seconds (issue 13: within 2 s).
CLOSE_WAIT_S = 1.0


PARAMS = (
    *params_of(PlannerConfig),
    Param(
        "sync_timeout_s",
        5.0,
        "how long a request waits for the map to hold the frame it names (fused, or with "
        "keyframes a frame as new or taken near its pose); then it is answered from what is "
        "fused and its message says how old that is, seconds",
        read_only=False,
        range=(0.0, 600.0),
    ),
    *params_of(SchedulerConfig),
    Param(
        "grid_period_s",
        1.0,
        "while frames wait for fusion, the grid goes out at most this often (it goes out after "
        "every frame otherwise, and once fusion has caught up), seconds",
        range=(0.0, 3600.0),
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
    Param(
        "hard_regions_max",
        100,
        "hard regions published at most, the largest (the status counts them all), regions",
        range=(0, 100000),
    ),
    SYNC_SLOP_PARAM,
    MIN_PAIRING_RATE_PARAM,
    *params_of(KeyframeConfig),
    WORLD_FRAME_PARAM,
    MAX_STAMP_AHEAD_PARAM,
    CAMERA_QOS_PARAM,
    *params_of(PoseSourceConfig),
)


class PlannerNode(Node):
    """Wires parameters, subscriptions, publishers and the services around the planner's core
    (`server.NextBestViewServer`) and its scheduling (`scheduler.PlannerScheduler`)."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__("planner", **kwargs)
        p = declare_parameters(self, PARAMS)
        report_unknown_parameters(self)
        config = config_from_parameters(p)
        # the rebuild worker publishes only while the node runs
        self.gate = PublishGate(self.context.ok)
        # Rebuild seeds and visibility masks in a worker right after each fused frame, so that a
        # request only waits for a rebuild in flight and then plans from the cached masks.
        scheduling = SchedulerConfig(**{f.name: p[f.name] for f in fields(SchedulerConfig)})
        self._new_map = lambda: PlannerScheduler(config, scheduling, self._on_refresh)
        self.scheduler = self._new_map()
        self.resets = 0  # area3d/planner/reset calls served
        # view requests answered (the status after one carries its `last_request_s`)
        self.requests_answered = 0
        self.min_pairing_rate = p["min_pairing_rate"]
        self.world_frame = p["world_frame"]
        roi = np.subtract(config.roi_max, config.roi_min)
        self.marker_range = p["view_marker_range"] or 0.25 * float(np.linalg.norm(roi))
        self.max_stamp_ahead_s = p["max_stamp_ahead_s"]
        self.hard_regions_max = p["hard_regions_max"]
        self.hard_regions = 0  # hard regions in the last grid published
        self.fusion_failures = 0  # frames whose fusion raised (not bad input: that is rejected)
        self.rebuild_failures_logged = 0
        # The status goes out after every fused frame and rebuild, and a moment after a request's
        # answer (never just before it: a client that also listens to the status, a mission
        # manager, would otherwise see the answer late: measured 0.1-1.3 s round trips instead of
        # 7 ms under rclpy). No heartbeat: each line is one event (the soak bench's ages).
        self.status = StatusPublisher(self, topics.PLANNER_STATUS, self._status, heartbeat_s=None)
        self.rejections = Rejections(on_count=self.status.changed)
        # whole frames are fused in arrival order by a worker thread, off the executor
        self.fusion = FrameWorker(
            self._fuse_frame,
            self._on_fused,
            self._on_fusion_failed,
            "planner-fusion",
            publish_period_s=p["grid_period_s"],
            now_ns=self._now_ns,
        )

        self.grid_pub, self.views_pub, self.markers_pub, self.hard_pub, self.hard_markers_pub = (
            self.create_publisher(topic.msg_type, topic.name, topic.qos())
            for topic in (
                topics.UNCERTAINTY_GRID, topics.NEXT_VIEWS, topics.VIEW_MARKERS,
                topics.HARD_REGIONS, topics.HARD_REGION_MARKERS,
            )
        )  # fmt: skip
        frames = MutuallyExclusiveCallbackGroup()
        self.inputs = PosedFrames(
            self,
            {
                "depth": (topics.PERCEPTION_DEPTH, partial(decode_frame_part, "depth")),
                "confidence": (topics.PERCEPTION_CONFIDENCE, partial(decode_frame_part, "confidence")),
            },
            p, self.rejections, self._fuse, self.status.changed, callback_group=frames,
        )  # fmt: skip
        # a request's frame may have been skipped (here or by perception): the map holds it when
        # a frame as new, or one taken near its pose, was fused (`NextBestViewServer.covers`)
        self.near = self.inputs.near
        semantic = topics.SEMANTIC_UNCERTAINTY
        subscribe(
            self, semantic.msg_type, semantic.name, self._on_semantic,
            semantic.reader_qos(p["camera_qos"], qos.FRAME_DEPTH), self.rejections,
            callback_group=frames,
        )  # fmt: skip
        # the view services one group each: a request waits for its frame while the other
        # answers; reset and load in the frames' group: no part of a frame is taken while the
        # map is cleared or loaded
        for service, handler, group in (
            (topics.SELECT_VIEWS, self._on_select_views, MutuallyExclusiveCallbackGroup()),
            (topics.NEXT_BEST_VIEW, self._on_request, MutuallyExclusiveCallbackGroup()),
            (topics.PLANNER_RESET, self._on_reset, frames),
            (topics.PLANNER_LOAD_MAP, self._on_load_map, frames),
            (topics.PLANNER_SAVE_MAP, self._on_save_map, MutuallyExclusiveCallbackGroup()),
        ):
            self.create_service(service.srv_type, service.name, handler, callback_group=group)
        self.get_logger().info(
            f"planner ready: policy={config.policy} mode={config.mode} "
            f"voxels={self.scheduler.core.grid.spec.num_voxels} world_frame={self.world_frame} "
            f"pose_source={self.inputs.pose_source}"
        )

    def destroy_node(self) -> None:
        self.fusion.stop(CLOSE_WAIT_S)
        self.scheduler.close(CLOSE_WAIT_S)
        super().destroy_node()

    def _status(self) -> dict:
        return {
            **self.scheduler.core.status(),
            "resets": self.resets,
            "requests_answered": self.requests_answered,
            **self.inputs.status(self.min_pairing_rate),
            "frames_dropped_backlog": self.fusion.dropped,
            "hard_regions": self.hard_regions,
            "fusion_failures": self.fusion_failures,
            # a worker thread that ended before the node stopped (diagnostics: ERROR)
            "workers": {
                "fusion": self.fusion.alive or self.fusion.stopping,
                **({"rebuild": self.scheduler.worker_alive} if self.scheduler.background else {}),
            },
            **{
                key: None if value is None else round(value, 4)
                for key, value in (
                    ("last_paired_age_s", self.fusion.last_paired_age_s),
                    ("last_fused_age_s", self.fusion.last_done_age_s),
                    ("last_fusion_s", self.fusion.last_process_s),
                )
            },
            "rejected": self.rejections.snapshot(),
        }

    def _on_refresh(self) -> None:
        with self.gate as running:  # called by the rebuild worker too
            if running:
                if self.scheduler.core.rebuild_failures > self.rebuild_failures_logged:
                    self.rebuild_failures_logged = self.scheduler.core.rebuild_failures
                    self.get_logger().error(
                        f"mask rebuild failed ({self.scheduler.core.last_rebuild_error}); the next "
                        "frame or request rebuilds them"
                    )
                self.status.publish()

    def stop(self) -> None:
        """Before the executor stops: no more publishing from the rebuild and fusion workers, and
        a request waiting for a mask rebuild returns at once instead of holding the executor's
        shutdown."""
        self.gate.close()
        self.fusion.stop(0.0)
        self.scheduler.close(0.0)

    def _on_reset(self, request, response):
        """area3d/planner/reset (std_srvs/Trigger): a new, empty map with the same parameters;
        frames fused, semantic maps, parts waiting for partners, frames waiting for camera info,
        a pose or fusion are dropped (counted in the answer's message, not as losses). Camera
        info and transforms stay: they describe the robot, not the episode."""
        try:
            with self.fusion.cleared() as waiting_fusion:
                old, self.scheduler = self.scheduler, self._new_map()
                parts, held = self.inputs.clear()  # the next frame starts the new map
            old.close(0.0)  # a request still waiting on the old map gets its answer from it
            fused = old.core.status().get("frames_fused", 0)
            self.resets += 1
            self._publish_state(self._now_ns())  # the empty grid replaces the latched one
            self._publish_views([], self.scheduler.core)  # and no planned view is drawn
        except Exception as exc:  # the node keeps serving; the caller learns why
            response.success = False
            response.message = f"reset failed: {type(exc).__name__}: {exc}"
            self.get_logger().error(f"{topics.PLANNER_RESET.name}: {response.message}")
            return response
        response.success = True
        response.message = (
            f"map cleared (reset {self.resets}): {fused} frames fused, "
            f"{waiting_fusion} waiting for fusion, {held} waiting for camera info "
            f"or a pose and {parts} parts of frames dropped"
        )
        self.get_logger().info(f"{topics.PLANNER_RESET.name}: {response.message}")
        return response

    def _on_save_map(self, request, response):
        """area3d/planner/save_map (MapFile): the whole map written to `path` (`map_io`); frames
        go on being fused meanwhile (the map is copied under its lock first)."""
        service = topics.PLANNER_SAVE_MAP.name
        try:
            written, size, header = map_io.save(self.scheduler.core, request.path, self.world_frame)
        except (InputError, OSError) as exc:
            return map_files.refused(response, service, exc, self.get_logger())
        return map_files.done(
            response, service, written, size, self.get_logger(),
            f"saved {header['frames']} fused frames and {header['committed']} views handed out",
        )  # fmt: skip

    def _on_load_map(self, request, response):
        """area3d/planner/load_map (MapFile): a saved map in place of the running one; a file that
        does not fit is refused before anything changes. Frames and parts waiting are dropped,
        as by a reset: they belong to the map being replaced."""
        service = topics.PLANNER_LOAD_MAP.name
        scheduler = self._new_map()
        try:
            loaded = map_io.read(scheduler.core, request.path, self.world_frame)
            with self.fusion.cleared():
                map_io.restore(scheduler.core, loaded)
                scheduler.loaded()
                old, self.scheduler = self.scheduler, scheduler
                self.inputs.clear()
        except Exception as exc:  # read and restored into the new map only: the running one stays
            scheduler.close(0.0)
            return map_files.load_failed(response, service, exc, self.get_logger())
        old.close(0.0)
        self._publish_state(self.scheduler.core.last_fused_stamp or self._now_ns())
        h = loaded.header
        return map_files.done(
            response, service, loaded.path, loaded.size_bytes, self.get_logger(),
            f"loaded {h['frames']} fused frames and {h['committed']} views handed out; "
            f"{self.scheduler.core.remaining_budget()} views remain",
        )  # fmt: skip

    def _fuse(self, stamp: int, frame: dict, K: np.ndarray) -> None:
        """Hand a whole frame to the fusion worker; one that finds its backlog full is dropped,
        logged and counted (`frames_dropped_backlog`)."""
        if not self.fusion.submit(stamp, frame, K):
            self.get_logger().warning(
                f"frame at stamp {stamp} dropped: {self.fusion.backlog} frames wait for fusion "
                "already (the camera outruns the planner)"
            )

    def _fuse_frame(self, stamp: int, frame: dict, K: np.ndarray) -> bool:
        """The fusion worker's step: fuse one frame into the map (False: fused already)."""
        return self.scheduler.add_frame(
            stamp, frame["depth"], frame["confidence"], K, frame["pose"]
        )

    def _on_fused(self, stamp: int, fused: bool, publish_grid: bool) -> bool:
        """After the fusion worker's step (its thread): the grid and status, or the status only
        while frames wait (`grid_period_s`); False once the node has stopped."""
        with self.gate as running:
            if not running:
                return False
            if not fused:
                self.get_logger().info(
                    f"frame {stamp} is fused already; the repeat changes nothing"
                )
            elif publish_grid:
                self._publish_state(stamp)
            else:
                self.status.publish()
            return True
        return False  # the context was shut down during the publish (the gate swallowed it)

    def _on_fusion_failed(self, stamp: int, exc: BaseException) -> None:
        """A frame whose fusion raised is dropped; the node keeps fusing the frames that follow."""
        depth_topic = topics.PERCEPTION_DEPTH.name
        if isinstance(exc, InputError):
            reject(self, self.rejections, f"frame at stamp {stamp}", exc, topic=depth_topic)
            return
        trace = "".join(traceback.format_exception(exc))
        self.get_logger().error(f"frame at stamp {stamp}: fusion failed, frame dropped:\n{trace}")
        self.fusion_failures += 1
        with self.gate as running:  # the fusion worker's thread
            if running:
                self.status.publish()

    def _on_semantic(self, msg) -> None:
        stamp = self.inputs.stamp(msg)
        u_sem = decode_frame_part("semantic uncertainty", msg)
        if self.scheduler.add_semantic(stamp, u_sem):
            self._publish_state(stamp)

    def _publish_state(self, stamp_ns: int) -> None:
        """The grid, its hard regions (boxes too) and the status, stamped with the last frame."""
        cloud, regions, boxes, self.hard_regions = grid_messages(
            self.scheduler.core.grid, stamp_ns, self.world_frame, self.hard_regions_max
        )
        self.grid_pub.publish(cloud)
        self.hard_pub.publish(regions)
        self.hard_markers_pub.publish(boxes)
        self.status.publish()

    def _on_request(self, request: msgs.GetPlan_Request, response: msgs.GetPlan_Response):
        """nav_msgs/GetPlan: `start` the current pose, `goal.pose.position.x` how many views;
        an empty plan when there is none (the reason in the log)."""
        try:
            try:
                start = codecs.pose_to_matrix(request.start.pose)
            except ValueError as exc:
                self.get_logger().warning(
                    f"next_best_view: start pose rejected ({exc}); planning without a start"
                )
                start = None
            stamp = codecs.stamp_to_ns(request.start.header.stamp)
            wanted = get_plan_request(start, stamp, request.goal.pose.position.x)
            _, response.plan = self._serve("next_best_view", wanted)
        except Exception as exc:  # an empty plan, the reason in the log; the node serves on
            self._failed("next_best_view", exc)
            response.plan = views_path([], self.world_frame, self._now_ns())
        return response

    def _on_select_views(self, request, response):
        """area3d_interfaces/NextBestView: the views with their gains, or success false with the
        reason (no frame yet, budget spent, degenerate workspace, a bad request, ...)."""
        service = topics.SELECT_VIEWS.name
        try:
            a = codecs.msg_to_view_request(request)
            # an empty frame_id (`ros2 service call ... "{count: 3}"` sends none) is world_frame
            if a.frame_id not in ("", self.world_frame):
                raise InputError(
                    "current.header.frame_id", a.frame_id, f"{self.world_frame!r} (world_frame)"
                )
            wanted = PlanRequest(a.current, a.stamp_ns, a.count, a.mode, a.request_id)
            plan, _ = self._serve("select_views", wanted)
        except Exception as exc:  # a refusal, and the node serves on
            plan = Plan([], [], self._failed(service, exc))
        stamp = codecs.stamp_to_ns(request.current.header.stamp) or self._now_ns()
        if plan.reason:
            return codecs.view_refusal_to_msg(plan.reason, stamp, self.world_frame)
        return codecs.view_answer_to_msg(
            np.array(plan.poses), plan.gains, stamp, self.world_frame, plan.note
        )

    def _failed(self, service: str, exc: Exception) -> str:
        """Why a request got no plan, logged: a bad request (InputError) as a warning, any other
        failure as an error (at info after Ctrl-C: the stop ended it)."""
        if isinstance(exc, InputError):
            reason, log = f"request rejected: {exc}", self.get_logger().warning
        else:
            reason = f"request failed: {type(exc).__name__}: {exc}"
            log = self.get_logger().error if self.context.ok() else self.get_logger().info
        log(f"{service}: {reason}")
        return reason

    def _now_ns(self) -> int:
        return self.get_clock().now().nanoseconds

    def _serve(self, service: str, request: PlanRequest) -> tuple[Plan, msgs.Path]:
        """Wait for the request's frame, plan, publish the views (the Path returned) and their
        markers. A request with the id of one answered gets that answer again at once; one whose
        frame lies ahead of the clock is refused (InputError)."""
        log = self.get_logger()
        # the map of the whole request, even if a reset replaces it meanwhile
        scheduler = self.scheduler
        server = scheduler.core
        check_request_stamp(request, self._now_ns(), self.max_stamp_ahead_s)
        if (plan := scheduler.answered(request.request_id)) is not None:
            log.info(f"{service}: request {request.request_id} again: answered as before")
            return plan, self._publish_views(plan.poses, server)
        sync_timeout_s = self.get_parameter("sync_timeout_s").value
        t0 = time.perf_counter()
        stale = ""
        if not scheduler.wait_fused(request.stamp_ns, sync_timeout_s, request.start, self.near):
            stale = server.stale_note(request.stamp_ns, sync_timeout_s)
            log.warning(f"{service}: {stale}")
        t1 = time.perf_counter()
        plan = scheduler.plan_views(request, stale)
        # where the last request's time went, in the status (a mission manager's latency budget)
        server.last_request_s = {
            "wait_fused": round(t1 - t0, 4),
            **{k: round(v, 4) for k, v in server.last_plan_s.items()},
        }
        self.requests_answered += 1
        if plan.reason:
            log.warning(f"{service}: {plan.reason}")
        path = self._publish_views(plan.poses, server)
        self.status.changed()
        return plan, path

    def _publish_views(self, poses: list, server: NextBestViewServer) -> msgs.Path:
        """The views on next_views and as frustums on view_markers (none: both cleared)."""
        now = self._now_ns()
        path = views_path(poses, self.world_frame, now)
        self.views_pub.publish(path)
        hfov_deg, width, height = server.camera()
        self.markers_pub.publish(
            view_markers(poses, self.world_frame, now, hfov_deg, width, height, self.marker_range)
        )
        return path


def config_from_parameters(p: dict) -> PlannerConfig:
    """The planner configuration this node's parameters `p` describe (also what
    `area3d_bringup.inprocess` plans with)."""
    return PlannerConfig(**{f.name: p[f.name] for f in fields(PlannerConfig)})


def main(args: Sequence[str] | None = None) -> int:
    return run_node(
        PlannerNode,
        "planner",
        args,
        executor=lambda: GuardedMultiThreadedExecutor(num_threads=EXECUTOR_THREADS),
        on_stop=lambda node: node.stop(),
    )


if __name__ == "__main__":
    exit_process(main())
