"""Planner benchmark: visibility-cache build and 40-view selection, lazy vs plain greedy.

Grids: the largest bundled room scene at 5 cm (initial views rendered and fused with confidence 1)
when sim_bridge can render, and a synthetic room-like grid of 10^6 voxels.
"""

from __future__ import annotations

import time

import numpy as np

from area3d_perception.grid import GridSpec
from area3d_planner.fusion import FREE, FusedGrid
from area3d_planner.greedy import GreedyParams, lazy_greedy, plain_greedy
from area3d_planner.visibility import VisibilityCache, VisibilityParams, candidate_seeds

TARGET_CACHE_S = 5.0
TARGET_SELECT_S = 1.0
TARGET_SPEEDUP = 10.0


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
    occ = grid.occupancy()
    seeds = candidate_seeds(ws_lo, ws_hi, seed_spacing, grid.spec, occ, allow_unknown=True)
    relevant = grid.roi_mask & (occ != FREE)
    t0 = time.perf_counter()
    cache = VisibilityCache.build(grid.spec, occ, seeds, params, relevant=relevant)
    t_cache = time.perf_counter() - t0
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


def run_bench(
    views: int = 40, mc_rays: int = 256, synthetic_only: bool = False, print_table: bool = True
) -> dict:
    """Figures per grid (see bench_grid); prints a rich table with targets and ratios."""
    params = VisibilityParams(mc_rays=mc_rays)
    # warm the numba kernels so compile time is not measured
    warm, lo, hi = synthetic_room(30, 0.2)
    bench_grid(warm, lo, hi, 2.0, 2, VisibilityParams(mc_rays=8))
    results: dict = {}
    if not synthetic_only:
        try:
            grid, lo, hi, name = room_scene_grid()
            results[f"scene:{name}"] = bench_grid(grid, lo, hi, 0.5, views, params)
        except Exception as exc:  # sim_bridge missing or no renderer: synthetic only
            results["scene"] = {"error": f"{type(exc).__name__}: {exc}"}
    grid, lo, hi = synthetic_room(100, 0.05)
    results["synthetic_1e6"] = bench_grid(grid, lo, hi, 0.5, views, params)
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


if __name__ == "__main__":
    run_bench()
