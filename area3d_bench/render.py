"""Render speed of the simulated RGB-D camera: frames per second at 640x480, RGB + depth, per scene."""

from __future__ import annotations

import time

import numpy as np
from rich.console import Console
from rich.table import Table

from sim_bridge.render import RgbdRenderer
from sim_bridge.scenes import list_scenes, load_scene
from sim_bridge.validity import check_pose, valid_positions

TARGET_FPS_OBJECT = 15.0  # object scenes: fast enough for interactive closed-loop episodes
TARGET_FPS_ROOM = 5.0
TARGET_CHECK_POSE_MS = 1.0  # the planner may check thousands of seeds


def run_bench(
    scenes: list[str] | None = None, frames: int = 30, width: int = 640, height: int = 480
) -> dict:
    """Time `frames` renders of each scene's views; returns {scene: {fps, ms_per_frame, ...}}."""
    names = scenes or list_scenes()
    results: dict[str, dict] = {}
    for name in names:
        scene = load_scene(name)
        views = np.concatenate([scene.initial_views, scene.eval_views])
        with RgbdRenderer(scene, width, height) as renderer:
            renderer.render(views[0])  # warm-up: texture upload, shader compile
            t0 = time.perf_counter()
            for i in range(frames):
                renderer.render(views[i % len(views)])
            elapsed = time.perf_counter() - t0
        check_pose(scene, views[0])  # builds the collision structures once
        t0 = time.perf_counter()
        for T in views:
            check_pose(scene, T)
        check_ms = (time.perf_counter() - t0) / len(views) * 1e3
        seeds = np.random.default_rng(0).uniform(
            scene.workspace_min, scene.workspace_max, (10000, 3)
        )
        t0 = time.perf_counter()
        valid_positions(scene, seeds)
        seeds_ms = (time.perf_counter() - t0) * 1e3
        fps = frames / elapsed
        target = TARGET_FPS_OBJECT if scene.level == "object" else TARGET_FPS_ROOM
        results[name] = {
            "level": scene.level,
            "fps": fps,
            "ms_per_frame": 1e3 * elapsed / frames,
            "target_fps": target,
            "ratio": fps / target,
            "check_pose_ms": check_ms,
            "valid_positions_10k_ms": seeds_ms,
        }
    table = Table(title=f"sim_bridge: {width}x{height} RGB-D rendering ({frames} frames per scene)")
    for col in (
        "scene",
        "level",
        "fps",
        "target",
        "ratio",
        "ms/frame",
        "pose check ms",
        "target",
        "10k seeds ms",
    ):
        table.add_column(col, justify="right" if col not in ("scene", "level") else "left")
    for name, r in results.items():
        table.add_row(
            name,
            r["level"],
            f"{r['fps']:.1f}",
            f"{r['target_fps']:.0f}",
            f"{r['ratio']:.2f}",
            f"{r['ms_per_frame']:.1f}",
            f"{r['check_pose_ms']:.3f}",
            f"{TARGET_CHECK_POSE_MS:.1f}",
            f"{r['valid_positions_10k_ms']:.1f}",
        )
    Console(width=max(Console().width, 110)).print(table)
    return results


if __name__ == "__main__":
    run_bench()
