"""The reconstruction node: the frames the planner fuses, integrated into a TSDF volume, and its
coloured mesh, live.

Subscribes area3d/perception/depth and area3d/perception/weight (camera or estimated depth:
each pixel weighs by perception's fusion weight) and area3d/perception/color (the colour of the frames
perception answered), area3d/camera/camera_info
and the camera pose of its `pose_source` (as the planner: the pose topic paired by stamp, or TF
or odometry at the frame's stamp), with the planner's keyframe rule. Integrates each frame once,
with the evaluation's code (`area3d_eval.reconstruct.TsdfFusion`: one reconstruction in the
project), on a worker thread off the executor, so neither the planner's latency nor this node's
callbacks wait for it. Publishes, in `world_frame`, the latched area3d/reconstruction/mesh
(visualization_msgs/Marker TRIANGLE_LIST with vertex colours, what RViz and Foxglove draw; after
each frame, at most every mesh_period_s while frames wait) and area3d/reconstruction/status (and
/diagnostics). Serves save_map, load_map, export_mesh (area3d_interfaces/srv/MapFile) and reset
(std_srvs/Trigger) under area3d/reconstruction/.
"""

from __future__ import annotations

import threading
import time
import traceback
from collections.abc import Sequence
from functools import partial
from typing import Any

import numpy as np
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.node import Node

from area3d_eval.reconstruct import TsdfFusion, TsdfParams
from area3d_msgs_py import codecs, map_files, topics
from area3d_msgs_py.errors import InputError
from area3d_msgs_py.guard import Rejections, reject
from area3d_msgs_py.inputs import (
    decode_frame_part,
)
from area3d_msgs_py.keyframes import KeyframeConfig
from area3d_msgs_py.lifecycle import PublishGate, exit_process, run_node
from area3d_msgs_py.parameters import (
    CAMERA_QOS_PARAM,
    MAX_STAMP_AHEAD_PARAM,
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
from area3d_reconstruction import map_io

# Frame callbacks, the services and the worker's publishing run on separate threads.
EXECUTOR_THREADS = 3
CLOSE_WAIT_S = 1.0
LEVELS = ("object", "room")

PARAMS = (
    Param(
        "roi_min",
        [-0.3, -0.3, 0.0],
        "lower corner [x, y, z] of the region to reconstruct (the planner's), metres",
    ),
    Param(
        "roi_max", [0.3, 0.3, 0.5], "upper corner [x, y, z] of the region to reconstruct, metres"
    ),
    Param(
        "level",
        "object",
        "the volume's defaults: object (4 mm voxels) or room (2 cm), as the evaluation's",
        choices=LEVELS,
    ),
    Param(
        "voxel_length",
        0.0,
        "voxel edge of the volume; 0 = the level's; the truncation band stays 4 voxels, metres",
        range=(0.0, 1.0),
    ),
    Param(
        "mesh_period_s",
        1.0,
        "while frames wait to be integrated, the mesh goes out at most this often (after every "
        "frame otherwise), seconds",
        range=(0.0, 3600.0),
    ),
    Param(
        "sync_max_age_s",
        60.0,
        "parts of a frame wait this long for their partners, seconds",
        range=(0.0, 3600.0),
    ),
    SYNC_SLOP_PARAM,
    *params_of(KeyframeConfig),
    WORLD_FRAME_PARAM,
    MAX_STAMP_AHEAD_PARAM,
    CAMERA_QOS_PARAM,
    *params_of(PoseSourceConfig),
)


def volume_from_parameters(p: dict) -> TsdfFusion:
    """An empty volume as the parameters `p` describe it (the evaluation's at the level)."""
    params = TsdfParams.for_level(p["level"])
    if p["voxel_length"] > 0:
        ratio = params.sdf_trunc / params.voxel_length
        params = TsdfParams(
            voxel_length=p["voxel_length"],
            sdf_trunc=ratio * p["voxel_length"],
            depth_trunc=params.depth_trunc,
            depth_stride=params.depth_stride,
            roi_margin=params.roi_margin,
        )
    return TsdfFusion(params, np.asarray(p["roi_min"], float), np.asarray(p["roi_max"], float))


class ReconstructionNode(Node):
    """Wires parameters, subscriptions, the mesh publisher and the services around `TsdfFusion`."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__("reconstruction", **kwargs)
        p = declare_parameters(self, PARAMS)
        report_unknown_parameters(self)
        self._new_volume = lambda: volume_from_parameters(p)
        self.volume = self._new_volume()
        self.stamps: list[int] = []  # the frames integrated, in order (each once)
        self._integrated: set[int] = set()
        # the volume: the worker integrates, the services save, load, export and reset it
        self._lock = threading.Lock()
        self.gate = PublishGate(self.context.ok)
        self.world_frame = p["world_frame"]
        self.resets = 0
        self.failures = 0
        self.mesh: dict = {}  # the last mesh published: triangles, seconds to extract and send
        self.status = StatusPublisher(self, topics.RECONSTRUCTION_STATUS, self._status)
        self.rejections = Rejections(on_count=self.status.changed)
        self.worker = FrameWorker(
            self._integrate,
            self._on_integrated,
            self._on_failed,
            "reconstruction-integration",
            publish_period_s=p["mesh_period_s"],
            now_ns=self._now_ns,
        )
        self.mesh_pub = self.create_publisher(
            topics.RECONSTRUCTION_MESH.msg_type,
            topics.RECONSTRUCTION_MESH.name,
            topics.RECONSTRUCTION_MESH.qos(),
        )
        self.inputs = PosedFrames(
            self,
            {
                "depth": (topics.PERCEPTION_DEPTH, partial(decode_frame_part, "depth")),
                "weight": (topics.PERCEPTION_WEIGHT, partial(decode_frame_part, "weight")),
                "color": (topics.PERCEPTION_COLOR, partial(decode_frame_part, "color")),
            },
            p, self.rejections, self._submit, self.status.changed,
            callback_group=MutuallyExclusiveCallbackGroup(),
        )  # fmt: skip
        services = MutuallyExclusiveCallbackGroup()
        for service, handler in (
            (topics.RECONSTRUCTION_SAVE_MAP, self._on_save_map),
            (topics.RECONSTRUCTION_LOAD_MAP, self._on_load_map),
            (topics.RECONSTRUCTION_EXPORT_MESH, self._on_export_mesh),
            (topics.RECONSTRUCTION_RESET, self._on_reset),
        ):
            self.create_service(service.srv_type, service.name, handler, callback_group=services)
        v = self.volume.params
        self.get_logger().info(
            f"reconstruction ready: voxel_length={v.voxel_length} level={p['level']} "
            f"world_frame={self.world_frame} pose_source={self.inputs.pose_source}"
        )

    def destroy_node(self) -> None:
        self.worker.stop(CLOSE_WAIT_S)
        super().destroy_node()

    def stop(self) -> None:
        self.gate.close()
        self.worker.stop(0.0)

    def _now_ns(self) -> int:
        return self.get_clock().now().nanoseconds

    def _status(self) -> dict:
        return {
            "frames_integrated": len(self.stamps),
            "last_integrated_stamp_ns": self.stamps[-1] if self.stamps else 0,
            "voxel_length": self.volume.params.voxel_length,
            "mesh": self.mesh,
            "resets": self.resets,
            # the keyframe rule's counts but its "frames_integrated" (frames it let through)
            **{k: v for k, v in self.inputs.status().items() if k != "frames_integrated"},
            "frames_dropped_backlog": self.worker.dropped,
            "integration_failures": self.failures,
            "workers": {"integration": self.worker.alive or self.worker.stopping},
            "last_integration_s": None
            if self.worker.last_process_s is None
            else round(self.worker.last_process_s, 4),
            "rejected": self.rejections.snapshot(),
        }

    # ------------------------------------------------------------------ frames
    def _submit(self, stamp: int, frame: dict, K: np.ndarray) -> None:
        if not self.worker.submit(stamp, frame, K):
            self.get_logger().warning(
                f"frame at stamp {stamp} dropped: {self.worker.backlog} frames wait already"
            )

    def _integrate(self, stamp: int, frame: dict, K: np.ndarray) -> bool:
        """The worker's step: integrate one frame (False: integrated already)."""
        rgb, depth = frame["color"], frame["depth"]
        if rgb.shape[:2] != depth.shape:
            raise InputError(
                f"{topics.PERCEPTION_COLOR.name} at stamp {stamp}",
                f"{rgb.shape[1]}x{rgb.shape[0]}",
                f"the depth's size {depth.shape[1]}x{depth.shape[0]}",
            )
        with self._lock:
            if stamp in self._integrated:
                return False
            self.volume.integrate(rgb, depth, K, frame["pose"], frame["weight"])
            self._integrated.add(stamp)
            self.stamps.append(stamp)
        return True

    def _on_integrated(self, stamp: int, done: bool, publish: bool) -> bool:
        """After the worker's step (its thread): the mesh (made before the publish gate is taken:
        it takes up to a second, and a Ctrl-C meanwhile shuts the context down) and the status;
        False once the node has stopped."""
        data = self._mesh_message(stamp) if done and publish else None
        with self.gate as running:
            if not running:
                return False
            if data is not None:
                self.mesh_pub.publish(data)
            self.status.publish()
            return True
        return False  # the context was shut down during the publish (the gate swallowed it)

    def _on_failed(self, stamp: int, exc: BaseException) -> None:
        if isinstance(exc, InputError):
            reject(self, self.rejections, f"frame at stamp {stamp}", exc)
            return
        trace = "".join(traceback.format_exception(exc))
        self.get_logger().error(f"frame at stamp {stamp}: integration failed, dropped:\n{trace}")
        self.failures += 1
        with self.gate as running:
            if running:
                self.status.publish()

    def _mesh_message(self, stamp: int) -> bytes:
        """The volume's mesh as a serialized Marker stamped with its last frame (what
        area3d/reconstruction/mesh carries); its size and timings go to the status."""
        t0 = time.perf_counter()
        with self._lock:
            vertices, triangles, colours = self.volume.surface_arrays()
        t1 = time.perf_counter()
        data = codecs.mesh_marker_cdr(vertices, triangles, colours, stamp, self.world_frame)
        self.mesh = {
            "triangles": len(triangles),
            "extract_s": round(t1 - t0, 4),
            "encode_s": round(time.perf_counter() - t1, 4),
            "stamp_ns": stamp,
        }
        return data

    def _publish_mesh(self, stamp: int) -> None:
        """The mesh on area3d/reconstruction/mesh (from a service: the executor's thread)."""
        self.mesh_pub.publish(self._mesh_message(stamp))

    # ------------------------------------------------------------------ services
    def _on_save_map(self, request, response):
        service = topics.RECONSTRUCTION_SAVE_MAP.name
        try:
            with self._lock:
                written, size = map_io.save(
                    self.volume, self.stamps, request.path, self.world_frame
                )
                frames = len(self.stamps)
        except (InputError, OSError) as exc:
            return map_files.refused(response, service, exc, self.get_logger())
        return map_files.done(
            response, service, written, size, self.get_logger(), f"saved {frames} frames"
        )

    def _on_load_map(self, request, response):
        service = topics.RECONSTRUCTION_LOAD_MAP.name
        try:
            volume = self._new_volume()
            loaded = map_io.read(volume, request.path, self.world_frame)
            stamps = map_io.restore(volume, loaded)
        except Exception as exc:  # read and restored into a new volume only: the running one stays
            return map_files.load_failed(response, service, exc, self.get_logger())
        with self.worker.cleared(), self._lock:
            self.volume, self.stamps, self._integrated = volume, stamps, set(stamps)
            self.inputs.clear()
        with self.gate as running:
            if running:
                self._publish_mesh(stamps[-1] if stamps else self._now_ns())
                self.status.publish()
        return map_files.done(
            response, service, loaded.path, loaded.size_bytes, self.get_logger(),
            f"loaded {len(stamps)} frames",
        )  # fmt: skip

    def _on_export_mesh(self, request, response):
        service = topics.RECONSTRUCTION_EXPORT_MESH.name
        try:
            with self._lock:
                mesh = self.volume.extract_mesh()
            written, size = map_io.export_mesh(mesh, request.path)
        except (InputError, OSError) as exc:
            return map_files.refused(response, service, exc, self.get_logger())
        return map_files.done(
            response, service, written, size, self.get_logger(),
            f"exported {len(mesh.triangles)} triangles of {len(self.stamps)} frames",
        )  # fmt: skip

    def _on_reset(self, request, response):
        """area3d/reconstruction/reset (std_srvs/Trigger): an empty volume; frames waiting are
        dropped (counted in the answer)."""
        with self.worker.cleared() as waiting, self._lock:
            frames = len(self.stamps)
            self.volume, self.stamps, self._integrated = self._new_volume(), [], set()
            parts, held = self.inputs.clear()
        self.resets += 1
        with self.gate as running:
            if running:
                self._publish_mesh(self._now_ns())  # the empty mesh replaces the latched one
                self.status.publish()
        response.success = True
        response.message = (
            f"volume cleared (reset {self.resets}): {frames} frames integrated, {waiting} waiting, "
            f"{held} waiting for camera info or a pose and {parts} parts of frames dropped"
        )
        self.get_logger().info(f"{topics.RECONSTRUCTION_RESET.name}: {response.message}")
        return response


def main(args: Sequence[str] | None = None) -> int:
    return run_node(
        ReconstructionNode,
        "reconstruction",
        args,
        executor=lambda: GuardedMultiThreadedExecutor(num_threads=EXECUTOR_THREADS),
        on_stop=lambda node: node.stop(),
    )


if __name__ == "__main__":
    exit_process(main())
