"""Per-frame cost of perception: the node's whole frame, its sensor-model steps, splatting and carving.

A synthetic 640x480 frame (a sphere in front of a wall, 90 degree field of view) is processed
against a 100^3 = 1M-voxel grid that the whole frustum crosses. The first row is what the
perception node pays per frame with the shipped settings (`rgbd` backend, as in
area3d_bringup/config/area3d.yaml, on depth carrying the camera's noise): a real `PerceptionNode`'s
callbacks called directly on
messages as a subscription delivers them (a CDR round trip), from decoding the images to building
the output messages; only the two publish() calls are left out. Each figure is the median and
p10-p90 of `repeats` runs after one warm-up (which also compiles the numba kernels), as wall time
and as process CPU time: on a machine shared with other work the wall time includes waiting for a
core, which the CPU time does not, so the load average before and after is printed with them.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager

import numpy as np

from area3d_msgs_py.carving import CARVE_STRIDE, carve_depth_frame
from area3d_msgs_py.depth_sensor import RgbdSensorParams
from area3d_msgs_py.grid import GridSpec
from area3d_perception.geometric import splat_depth_frame
from area3d_perception.sensor_model import rgbd_confidence
from sim_bridge.noise import add_depth_noise

# Every per-frame step should keep up with a 30 Hz camera on 2 CPU cores.
TARGET_MS = 30.0
# The perception node's settings in the shipped graph (area3d_bringup/config/area3d.yaml).
# every frame is estimated (no keyframe rule): each timed frame is a whole frame's work
NODE_PARAMETERS = {
    "backend": "rgbd",
    "keyframe_distance": 0.0,
    "keyframe_angle_deg": 0.0,
    "keyframe_interval_s": 0.0,
}
WORKER_WAIT_S = 120.0
OPTICAL_FRAME = "camera_optical_frame"


def synthetic_frame(
    width: int = 640, height: int = 480
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(depth (H, W) float32, K (3, 3), T_world_cam (4, 4)): a 0.5 m sphere at (0, 0, 1) in front
    of a wall at y = 0.9, seen from (0, -2.5, 1) looking along +y, 90 degree horizontal FOV."""
    f = (width / 2) / np.tan(np.deg2rad(90.0) / 2)
    K = np.array([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1.0]])
    T = np.eye(4)
    T[:3, :3] = np.column_stack([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])
    T[:3, 3] = [0.0, -2.5, 1.0]
    u = (np.arange(width) + 0.5 - K[0, 2]) / f
    v = (np.arange(height) + 0.5 - K[1, 2]) / f
    uu, vv = np.meshgrid(u, v)
    rays = np.stack([uu, vv, np.ones_like(uu)], axis=-1)  # optical frame, z = 1
    depth = np.full((height, width), 3.4, dtype=np.float64)  # the wall, 3.4 m ahead
    centre = T[:3, :3].T @ (np.array([0.0, 0.0, 1.0]) - T[:3, 3])
    b = rays @ centre
    a = np.einsum("hwc,hwc->hw", rays, rays)
    disc = b * b - a * (centre @ centre - 0.5**2)
    hit = disc > 0
    t = (b - np.sqrt(np.where(hit, disc, 0.0))) / a
    depth[hit] = t[hit]
    return depth.astype(np.float32), K, T


def timed(fn: Callable[[], object], repeats: int) -> dict:
    """Run `fn` once to warm up, then `repeats` times; returns milliseconds of wall and process
    CPU time: {"wall", "wall_p10", "wall_p90", "cpu", "cpu_p10", "cpu_p90"} (medians and
    percentiles)."""
    fn()
    wall, cpu = [], []
    for _ in range(repeats):
        start, start_cpu = time.perf_counter(), time.process_time()
        fn()
        wall.append((time.perf_counter() - start) * 1e3)
        cpu.append((time.process_time() - start_cpu) * 1e3)
    return {
        "wall": float(np.median(wall)),
        "wall_p10": float(np.percentile(wall, 10)),
        "wall_p90": float(np.percentile(wall, 90)),
        "cpu": float(np.median(cpu)),
        "cpu_p10": float(np.percentile(cpu, 10)),
        "cpu_p90": float(np.percentile(cpu, 90)),
    }


class _Discard:
    """Stands in for a publisher: the bench times the node's frame, not the transport."""

    def publish(self, msg: object) -> None:
        pass


@contextmanager
def node_frames(
    depth: np.ndarray, K: np.ndarray, T_world_cam: np.ndarray, parameters: dict | None = None
) -> Iterator[Callable[[], None]]:
    """A function that feeds one captured frame (colour, depth, pose, each with a new stamp)
    through a real `PerceptionNode`'s callbacks, as a subscription delivers the messages; the
    node's outputs are built and discarded. On leaving, raises RuntimeError if the node did not
    publish every frame it was given (a rejected frame would time nothing).

    depth: (H, W) float32 metres; K: (3, 3); T_world_cam: (4, 4); parameters: node parameters
    (over `NODE_PARAMETERS`).
    """
    import rclpy
    from rclpy.parameter import Parameter

    from area3d_msgs_py import codecs, msgs
    from area3d_perception.node import PerceptionNode

    parameters = {**NODE_PARAMETERS, **(parameters or {})}
    h, w = depth.shape
    rgb = np.random.default_rng(0).integers(0, 256, (h, w, 3), dtype=np.uint8)

    def delivered(msg: object, type_name: str) -> object:
        return msgs.deserialize(msgs.serialize(msg), type_name)

    context = rclpy.Context()
    rclpy.init(context=context)
    node = PerceptionNode(
        context=context,
        parameter_overrides=[Parameter(k, value=v) for k, v in parameters.items()],
    )
    try:
        node.pub_depth = node.pub_conf = _Discard()
        stamp = node.get_clock().now().nanoseconds - 60 * 10**9
        node.on_camera_info(
            delivered(
                codecs.intrinsics_to_camera_info(K, w, h, stamp, OPTICAL_FRAME),
                "sensor_msgs/msg/CameraInfo",
            )
        )
        color_msg = delivered(
            codecs.image_to_msg(rgb, "rgb8", stamp, OPTICAL_FRAME), "sensor_msgs/msg/Image"
        )
        depth_msg = delivered(
            codecs.image_to_msg(depth, "32FC1", stamp, OPTICAL_FRAME), "sensor_msgs/msg/Image"
        )
        pose_msg = delivered(
            msgs.PoseStamped(
                header=codecs.header(stamp, "world"), pose=codecs.matrix_to_pose(T_world_cam)
            ),
            "geometry_msgs/msg/PoseStamped",
        )
        sent = 0

        def frame() -> None:
            nonlocal sent
            sent += 1
            for msg in (color_msg, depth_msg, pose_msg):
                msg.header.stamp = codecs.ns_to_stamp(stamp + sent * 1_000_000)
            node.on_color(color_msg)
            node.on_depth(depth_msg)
            node.on_pose(pose_msg)
            # the estimate runs on the node's worker thread: the frame is done once it is out
            if not node.worker.wait_idle(WORKER_WAIT_S):
                raise RuntimeError(f"frame {sent} not estimated within {WORKER_WAIT_S} s")

        yield frame
        if node.frames_published != sent:
            raise RuntimeError(
                f"the perception node published {node.frames_published} of {sent} frames "
                f"(rejected: {node.rejections.snapshot()}); its timing would not be a frame's"
            )
    finally:
        node.destroy_node()
        context.try_shutdown()


def run_bench(repeats: int = 15, stride: int = CARVE_STRIDE, print_table: bool = True) -> dict:
    """Time the per-frame steps; returns {"steps": {name: `timed` figures}} plus the setup
    figures and the load average (1, 5, 15 min) before and after."""
    load_before = os.getloadavg()
    depth, K, T = synthetic_frame()
    params = RgbdSensorParams()
    rng = np.random.default_rng(0)
    spec = GridSpec.from_bounds(np.array([-1.0, -1.0, 0.0]), np.array([1.0, 1.0, 2.0]), 0.02)
    evidence = np.zeros(spec.shape, np.float32)
    hits = np.zeros(spec.shape, np.float32)
    free = np.zeros(spec.shape, np.uint16)
    conf = rgbd_confidence(depth, K, params)
    noisy = add_depth_noise(depth, K, rng, params)  # what the camera delivers

    def carve() -> None:
        free[:] = 0  # keep the uint16 counter far from overflow across repeats
        carve_depth_frame(spec, depth, K, T, free, stride=stride)

    with node_frames(noisy, K, T) as node_frame:
        steps = {"node_frame": timed(node_frame, repeats)}
    steps.update(
        {
            "rgbd_confidence": timed(lambda: rgbd_confidence(noisy, K, params), repeats),
            "depth_noise": timed(lambda: add_depth_noise(depth, K, rng, params), repeats),
            "splat": timed(
                lambda: splat_depth_frame(spec, depth, conf, K, T, evidence, hits), repeats
            ),
            "carve": timed(carve, repeats),
        }
    )
    figures = {
        "steps": steps,
        "image": "640x480",
        "grid_voxels": spec.num_voxels,
        "carve_stride": stride,
        "carve_rays": int(np.ceil(480 / stride) * np.ceil(640 / stride)),
        "target_ms": TARGET_MS,
        "repeats": repeats,
        "cpu_count": os.cpu_count(),
        "load_average_before": load_before,
        "load_average_after": os.getloadavg(),
    }
    if print_table:
        _print_table(figures)
    return figures


def _print_table(figures: dict) -> None:
    from rich.console import Console
    from rich.table import Table

    table = Table(
        title=f"area3d_perception, 640x480 frame, {figures['grid_voxels']:,} voxels, "
        f"median (p10-p90) of {figures['repeats']}"
    )
    columns = ("step", "wall ms", "CPU ms", "target ms", "ratio wall / CPU")
    for column in columns:
        table.add_column(column, justify="right" if column != "step" else "left")
    rows = [
        ("perception node frame, all but publish", "node_frame"),
        ("  rgbd confidence", "rgbd_confidence"),
        ("depth noise (the simulated camera's, in sim_bridge)", "depth_noise"),
        ("back-project + splat", "splat"),
        (
            f"carve (stride {figures['carve_stride']}, {figures['carve_rays']:,} rays)",
            "carve",
        ),
    ]

    def ratio(ms: float) -> str:
        style = "green" if ms <= TARGET_MS else "red"
        return f"[{style}]{ms / TARGET_MS:.2f}[/{style}]"

    for label, key in rows:
        t = figures["steps"][key]
        table.add_row(
            label,
            f"{t['wall']:.1f} ({t['wall_p10']:.1f}-{t['wall_p90']:.1f})",
            f"{t['cpu']:.1f} ({t['cpu_p10']:.1f}-{t['cpu_p90']:.1f})",
            f"{TARGET_MS:.0f}",
            f"{ratio(t['wall'])} / {ratio(t['cpu'])}",
        )
    Console(width=max(Console().width, 112)).print(table)
    before = "/".join(f"{x:.2f}" for x in figures["load_average_before"])
    after = "/".join(f"{x:.2f}" for x in figures["load_average_after"])
    print(
        f"load average (1/5/15 min) before {before}, after {after}, on {figures['cpu_count']} "
        "CPUs; the node frame decodes colour + depth, computes the confidence and builds both "
        "output messages (the depth noise is the simulated camera's, not perception's)"
    )


if __name__ == "__main__":
    run_bench()
