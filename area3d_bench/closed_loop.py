"""Planner benchmark, the closed loop: frame captured -> next view answered, as the nodes run it,
quiet and beside busy processes, with each step's incremental rebuild beside a rebuild from nothing.
"""

from __future__ import annotations

import contextlib
import os
import subprocess
import time

import numpy as np


def planner_overrides(scene) -> dict:
    """What the planner node is told about a scene, as PlannerConfig values."""
    from area3d_bringup.launch_description import planner_region

    return {k: tuple(v) if isinstance(v, list) else v for k, v in planner_region(scene).items()}


CLOSED_LOOP_TARGET_S = {"object": 0.08, "room": 0.3}  # frame captured -> next view answered, p95
# steps per run: enough for a p95 that is not just the slowest step where a step is cheap (an
# object's, a few tenths of a second with the rebuild from nothing beside it); a room's step
# takes seconds
CLOSED_LOOP_STEPS = {"object": 40, "room": 12}
LOADED_BURNERS = (
    2  # busy processes beside the loaded run (`yes > /dev/null`: load about 4 on 2 cores)
)


@contextlib.contextmanager
def _burners(count: int):
    """`count` processes that keep a core busy each (`yes > /dev/null`) while the block runs."""
    procs = [subprocess.Popen(["yes"], stdout=subprocess.DEVNULL) for _ in range(count)]
    try:
        yield
    finally:
        for proc in procs:
            proc.kill()
            proc.wait()


def _full_rebuild_s(context, occupancy: np.ndarray) -> float:
    """Seconds the planner's rebuild of candidates and masks takes from nothing (no masks to
    update) for an occupancy snapshot."""
    from dataclasses import replace

    fresh = replace(context, _caches={}, _previous={}, _fields={}, _evidence=None)
    t0 = time.perf_counter()
    fresh.build(occupancy, ("roi_not_free",))
    return time.perf_counter() - t0


def bench_closed_loop(
    scene_name: str, steps: int | None = None, burners: int = 0, pipelined: bool = False
) -> dict:
    """Closed loop in one process, as the nodes run it: after the initial views, each step takes
    the frame captured at the last planned view through the sensor model's confidence, fusion, the
    background rebuild of candidates and masks (incremental), and one next-best-view request; the
    latency is from the rendered frame to the answer (rendering itself excluded). With
    `pipelined` (the planner's `pipeline_masks`) each request plans from the masks of the previous
    request's frame, and the rebuild for its own frame finishes after the answer, while the camera
    would move (not in the latency). Beside it, each step's rebuild from nothing on the
    same map (not in the latency), and with `burners` busy processes running (`_burners`), the
    load average over the run. `steps`: `CLOSED_LOOP_STEPS` of the scene's level by default."""
    from area3d_perception.sensor_model import rgbd_confidence
    from area3d_planner.config import PlannerConfig
    from area3d_planner.requests import PlanRequest
    from area3d_planner.scheduler import PlannerScheduler, SchedulerConfig
    from area3d_planner.server import CACHE_WAIT_S
    from sim_bridge.render import RgbdRenderer
    from sim_bridge.scenes import load_scene

    scene = load_scene(scene_name)
    steps = CLOSED_LOOP_STEPS[scene.level] if steps is None else steps
    config = PlannerConfig(
        **planner_overrides(scene),
        mode="closed_loop",
        budget=10**6,
        pipeline_masks=pipelined,
    )
    server = PlannerScheduler(config, SchedulerConfig(refresh_interval_s=0.0))
    renderer = RgbdRenderer(scene)
    latencies, incremental, full, updated, changed = [], [], [], [], []
    try:
        stamp = 0
        for T in scene.initial_views:
            stamp += 1
            _, depth = renderer.render(T)
            server.add_frame(stamp, depth, rgbd_confidence(depth, renderer.K), renderer.K, T)
        poses, reason = server.plan(PlanRequest(T, stamp, 1))
        with _burners(burners):
            time.sleep(2.0 if burners else 0.0)  # the busy processes get going
            for _ in range(steps):
                if reason:
                    raise RuntimeError(reason)
                T = poses[0]
                _, depth = renderer.render(T)
                t0 = time.perf_counter()
                stamp += 1
                server.add_frame(stamp, depth, rgbd_confidence(depth, renderer.K), renderer.K, T)
                poses, reason = server.plan(PlanRequest(T, stamp, 1))
                latencies.append(time.perf_counter() - t0)
                if not server.wait_cache(stamp, CACHE_WAIT_S):  # the camera moves meanwhile
                    raise RuntimeError(f"masks not rebuilt within {CACHE_WAIT_S} s")
                rebuild = dict(server.core.last_rebuild)
                incremental.append(rebuild["seconds"])
                updated.append(rebuild.get("updated", 0) / max(1, rebuild["positions"]))
                changed.append(rebuild.get("positions_changed", 0) / max(1, rebuild["positions"]))
                full.append(_full_rebuild_s(server.core.context, server.core.grid.occupancy()))
            load = os.getloadavg()[0]
    finally:
        renderer.close()
        server.close()
    lat = np.asarray(latencies)
    return {
        "level": scene.level,
        "voxels": server.core.grid.spec.num_voxels,
        "steps": len(latencies),
        "burners": burners,
        "pipelined": pipelined,
        "load": load,
        "p50_s": float(np.percentile(lat, 50)),
        "p95_s": float(np.percentile(lat, 95)),
        "rebuild_p50_s": float(np.percentile(incremental, 50)),
        "rebuild_p95_s": float(np.percentile(incremental, 95)),
        "full_rebuild_p50_s": float(np.percentile(full, 50)),
        "full_rebuild_p95_s": float(np.percentile(full, 95)),
        "positions_updated": float(np.mean(updated)),
        "positions_changed": float(np.mean(changed)),
    }
