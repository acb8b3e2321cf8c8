"""Per-frame cost of perception: sensor confidence + noise, splatting and free-space carving.

A synthetic 640x480 frame (a sphere in front of a wall, 90 degree field of view) is processed
against a 100^3 = 1M-voxel grid that the whole frustum crosses; each figure is the median of
`repeats` runs after one warm-up (which also compiles the numba kernels).
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

from area3d_perception.geometric import CARVE_STRIDE, carve_depth_frame, splat_depth_frame
from area3d_perception.grid import GridSpec
from area3d_perception.sensor_model import RgbdSensorParams, add_depth_noise, rgbd_confidence

# Every per-frame step should keep up with a 30 Hz camera on 2 CPU cores.
TARGET_MS = 30.0


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


def _median_ms(fn: Callable[[], object], repeats: int, cpu: dict | None = None) -> float:
    """Median wall time of `fn` in ms; `cpu` (optional) gets {"median", "p10", "p90"} of its
    process CPU time, which other work on a shared machine inflates far less than the wall time."""
    fn()
    times, cpu_times = [], []
    for _ in range(repeats):
        start, start_cpu = time.perf_counter(), time.process_time()
        fn()
        times.append((time.perf_counter() - start) * 1e3)
        cpu_times.append((time.process_time() - start_cpu) * 1e3)
    if cpu is not None:
        cpu.update(
            median=float(np.median(cpu_times)),
            p10=float(np.percentile(cpu_times, 10)),
            p90=float(np.percentile(cpu_times, 90)),
            wall_p10=float(np.percentile(times, 10)),
            wall_p90=float(np.percentile(times, 90)),
        )
    return float(np.median(times))


def run_bench(repeats: int = 15, stride: int = CARVE_STRIDE, print_table: bool = True) -> dict:
    """Time the per-frame steps; returns {name: milliseconds} plus the setup figures."""
    depth, K, T = synthetic_frame()
    params = RgbdSensorParams()
    rng = np.random.default_rng(0)
    spec = GridSpec.from_bounds(np.array([-1.0, -1.0, 0.0]), np.array([1.0, 1.0, 2.0]), 0.02)
    evidence = np.zeros(spec.shape, np.float32)
    hits = np.zeros(spec.shape, np.float32)
    free = np.zeros(spec.shape, np.uint16)
    conf = rgbd_confidence(depth, K, params)

    def conf_and_noise() -> None:
        noisy = add_depth_noise(depth, K, rng, params)
        rgbd_confidence(noisy, K, params)

    def carve() -> None:
        free[:] = 0  # keep the uint16 counter far from overflow across repeats
        carve_depth_frame(spec, depth, K, T, free, stride=stride)

    frame_spread: dict = {}
    figures = {
        "rgbd_confidence_ms": _median_ms(lambda: rgbd_confidence(depth, K, params), repeats),
        "depth_noise_ms": _median_ms(lambda: add_depth_noise(depth, K, rng, params), repeats),
        "rgbd_frame_ms": _median_ms(conf_and_noise, repeats, frame_spread),
        "splat_ms": _median_ms(
            lambda: splat_depth_frame(spec, depth, conf, K, T, evidence, hits), repeats
        ),
        "carve_ms": _median_ms(carve, repeats),
    }
    figures.update(
        {
            "image": "640x480",
            "grid_voxels": spec.num_voxels,
            "carve_stride": stride,
            "carve_rays": int(np.ceil(480 / stride) * np.ceil(640 / stride)),
            "target_ms": TARGET_MS,
            "rgbd_frame_spread_ms": frame_spread,
        }
    )
    if print_table:
        _print_table(figures)
    return figures


def _print_table(figures: dict) -> None:
    from rich.console import Console
    from rich.table import Table

    table = Table(title=f"area3d_perception, 640x480 frame, {figures['grid_voxels']:,} voxels")
    for column in ("step", "ms", "target ms", "ratio"):
        table.add_column(column, justify="right" if column != "step" else "left")
    rows = [
        ("rgbd confidence", "rgbd_confidence_ms"),
        ("depth noise", "depth_noise_ms"),
        ("rgbd frame (noise + confidence)", "rgbd_frame_ms"),
        ("back-project + splat", "splat_ms"),
        (
            f"carve free space (stride {figures['carve_stride']}, {figures['carve_rays']:,} rays)",
            "carve_ms",
        ),
    ]
    for label, key in rows:
        ms = figures[key]
        ratio = ms / TARGET_MS
        style = "green" if ratio <= 1.0 else "red"
        table.add_row(label, f"{ms:.1f}", f"{TARGET_MS:.0f}", f"[{style}]{ratio:.2f}[/{style}]")
    Console().print(table)
    spread = figures["rgbd_frame_spread_ms"]
    print(
        f"rgbd frame: wall p10-p90 {spread['wall_p10']:.1f}-{spread['wall_p90']:.1f} ms; "
        f"process CPU median {spread['median']:.1f} ms (p10-p90 {spread['p10']:.1f}-"
        f"{spread['p90']:.1f}), target {TARGET_MS:.0f} ms"
    )


if __name__ == "__main__":
    run_bench()
