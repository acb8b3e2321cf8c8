"""Reconstruction benchmark: what one integrated frame costs the reconstruction node (integrate,
extract the mesh, encode its marker), and what a save and a load of the planner's map and of the
volume cost, at object and room level.

Frames: a bundled scene's initial and held-out views rendered once at 640x480 with the RGB-D
sensor model's confidence, integrated in order as the node integrates them (the node's own code:
`TsdfFusion` at the level's settings, `codecs.mesh_marker_cdr`). The planner's map is that of the
same frames fused by `NextBestViewServer` with the scene's region. Files go to a temporary
directory on the machine's disk.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np

TARGET_MESH_UPDATE_P95_S = {"object": 0.05, "room": 0.3}
TARGET_SAVE_LOAD_S = 2.0
SCENES = {"object": "single_object", "room": "living_room"}


def _p(values: list[float], q: float) -> float:
    return float(np.percentile(values, q)) if values else float("nan")


def bench_level(level: str) -> dict:
    """Per-frame seconds to integrate, extract the mesh and encode it; save/load of the planner's
    map and of the volume: seconds and bytes."""
    from area3d_bench.frames import render_views
    from area3d_bringup.launch_description import planner_region
    from area3d_eval.reconstruct import TsdfFusion, TsdfParams
    from area3d_msgs_py import codecs
    from area3d_perception.sensor_model import rgbd_confidence
    from area3d_planner import map_io as planner_map
    from area3d_planner.config import PlannerConfig
    from area3d_planner.server import NextBestViewServer
    from area3d_reconstruction import map_io as volume_map

    scene, frames = render_views(SCENES[level], held_out=True)
    fusion = TsdfFusion(TsdfParams.for_level(level), scene.roi_min, scene.roi_max)
    integrate, extract, encode, triangles = [], [], [], []
    for rgb, depth, K, T in frames:
        confidence = rgbd_confidence(depth, K)
        t0 = time.perf_counter()
        fusion.integrate(rgb, depth, K, T, confidence)
        t1 = time.perf_counter()
        vertices, faces, colours = fusion.surface_arrays()  # what the node publishes
        t2 = time.perf_counter()
        codecs.mesh_marker_cdr(vertices, faces, colours, 1, "world")
        t3 = time.perf_counter()
        integrate.append(t1 - t0)
        extract.append(t2 - t1)
        encode.append(t3 - t2)
        triangles.append(len(faces))
    update = [a + b + c for a, b, c in zip(integrate, extract, encode, strict=True)]
    out = {
        "scene": scene.name,
        "frames": len(frames),
        "triangles": triangles[-1],
        "integrate_p95_s": _p(integrate[1:], 95),  # the first frame loads the compiled kernel
        "extract_p95_s": _p(extract[1:], 95),
        "encode_p95_s": _p(encode[1:], 95),
        "update_p50_s": _p(update[1:], 50),
        "update_p95_s": _p(update[1:], 95),
        "target_update_p95_s": TARGET_MESH_UPDATE_P95_S[level],
    }
    server = NextBestViewServer(PlannerConfig(**planner_region(scene), gamma=float(scene.gamma)))
    for i, (_, depth, K, T) in enumerate(frames):
        server.add_frame(i + 1, depth, rgbd_confidence(depth, K), K, T)
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "planner.a3map"
        t0 = time.perf_counter()
        _, size, _ = planner_map.save(server, path)
        t1 = time.perf_counter()
        fresh = NextBestViewServer(server.config)
        planner_map.restore(fresh, planner_map.read(fresh, path))
        t2 = time.perf_counter()
        out |= {"planner_save_s": t1 - t0, "planner_load_s": t2 - t1, "planner_bytes": size}
        path = Path(folder) / "volume.a3map"
        t0 = time.perf_counter()
        _, size = volume_map.save(fusion, list(range(len(frames))), path)
        t1 = time.perf_counter()
        other = TsdfFusion(fusion.params, fusion.roi_lo, fusion.roi_hi)
        volume_map.restore(other, volume_map.read(other, path))
        t2 = time.perf_counter()
        out |= {"volume_save_s": t1 - t0, "volume_load_s": t2 - t1, "volume_bytes": size}
    out["target_save_load_s"] = TARGET_SAVE_LOAD_S
    return out


def _reconstruct_forever(scene_name: str, level: str, ready, stop) -> None:
    """A reconstruction node's work without transport, as fast as it goes: the scene's views
    integrated one after the other, each followed by the mesh's extraction and encoding, over
    and over (a fresh volume every pass) until `stop` is set."""
    from area3d_bench.frames import render_views
    from area3d_eval.reconstruct import TsdfFusion, TsdfParams
    from area3d_msgs_py import codecs
    from area3d_perception.sensor_model import rgbd_confidence

    scene, frames = render_views(scene_name, held_out=True)
    inputs = [(rgb, depth, K, T, rgbd_confidence(depth, K)) for rgb, depth, K, T in frames]
    ready.set()
    while not stop.is_set():
        fusion = TsdfFusion(TsdfParams.for_level(level), scene.roi_min, scene.roi_max)
        for rgb, depth, K, T, confidence in inputs:
            if stop.is_set():
                return
            fusion.integrate(rgb, depth, K, T, confidence)
            codecs.mesh_marker_cdr(*fusion.surface_arrays(), 1, "world")


def closed_loop_beside(level: str) -> dict:
    """The planner's closed loop (`bench_closed_loop`, masks pipelined as the bundled
    configuration has them) alone, then with a reconstruction process beside it that never
    rests (a worst case: the node integrates one frame per view): p95 latency of each."""
    import multiprocessing

    from area3d_bench.closed_loop import CLOSED_LOOP_TARGET_S, bench_closed_loop

    alone = bench_closed_loop(SCENES[level], pipelined=True)
    context = multiprocessing.get_context("spawn")
    ready, stop = context.Event(), context.Event()
    worker = context.Process(target=_reconstruct_forever, args=(SCENES[level], level, ready, stop))
    worker.start()
    try:
        ready.wait(300)
        beside = bench_closed_loop(SCENES[level], pipelined=True)
    finally:
        stop.set()
        worker.join(60)
        if worker.is_alive():
            worker.kill()
    return {
        "alone_p95_s": alone["p95_s"],
        "beside_p95_s": beside["p95_s"],
        "target_s": CLOSED_LOOP_TARGET_S[level],
    }


def run_bench(print_table: bool = True, closed_loop: bool = True) -> dict:
    """Both levels; a table of figures beside their targets and the ratio figure / target."""
    from area3d_msgs_py.lifecycle import tune_process

    tune_process()
    results = {level: bench_level(level) for level in SCENES}
    if closed_loop:
        for level in SCENES:
            results[level] |= {f"closed_loop_{k}": v for k, v in closed_loop_beside(level).items()}
    if print_table:
        from rich.console import Console
        from rich.table import Table

        table = Table(title="reconstruction: per integrated frame, and save / load")
        for column in ("level", "figure", "measured", "target", "ratio"):
            table.add_column(column)
        for level, r in results.items():
            rows = [
                ("frames / final triangles", f"{r['frames']} / {r['triangles']}", "", ""),
                ("integrate p95 (s)", f"{r['integrate_p95_s']:.4f}", "", ""),
                ("extract mesh p95 (s)", f"{r['extract_p95_s']:.4f}", "", ""),
                ("encode marker p95 (s)", f"{r['encode_p95_s']:.4f}", "", ""),
                (
                    "mesh update p95 (s)",
                    f"{r['update_p95_s']:.4f}",
                    f"< {r['target_update_p95_s']}",
                    f"{r['update_p95_s'] / r['target_update_p95_s']:.2f}",
                ),
            ]
            for what in ("planner", "volume"):
                for op in ("save", "load"):
                    s = r[f"{what}_{op}_s"]
                    rows.append(
                        (
                            f"{what} {op} (s; {r[f'{what}_bytes'] / 1e6:.1f} MB)",
                            f"{s:.3f}",
                            f"< {TARGET_SAVE_LOAD_S}",
                            f"{s / TARGET_SAVE_LOAD_S:.2f}",
                        )
                    )
            if "closed_loop_alone_p95_s" in r:
                target = r["closed_loop_target_s"]
                for label, key in (
                    ("alone", "alone_p95_s"),
                    ("reconstruction beside", "beside_p95_s"),
                ):
                    value = r[f"closed_loop_{key}"]
                    rows.append(
                        (
                            f"planner closed loop p95 (s), {label}",
                            f"{value:.3f}",
                            f"< {target}",
                            f"{value / target:.2f}",
                        )
                    )
            for row in rows:
                table.add_row(f"{level} ({r['scene']})", *row)
        Console().print(table)
    return results
