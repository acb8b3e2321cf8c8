"""Planner benchmark: visibility-cache build and 40-view selection, lazy vs plain greedy.

Grids: the largest bundled room scene at 5 cm (initial views rendered and fused with confidence 1)
when sim_bridge can render, and a synthetic room-like grid of 10^6 voxels.
"""

from __future__ import annotations

import itertools
import time

import numpy as np

from area3d_bench.closed_loop import (
    CLOSED_LOOP_TARGET_S,
    LOADED_BURNERS,
    bench_closed_loop,
    planner_overrides,
)
from area3d_bench.frames import object_frames
from area3d_bench.planner_service import TARGET_ROUND_TRIP_P95_S
from area3d_msgs_py.grid import GridSpec
from area3d_msgs_py.lifecycle import tune_process
from area3d_planner.candidates import VisibilityParams
from area3d_planner.fusion import FusedGrid
from area3d_planner.greedy import GreedyParams, lazy_greedy, plain_greedy

TARGET_CACHE_S = 5.0
TARGET_SELECT_S = 1.0
TARGET_SPEEDUP = 10.0
TARGET_SCORE_ERROR = 0.05  # median |score - reference| / reference, reference 16x the pixels


def synthetic_room(
    n: int = 100, voxel_size: float = 0.05, seed: int = 0
) -> tuple[FusedGrid, np.ndarray, np.ndarray]:
    """n^3 voxel room: walls, floor, ceiling, furniture boxes; space seen from the middle is free,
    what the boxes hide stays unknown. Returns (grid, workspace_lo, workspace_hi)."""
    rng = np.random.default_rng(seed)
    extent = n * voxel_size
    spec = GridSpec.from_bounds(np.zeros(3), np.full(3, extent), voxel_size)
    grid = FusedGrid(spec, np.zeros(3), np.full(3, extent), gamma=0.005)
    occ = np.zeros(spec.shape, np.int8)
    occ[[0, -1], :, :] = 1
    occ[:, [0, -1], :] = 1
    occ[:, :, [0, -1]] = 1
    for _ in range(25):
        lo = rng.integers(5, n - 20, 3)
        lo[2] = 1
        size = rng.integers(4, 16, 3)
        occ[lo[0] : lo[0] + size[0], lo[1] : lo[1] + size[1], lo[2] : lo[2] + size[2]] = 1
        # the far side of each box and the space under/behind it are unobserved
        occ[
            lo[0] + size[0] : lo[0] + size[0] + 6, lo[1] : lo[1] + size[1], 1 : lo[2] + size[2]
        ] = -1
    flat = occ.ravel()
    grid.hit_count[flat == 1] = 1
    grid.conf_sum[flat == 1] = rng.random(int((flat == 1).sum())).astype(np.float32)
    grid.free_count[flat == 0] = 1
    ws_lo = np.array([0.5, 0.5, 0.5]) * extent / 5
    ws_hi = np.array([4.5, 4.5, 2.0]) * extent / 5
    return grid, ws_lo, ws_hi


def room_scene_grid() -> tuple[FusedGrid, np.ndarray, np.ndarray, str]:
    """Largest bundled room scene at 5 cm, fused from its rendered initial views."""
    from sim_bridge.render import RgbdRenderer
    from sim_bridge.scenes import list_scenes, load_scene

    rooms = [load_scene(n) for n in list_scenes()]
    rooms = [s for s in rooms if s.level == "room"]
    scene = max(rooms, key=lambda s: float(np.prod(s.roi_max - s.roi_min)))
    lo = np.minimum(scene.workspace_min, scene.roi_min)
    hi = np.maximum(scene.workspace_max, scene.roi_max)
    grid = FusedGrid(
        GridSpec.from_bounds(lo, hi, 0.05), scene.roi_min, scene.roi_max, gamma=scene.gamma
    )
    renderer = RgbdRenderer(scene)
    try:
        for T in scene.initial_views:
            _, depth = renderer.render(T)
            grid.integrate_depth(depth, np.ones_like(depth), renderer.K, T, 5.0, 2)
    finally:
        renderer.close()
    return grid, scene.workspace_min, scene.workspace_max, scene.name


def bench_grid(
    grid: FusedGrid, ws_lo, ws_hi, seed_spacing: float, views: int, params: VisibilityParams
) -> dict:
    """Candidates and masks built as the planner builds them (a room-level lattice in known-free
    space; the boundary of carved space occludes and is recorded), then a batch of `views` by lazy
    and by plain greedy."""
    from dataclasses import replace

    from area3d_planner.context import PlanningContext

    occ = grid.occupancy()
    context = PlanningContext(
        grid=grid,
        workspace_lo=np.asarray(ws_lo, float),
        workspace_hi=np.asarray(ws_hi, float),
        visibility=replace(params, seed_spacing=seed_spacing),
    )
    t0 = time.perf_counter()
    _, caches = context.build(occ, ("roi_not_free",))
    t_cache = time.perf_counter() - t0
    cache = caches["roi_not_free"].bind(context.evidence())  # scored as the planner scores
    U = grid.fused()
    gp = GreedyParams()
    t0 = time.perf_counter()
    lazy = lazy_greedy(cache, U, views, gp)
    t_lazy = time.perf_counter() - t0
    t0 = time.perf_counter()
    plain = plain_greedy(cache, U, views, gp)
    t_plain = time.perf_counter() - t0
    return {
        "voxels": grid.spec.num_voxels,
        "seeds": cache.num_seeds,
        "views": cache.num_views,
        "mask_entries": int(cache.voxel_ids.size),
        "cache_build_s": t_cache,
        "lazy_select_s": t_lazy,
        "plain_select_s": t_plain,
        "speedup": t_plain / max(t_lazy, 1e-9),
        "lazy_evaluations": lazy.evaluations,
        "plain_evaluations": plain.evaluations,
        "identical": lazy.views == plain.views,
        "selected": len(lazy.views),
    }


def bench_visibility_accuracy(scene_name: str) -> dict:
    """Median relative error of every candidate view's score (utility after the initial views)
    at the level's default `face_res` against a buffer with 16x the pixels (4x `face_res`), with
    the same candidates, occluders and field."""
    from dataclasses import replace

    from area3d_perception.sensor_model import rgbd_confidence
    from area3d_planner.config import PlannerConfig
    from area3d_planner.server import NextBestViewServer
    from sim_bridge.render import RgbdRenderer
    from sim_bridge.scenes import load_scene

    scene = load_scene(scene_name)
    config = PlannerConfig(**{**planner_overrides(scene), "mode": "closed_loop", "budget": 10**6})
    server = NextBestViewServer(config)
    renderer = RgbdRenderer(scene)
    try:
        for stamp, T in enumerate(scene.initial_views, start=1):
            _, depth = renderer.render(T)
            server.add_frame(stamp, depth, rgbd_confidence(depth, renderer.K), renderer.K, T)
    finally:
        renderer.close()
    context = server.context
    occupancy = context.grid.occupancy()
    candidates = context.candidate_views(occupancy)
    field = context.grid.fused()
    face_res = context.visibility.face_res
    scores = {}
    for res in (face_res, 4 * face_res):
        context.visibility = replace(context.visibility, face_res=res)
        cache = context._build_cache("roi_not_free", occupancy, *candidates)
        scores[res] = cache.score(field)
    context.visibility = replace(context.visibility, face_res=face_res)
    reference = scores[4 * face_res]
    useful = reference > 0
    error = np.abs(scores[face_res][useful] - reference[useful]) / reference[useful]
    return {
        "level": config.resolved_level(),
        "face_res": face_res,
        "views": int(useful.sum()),
        "median_error": float(np.median(error)),
        "p90_error": float(np.percentile(error, 90)),
        # the reference score of the view ranked best, over the reference's best score
        "best_view_ratio": float(reference[np.argmax(scores[face_res])] / reference.max()),
    }


def bench_server(requests: int = 50) -> dict:
    """In-process `PlannerScheduler.plan` for one closed-loop view with a warm cache (object
    level, the scene's initial views fused), and the background refresh after one more frame."""
    from area3d_planner.config import PlannerConfig
    from area3d_planner.requests import PlanRequest
    from area3d_planner.scheduler import PlannerScheduler, SchedulerConfig

    scene, frames = object_frames()
    config = PlannerConfig(**{**planner_overrides(scene), "mode": "closed_loop", "budget": 10**6})
    server = PlannerScheduler(config, SchedulerConfig(refresh_interval_s=0.0))
    try:
        t0 = time.perf_counter()
        for i, (depth, conf, K, T) in enumerate(frames):
            server.add_frame(i + 1, depth, conf, K, T)
        t_fuse = time.perf_counter() - t0
        server.wait_cache(len(frames))
        t_ready = time.perf_counter() - t0
        latencies = []
        for _ in range(requests):
            t0 = time.perf_counter()
            poses, reason = server.plan(PlanRequest(frames[-1][3], len(frames), 1))
            latencies.append(time.perf_counter() - t0)
            if reason:
                raise RuntimeError(reason)
        depth, conf, K, T = frames[0]
        server.add_frame(len(frames) + 1, depth, conf, K, T)
        t0 = time.perf_counter()
        server.wait_cache(len(frames) + 1)
        t_refresh = time.perf_counter() - t0
        cache = server.core.context.cache()
    finally:
        server.close()
    lat = np.asarray(latencies)
    return {
        "voxels": server.core.grid.spec.num_voxels,
        "seeds": cache.num_seeds,
        "mask_entries": int(cache.voxel_ids.size),
        "fuse_initial_s": t_fuse,
        "cache_ready_after_s": t_ready,
        "refresh_after_frame_s": t_refresh,
        "plan_p50_s": float(np.percentile(lat, 50)),
        "plan_p95_s": float(np.percentile(lat, 95)),
    }


def run_bench(
    views: int = 40,
    face_res: int = 128,  # the room level default
    synthetic_only: bool = False,
    print_table: bool = True,
    service: bool = True,
    transport: bool = True,
    requests: int = 50,
) -> dict:
    """Figures per grid (see bench_grid), the in-process plan latency (bench_server) and the
    GetPlan round trip between two processes (bench_transport); prints a rich table with targets
    and ratios. Parts that cannot run here (no renderer, no DDS) report their error.

    The process first takes the settings every node process runs with (`tune_process`: the 1 ms
    GIL switch interval, malloc's arenas and mapped blocks), so that the closed loop's threads
    (fusion, the background rebuild, the request) share the interpreter as in the planner node."""
    tune_process()
    params = VisibilityParams(level="room", face_res=face_res)
    # warm the numba kernels so compile time is not measured
    warm, lo, hi = synthetic_room(30, 0.2)
    bench_grid(warm, lo, hi, 2.0, 2, VisibilityParams(level="room", face_res=8))
    results: dict = {}
    if not synthetic_only:
        try:
            grid, lo, hi, name = room_scene_grid()
            results[f"scene:{name}"] = bench_grid(grid, lo, hi, 0.5, views, params)
        except Exception as exc:  # sim_bridge missing or no renderer: synthetic only
            results["scene"] = {"error": f"{type(exc).__name__}: {exc}"}
    grid, lo, hi = synthetic_room(100, 0.05)
    results["synthetic_1e6"] = bench_grid(grid, lo, hi, 0.5, views, params)
    if service and not synthetic_only:
        try:
            results["service:single_object"] = bench_server(requests)
        except Exception as exc:  # no renderer
            results["service:single_object"] = {"error": f"{type(exc).__name__}: {exc}"}
    if service and not synthetic_only:
        for name, pipelined, (burners, label) in itertools.product(
            ("single_object", "living_room"),
            (False, True),
            ((0, "quiet"), (LOADED_BURNERS, "loaded")),
        ):
            masks = "pipelined masks" if pipelined else "masks of its frame"
            key = f"closed_loop:{name} ({label}, {masks})"
            try:
                results[key] = bench_closed_loop(name, burners=burners, pipelined=pipelined)
            except Exception as exc:  # no renderer
                results[key] = {"error": f"{type(exc).__name__}: {exc}"}
    if not synthetic_only:
        for name in ("clutter7_a", "living_room"):
            try:
                results[f"visibility:{name}"] = bench_visibility_accuracy(name)
            except Exception as exc:  # no renderer
                results[f"visibility:{name}"] = {"error": f"{type(exc).__name__}: {exc}"}
    if transport and not synthetic_only:
        from area3d_bench.planner_service import bench_transport

        try:
            results["transport:single_object"] = bench_transport(requests)
        except Exception as exc:  # no DDS, or the node did not come up
            results["transport:single_object"] = {"error": f"{type(exc).__name__}: {exc}"}
    if print_table:
        _print(results, views)
    return results


def _print(results: dict, views: int) -> None:
    from rich.console import Console
    from rich.table import Table

    table = Table(title=f"area3d_planner: visibility cache and {views}-view selection")
    for col in ("grid", "figure", "value", "target", "ratio"):
        table.add_column(col)
    for name, r in results.items():
        if "error" in r:
            table.add_row(name, "skipped", r["error"], "", "")
            continue
        if name.startswith("service"):
            table.add_row(name, "voxels / seeds", f"{r['voxels']} / {r['seeds']}", "", "")
            table.add_row(name, "initial views fused", f"{r['fuse_initial_s']:.2f} s", "", "")
            table.add_row(name, "cache ready after", f"{r['cache_ready_after_s']:.2f} s", "", "")
            table.add_row(
                name, "background refresh, 1 frame", f"{r['refresh_after_frame_s']:.2f} s", "", ""
            )
            table.add_row(name, "plan 1 view p50", f"{r['plan_p50_s'] * 1e3:.1f} ms", "", "")
            _latency_row(table, name, "plan 1 view p95", r["plan_p95_s"])
            continue
        if name.startswith("closed_loop"):
            target = CLOSED_LOOP_TARGET_S[r["level"]]
            table.add_row(
                name,
                "voxels / steps / busy processes / load (1 min)",
                f"{r['voxels']} / {r['steps']} / {r['burners']} / {r['load']:.1f}",
                "",
                "",
            )
            table.add_row(name, "frame -> next view p50", f"{r['p50_s'] * 1e3:.0f} ms", "", "")
            table.add_row(
                name,
                "frame -> next view p95",
                f"{r['p95_s'] * 1e3:.0f} ms",
                f"< {target * 1e3:.0f} ms",
                f"{r['p95_s'] / target:.2f}",
            )
            table.add_row(
                name,
                "rebuild per frame p50 / p95: incremental",
                f"{r['rebuild_p50_s'] * 1e3:.0f} / {r['rebuild_p95_s'] * 1e3:.0f} ms",
                "",
                "",
            )
            table.add_row(
                name,
                "rebuild per frame p50 / p95: from nothing",
                f"{r['full_rebuild_p50_s'] * 1e3:.0f} / {r['full_rebuild_p95_s'] * 1e3:.0f} ms",
                "",
                f"{r['full_rebuild_p50_s'] / max(r['rebuild_p50_s'], 1e-9):.1f}x",
            )
            table.add_row(
                name,
                "positions updated / of them changed",
                f"{r['positions_updated']:.0%} / {r['positions_changed']:.0%}",
                "",
                "",
            )
            continue
        if name.startswith("visibility"):
            table.add_row(
                name, "views scored / face_res", f"{r['views']} / {r['face_res']}", "", ""
            )
            table.add_row(
                name,
                "score error vs 16x pixels, median",
                f"{r['median_error'] * 100:.1f} %",
                f"< {TARGET_SCORE_ERROR * 100:.0f} %",
                f"{r['median_error'] / TARGET_SCORE_ERROR:.2f}",
            )
            table.add_row(name, "score error, p90", f"{r['p90_error'] * 100:.1f} %", "", "")
            table.add_row(
                name, "best view's reference score / best", f"{r['best_view_ratio']:.3f}", "", ""
            )
            continue
        if name.startswith("transport"):
            table.add_row(
                name, "fused + cache ready", f"{r['fused_and_cache_ready_s']:.2f} s", "", ""
            )
            table.add_row(name, "round trip p50", f"{r['round_trip_p50_s'] * 1e3:.1f} ms", "", "")
            _latency_row(table, name, "round trip p95", r["round_trip_p95_s"])
            continue
        table.add_row(
            name, "voxels / seeds / views", f"{r['voxels']} / {r['seeds']} / {r['views']}", "", ""
        )
        table.add_row(name, "mask entries", f"{r['mask_entries']}", "", "")
        table.add_row(
            name,
            "cache build",
            f"{r['cache_build_s']:.2f} s",
            f"< {TARGET_CACHE_S} s",
            f"{r['cache_build_s'] / TARGET_CACHE_S:.2f}",
        )
        table.add_row(
            name,
            "lazy greedy",
            f"{r['lazy_select_s']:.3f} s",
            f"< {TARGET_SELECT_S} s",
            f"{r['lazy_select_s'] / TARGET_SELECT_S:.2f}",
        )
        table.add_row(name, "plain greedy", f"{r['plain_select_s']:.3f} s", "", "")
        table.add_row(
            name,
            "speed-up lazy vs plain",
            f"{r['speedup']:.1f}x",
            f">= {TARGET_SPEEDUP}x",
            f"{r['speedup'] / TARGET_SPEEDUP:.2f}",
        )
        table.add_row(
            name,
            "evaluations lazy / plain",
            f"{r['lazy_evaluations']} / {r['plain_evaluations']}",
            "",
            "",
        )
        table.add_row(name, "identical choices", str(r["identical"]), "True", "")
    Console().print(table)


def _latency_row(table, name: str, figure: str, seconds: float) -> None:
    table.add_row(
        name,
        figure,
        f"{seconds * 1e3:.1f} ms",
        f"< {TARGET_ROUND_TRIP_P95_S * 1e3:.0f} ms",
        f"{seconds / TARGET_ROUND_TRIP_P95_S:.2f}",
    )


if __name__ == "__main__":
    run_bench()
