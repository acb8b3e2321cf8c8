"""The perception node: captured frames in, metric depth + confidence in [0, 1] out.

Subscribes the camera's color, depth and camera info (with the `stereo` backend also the right
image and right camera info of a rectified pair) with the QoS `camera_qos` chooses, pairs them by
stamp (`StampSync`, within `sync_slop_s`), takes each frame's camera pose from its `pose_source`
(the pose topic, paired by stamp; or TF or odometry, interpolated:
`area3d_msgs_py/pose_inputs.py`), keeps the keyframes of a streaming camera (`KeyframeSelector`:
moved, turned or time passed; the others are counted as skipped), runs `FrameEstimator` on them on
a thread of its own (`FrameWorker`, a bounded backlog) and publishes depth, confidence (for the
planner and semantics), fusion weight (for the reconstruction) and colour with the source frame's
stamp and frame_id. Topics: `area3d_msgs_py/topics.py`; names are relative: `__ns` moves them all.
"""

from __future__ import annotations

import dataclasses
import re
import traceback
from collections.abc import Sequence
from typing import Any

from rclpy.node import Node

from area3d_msgs_py import codecs, topics
from area3d_msgs_py.errors import InputError
from area3d_msgs_py.frame_sync import MAX_AGE_NS, HeldFrames, StampSync, pairing_warning
from area3d_msgs_py.guard import Rejections, reject, subscribe
from area3d_msgs_py.inputs import (
    COLOR_ENCODINGS,
    check_frame_id,
    check_stamp,
    decode_camera_depth,
    decode_camera_info,
    decode_image,
    distortion_note,
)
from area3d_msgs_py.keyframes import KeyframeConfig, KeyframeSelector
from area3d_msgs_py.lens import Remap, camera_undistortion
from area3d_msgs_py.lifecycle import PublishGate, exit_process, run_node
from area3d_msgs_py.parameters import (
    CAMERA_QOS_PARAM,
    CAMERA_RATE_PARAM,
    MAX_STAMP_AHEAD_PARAM,
    MIN_PAIRING_RATE_PARAM,
    SYNC_SLOP_PARAM,
    WORLD_FRAME_PARAM,
    Param,
    declare_parameters,
    params_of,
    report_unknown_parameters,
)
from area3d_msgs_py.pose_inputs import PoseInputs
from area3d_msgs_py.pose_source import PoseSourceConfig
from area3d_msgs_py.scheduling import FrameWorker
from area3d_msgs_py.status import StatusPublisher
from area3d_perception.estimator import (
    BACKENDS,
    FEEDFORWARD_WINDOW,
    NO_RETURN_RULES,
    check_frame,
    estimator_from_parameters,
    nothing_outside,
    undistorted,
)
from area3d_perception.sensor_model import RgbdSensorParams
from area3d_perception.stamp_watch import StampWatch
from area3d_perception.stereo import StereoParams

FRAME = "frame"  # rejections of a complete frame whose parts do not fit together
# Complete frames held while no camera info has arrived yet (oldest dropped beyond this).
MAX_FRAMES_WITHOUT_INFO = 8
# Keyframes waiting for the estimator at most (a 848x480 frame: 2.4 MB); beyond it a keyframe is
# dropped and counted (frames_dropped_backlog): the camera outruns the backend for good.
ESTIMATOR_BACKLOG = 16
# On shutdown the frame in flight gets this long to finish.
CLOSE_WAIT_S = 1.0

DEVICE = re.compile(r"auto|cpu|cuda(:[0-9]+)?")  # the torch devices a backend runs on

PARAMS = (
    Param("backend", "rgbd", "depth + confidence estimator", choices=BACKENDS),
    Param("checkpoint", "", "local VGGT / Depth Anything 3 weights (never downloaded at run time)"),
    Param(
        "device",
        "auto",
        "torch device of a feed-forward backend: auto | cpu | cuda[:N]",
        check=lambda v: None if DEVICE.fullmatch(v) else "auto, cpu, cuda or cuda:N",
    ),
    Param("window", FEEDFORWARD_WINDOW, "views per feed-forward pass, frames", range=(1, 256)),
    Param(
        "confidence_normalization",
        "inverse",
        "how a feed-forward confidence >= 1 maps to [0, 1]",
        choices=("inverse", "percentile"),
    ),
    Param(
        "no_return",
        "regions",
        "which of a depth camera's pixels without a return are a return beyond its range, "
        "published as +Inf (REP 117) and carved free by the planner: those in regions of no "
        "return (sky, open space; not the dropouts of a dark or specular surface), all or none; "
        "the stereo and feed-forward backends never declare one (a failed estimate is unknown)",
        choices=NO_RETURN_RULES,
    ),
    Param(
        "uniform_confidence",
        False,
        "confidence 1 on every valid pixel, on the backend's depth (the w/o feed-forward ablation)",
    ),
    Param("use_depth", True, "pair frames with the camera's depth (False: colour-only backends)"),
    Param(
        "undistort",
        True,
        "remap images whose camera_info has lens distortion (plumb_bob, rational_polynomial, "
        "equidistant) into the pinhole camera k before anything else (False: used as they come, "
        "with a standing warning)",
    ),
    Param(
        "sync_max_age_s",
        MAX_AGE_NS / 1e9,
        "parts of a frame wait this long for their partners, seconds",
        range=(0.0, 3600.0),
    ),
    SYNC_SLOP_PARAM,
    CAMERA_RATE_PARAM,
    MIN_PAIRING_RATE_PARAM,
    *params_of(KeyframeConfig),
    WORLD_FRAME_PARAM,
    MAX_STAMP_AHEAD_PARAM,
    Param(
        "max_stamp_lag_s",
        5.0,
        "a frame that pairs more than this after its stamp (by this node's clock) is a standing "
        "warning on /diagnostics until one arrives in time: the camera's clock behind this "
        "node's (hosts without time sync), a bag played without use_sim_time; 0 = no check, "
        "seconds",
        range=(0.0, 86400.0),
    ),
    CAMERA_QOS_PARAM,
    *params_of(PoseSourceConfig),
    *params_of(RgbdSensorParams, "sensor."),
    # the camera's range is sensor.max_range
    *params_of(StereoParams, "stereo.", skip=("max_range",)),
)


class PerceptionNode(Node):
    """Wires parameters, subscriptions and publishers around `FrameEstimator`."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__("perception", **kwargs)
        p = declare_parameters(self, PARAMS)
        report_unknown_parameters(self)
        self.use_depth = p["use_depth"]
        self.stereo = p["backend"] == "stereo"
        self.estimator = estimator_from_parameters(p)
        pose_config = PoseSourceConfig(
            **{f.name: p[f.name] for f in dataclasses.fields(PoseSourceConfig)}
        )
        pose_topic = pose_config.pose_source == "topic"  # else TF or odometry (self.poses)
        keys = ("color", "depth") if self.use_depth else ("color",)
        keys += ("pose",) if pose_topic else ()
        if self.stereo:
            keys += ("right",)
        self.sync = StampSync(
            keys,
            max_age_ns=int(p["sync_max_age_s"] * 1e9),
            slop_ns=int(round(p["sync_slop_s"] * 1e9)),
            count_gaps=True,  # a streaming camera's frames lost whole count against the rate
            period_ns=int(round(1e9 / p["camera_rate_hz"])) if p["camera_rate_hz"] > 0 else 0,
        )
        self.min_pairing_rate = p["min_pairing_rate"]
        self.keyframes = KeyframeSelector(
            KeyframeConfig(**{f.name: p[f.name] for f in dataclasses.fields(KeyframeConfig)})
        )
        # the estimator's worker publishes only while the node runs
        self.gate = PublishGate(self.context.ok)
        self.camera: tuple[Any, int, int] | None = None
        self.right_camera: tuple[float, int, int] | None = None  # (baseline m, width, height)
        self.waiting = HeldFrames(MAX_FRAMES_WITHOUT_INFO)
        self.frames_published = 0
        self.world_frame = p["world_frame"]
        self.max_stamp_ahead_s = p["max_stamp_ahead_s"]
        self.stamps = StampWatch(p["max_stamp_lag_s"])  # late and backward stamps
        self.undistort = p["undistort"]
        self.distortion: str | None = None  # what the camera info says of lens distortion
        # the remap of each camera's raw images into k (`undistort`), by camera info topic
        self.undistortions: dict[str, Remap | None] = {"left": None, "right": None}
        self.status = StatusPublisher(self, topics.PERCEPTION_STATUS, self._status)
        self.rejections = Rejections(on_count=self.status.changed)
        self.dropped = 0
        self.last_frame_age_s: float | None = None  # age of the last frame published, seconds
        # the backend's last failure (a feed-forward model or the stereo matcher raised), until
        # a frame succeeds; the frames it failed on are dropped
        self.backend_error: str | None = None
        self.frames_dropped_backend = 0

        self.worker = FrameWorker(
            self._estimate,
            self._on_estimated,
            lambda stamp, exc: None,  # `_estimate` handles its own failures
            "perception-estimator",
            backlog=ESTIMATOR_BACKLOG,
            publish_period_s=0.0,
            now_ns=self._now_ns,
        )
        self.pub_depth = self._publisher(topics.PERCEPTION_DEPTH)
        self.pub_conf = self._publisher(topics.PERCEPTION_CONFIDENCE)
        self.pub_weight = self._publisher(topics.PERCEPTION_WEIGHT)
        self.pub_color = self._publisher(topics.PERCEPTION_COLOR)
        self.poses = None
        if not pose_topic:
            self.poses = PoseInputs(
                self, pose_config, self.world_frame, self.max_stamp_ahead_s, p["camera_qos"],
                self.rejections, self._posed, self.status.changed,
            )  # fmt: skip
        inputs = [(topics.COLOR, self.on_color), (topics.CAMERA_INFO, self.on_camera_info)]
        if pose_topic:
            inputs.append((topics.POSE, self.on_pose))
        if self.use_depth:
            inputs.append((topics.DEPTH, self.on_depth))
        if self.stereo:
            inputs += [
                (topics.RIGHT_IMAGE, self.on_right),
                (topics.RIGHT_CAMERA_INFO, self.on_right_camera_info),
            ]
        for topic, callback in inputs:
            subscribe(
                self, topic.msg_type, topic.name, callback, topic.reader_qos(p["camera_qos"]),
                self.rejections,
            )  # fmt: skip
        self.get_logger().info(
            f"backend={p['backend']} use_depth={self.use_depth} "
            f"pose_source={pose_config.pose_source} camera_qos={p['camera_qos']}"
        )

    def _publisher(self, topic: topics.Topic) -> Any:
        return self.create_publisher(topic.msg_type, topic.name, topic.qos())

    def stop(self) -> None:
        """Before the executor stops: no more publishing from the estimator's worker."""
        self.gate.close()
        self.worker.stop(0.0)

    def destroy_node(self) -> None:
        self.gate.close()
        self.worker.stop(CLOSE_WAIT_S)
        super().destroy_node()

    def _status(self) -> dict:
        warnings = [
            pairing_warning(self.sync, self.min_pairing_rate),
            *self.stamps.warnings(),
            self.distortion,
        ]
        return {
            "node": "perception",
            "frames_published": self.frames_published,
            **self.keyframes.status(),
            "frames_paired": self.sync.frames_paired,
            "frames_missed": self.sync.frames_missed,
            "pairing_rate": self.sync.pairing_rate(),
            "frames_waiting_for_estimator": self.worker.waiting,
            "frames_dropped_backlog": self.worker.dropped,
            "workers": {"estimator": self.worker.alive or self.worker.stopping},
            "warnings": [w for w in warnings if w],
            # the distortion model whose images are remapped into k, by camera
            "undistorted": {k: v.model for k, v in self.undistortions.items() if v is not None},
            **self.stamps.status(),
            "last_frame_age_s": None
            if self.last_frame_age_s is None
            else round(self.last_frame_age_s, 4),
            "frames_waiting_for_camera_info": len(self.waiting),
            "parts_dropped_unpaired": self.dropped,
            "frames_dropped_without_camera_info": self.waiting.dropped,
            "frames_dropped_backend_failure": self.frames_dropped_backend,
            "backend_error": self.backend_error,
            **({} if self.poses is None else self.poses.status()),
            "rejected": self.rejections.snapshot(),
        }

    # inputs ---------------------------------------------------------------------------------
    def _camera_size(self) -> tuple[int, int] | None:
        return None if self.camera is None else (self.camera[1], self.camera[2])

    def on_color(self, msg: Any) -> None:
        self._add("color", msg, lambda m: decode_image(m, COLOR_ENCODINGS, self._camera_size()))

    def on_depth(self, msg: Any) -> None:
        self._add("depth", msg, lambda m: decode_camera_depth(m, self._camera_size()))

    def on_pose(self, msg: Any) -> None:
        check_frame_id(msg, self.world_frame)
        self._add("pose", msg, lambda m: codecs.pose_to_matrix(m.pose))

    def on_right(self, msg: Any) -> None:
        self._add("right", msg, codecs.msg_to_image)

    def on_camera_info(self, msg: Any) -> None:
        check_stamp(msg, self._now_ns(), self.max_stamp_ahead_s)
        K, width, height = decode_camera_info(msg)
        note = self._distortion("left", K, width, height, msg)
        if note != self.distortion:
            self.distortion = note
            if note:
                self.get_logger().warning(note)
            self.status.changed()
        self.camera = (K, width, height)
        self._release_waiting()

    def _distortion(self, side: str, K: Any, width: int, height: int, msg: Any) -> str | None:
        """Keep the remap of `side`'s camera up to date (built again only when its camera info
        changes); the standing warning, if any, of its distortion."""
        if not self.undistort:
            return distortion_note(msg)
        remap, note = camera_undistortion(K, width, height, msg.distortion_model, msg.d)
        if remap is not None and remap is not self.undistortions[side]:
            self.get_logger().info(
                f"{side} camera: distortion_model {remap.model!r} with d "
                f"{[round(v, 4) for v in remap.d]}: images undistorted into k"
            )
        self.undistortions[side] = remap
        return note

    def on_right_camera_info(self, msg: Any) -> None:
        check_stamp(msg, self._now_ns(), self.max_stamp_ahead_s)
        K, width, height = decode_camera_info(msg)
        note = self._distortion("right", K, width, height, msg)
        if note:
            self.get_logger().warning(note, throttle_duration_sec=10.0)
        self.right_camera = (codecs.camera_info_to_baseline(msg), width, height)
        self._release_waiting()

    def _ready(self) -> bool:
        return self.camera is not None and (not self.stereo or self.right_camera is not None)

    def _release_waiting(self) -> None:
        if self._ready():
            for stamp, parts in self.waiting.release():
                self._process(stamp, parts)

    def _now_ns(self) -> int:
        return self.get_clock().now().nanoseconds

    def _add(self, key: str, msg: Any, decode) -> None:
        stamp = check_stamp(msg, self._now_ns(), self.max_stamp_ahead_s)
        value = (decode(msg), check_frame_id(msg))
        paired = self.sync.add_part(key, stamp, value)
        for dropped in self.sync.pop_dropped():
            self.dropped += 1
            self.get_logger().warning(
                f"{dropped.key} at stamp {dropped.stamp_ns} dropped: {dropped.reason}",
                throttle_duration_sec=1.0,
            )
        if paired is None:
            return
        stamp, parts = paired
        changed, jumped = self.stamps.note(stamp, self._now_ns())
        if jumped:
            self.get_logger().warning(jumped, throttle_duration_sec=1.0)
        if changed:
            self.status.changed()  # a warning starts or ends
        if self.poses is not None:  # the pose at the frame's stamp, now or once it has arrived
            self.poses.submit(stamp, parts["color"][1], parts)
            return
        self._complete(stamp, parts)

    def _posed(self, stamp: int, parts: dict, T_world_cam: Any) -> None:
        self._complete(stamp, {**parts, "pose": (T_world_cam, self.world_frame)})

    def _complete(self, stamp: int, parts: dict) -> None:
        if not self.keyframes.offer(stamp, parts["pose"][0]):
            self.status.changed()
            return  # the camera has not moved, turned or waited enough: skipped, counted
        if not self._ready():
            missing = topics.CAMERA_INFO if self.camera is None else topics.RIGHT_CAMERA_INFO
            warning = self.waiting.hold(stamp, parts, missing.name)
            if warning:
                self.get_logger().warning(warning)
            return
        self._process(stamp, parts)

    def _process(self, stamp: int, parts: dict) -> None:
        """Hand a keyframe to the estimator's worker with the camera it was taken with; one that
        finds the backlog full is dropped, logged and counted (`frames_dropped_backlog`)."""
        cameras = (self.camera, self.right_camera, dict(self.undistortions))
        if not self.worker.submit(stamp, parts, cameras):
            self.get_logger().warning(
                f"frame at stamp {stamp} dropped: {self.worker.backlog} frames wait for the "
                f"{self.estimator.backend} backend already (the camera outruns it)",
                throttle_duration_sec=1.0,
            )
            self.status.changed()

    def _on_estimated(self, stamp: int, published: bool, publish: bool) -> bool:
        with self.gate as running:
            if running:
                self.status.changed()
            return running

    # processing -----------------------------------------------------------------------------
    def _estimate(self, stamp: int, parts: dict, cameras: tuple) -> bool:
        """The worker's step: depth and confidence of one keyframe, published; False when it
        was rejected or the backend failed (said, counted)."""
        (K, width, height), right_camera, undistortions = cameras
        rgb, color_frame = parts["color"]
        depth, depth_frame = parts["depth"] if "depth" in parts else (None, None)
        T_world_cam, _ = parts["pose"]
        right, _ = parts["right"] if "right" in parts else (None, None)
        baseline = None
        frame_id = depth_frame or color_frame
        try:
            if depth_frame is not None and depth_frame != color_frame:
                raise InputError(
                    "depth header.frame_id",
                    depth_frame,
                    f"the color image's {color_frame!r} (depth registered to color)",
                )
            check_frame(rgb, depth, (width, height))
            rgb, depth, right = undistorted(rgb, depth, right, undistortions)
            if self.stereo:
                baseline, right_width, right_height = right_camera
                if (right_width, right_height) != (width, height):
                    raise InputError(
                        "right camera_info",
                        f"size {right_width}x{right_height}",
                        f"the left camera's size {width}x{height}",
                    )
            result = self.estimator.process(
                rgb, depth, K, T_world_cam, right=right, baseline=baseline
            )
            if undistortions["left"] is not None:
                result = nothing_outside(result, undistortions["left"])
        except InputError as exc:
            with self.gate as running:
                if running:
                    reject(self, self.rejections, f"{FRAME} at stamp {stamp}", exc, topic=FRAME)
            return False
        except Exception as exc:  # the backend failed on a good frame: dropped, and said so
            self.backend_error = f"{exc.__class__.__name__}: {exc}"
            self.frames_dropped_backend += 1
            self.get_logger().error(
                f"frame at stamp {stamp}: {self.estimator.backend} backend failed, frame "
                f"dropped:\n{traceback.format_exc()}"
            )
            return False
        self.backend_error = None
        for note in result.notes:
            self.get_logger().warning(f"frame at stamp {stamp}: {note}")
        with self.gate as running:
            if not running:
                return False
            # counted before it goes out: a status never shows fewer than a reader has received
            self.frames_published += 1
            self.pub_depth.publish(codecs.image_to_msg(result.depth, "32FC1", stamp, frame_id))
            confidence = codecs.image_to_msg(result.confidence, "32FC1", stamp, frame_id)
            self.pub_conf.publish(confidence)
            # the same image (every backend but stereo) is encoded once
            weight = (
                confidence
                if result.weight is result.confidence
                else codecs.image_to_msg(result.weight, "32FC1", stamp, frame_id)
            )
            self.pub_weight.publish(weight)
            self.pub_color.publish(codecs.image_to_msg(rgb, "rgb8", stamp, frame_id))
        # how old the frame was when its outputs went out, by this node's clock (the camera's
        # stamp is its capture time; recorded or simulated stamps make this meaningless)
        self.last_frame_age_s = (self._now_ns() - stamp) / 1e9
        return True


def main(args: Sequence[str] | None = None) -> int:
    """Process entry point: `python -m area3d_perception.node [--ros-args ...]`."""
    return run_node(
        PerceptionNode,
        "perception",
        args,
        startup_errors=(InputError, FileNotFoundError, ImportError, RuntimeError),
        on_stop=lambda node: node.stop(),
    )


if __name__ == "__main__":
    exit_process(main())
