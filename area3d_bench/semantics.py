"""Semantics benchmark: parse + weight maps + U_sem for a room-level query (15 views, 640x480)."""

from __future__ import annotations

import time

import cv2
import numpy as np
from rich.console import Console
from rich.table import Table

from area3d_semantics.backends import HeuristicBackend
from area3d_semantics.parser import parse_answer
from area3d_semantics.weights import (
    SemanticParams,
    semantic_uncertainty,
    sigma_from_confidence,
    weight_map,
)

TARGET_MS = (
    100.0  # parse + masks + weights + U_sem for 15 views must stay well inside one frame period
)


def _views(n: int, height: int, width: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    images, depths, confidences = [], [], []
    for _ in range(n):
        coarse = rng.integers(40, 220, (height // 16, width // 16, 3)).astype(np.uint8)
        image = cv2.resize(coarse, (width, height), interpolation=cv2.INTER_LINEAR)
        image[rng.integers(0, height // 2) :][: height // 6, : width // 5] = 255
        depth = np.full((height, width), 3.0, np.float32)
        depth[:, rng.integers(width // 4, 3 * width // 4) :] = 1.5
        images.append(image)
        depths.append(depth)
        confidences.append(rng.uniform(0, 1, (height, width)).astype(np.float32))
    return images, depths, confidences


def run_bench(num_views: int = 15, height: int = 480, width: int = 640, repeats: int = 5) -> dict:
    """Time each stage (best of `repeats`), print a table, return the figures in milliseconds."""
    images, depths, confidences = _views(num_views, height, width)
    params = SemanticParams()
    backend = HeuristicBackend()
    best = {"heuristic_ms": np.inf, "parse_ms": np.inf, "weights_ms": np.inf, "usem_ms": np.inf}
    regions = 0
    totals = []  # parse + weights + U_sem of each repeat
    for repeat in range(repeats + 1):  # the first one warms up (loads the numba kernels)
        t0 = time.perf_counter()
        answer = backend.analyze(images, depths)
        t1 = time.perf_counter()
        parsed = parse_answer(answer, num_views)
        t2 = time.perf_counter()
        maps = [weight_map(parsed.regions_of(i), height, width, params) for i in range(num_views)]
        t3 = time.perf_counter()
        for conf, w in zip(confidences, maps, strict=True):
            semantic_uncertainty(sigma_from_confidence(conf), w, params.lam)
        t4 = time.perf_counter()
        regions = len(parsed.regions)
        if repeat == 0:
            continue
        totals.append((t4 - t1) * 1e3)
        for key, dt in zip(best, (t1 - t0, t2 - t1, t3 - t2, t4 - t3), strict=True):
            best[key] = min(best[key], dt * 1e3)
    total = best["parse_ms"] + best["weights_ms"] + best["usem_ms"]
    figures = {
        **best,
        "total_ms": total,
        "total_mean_ms": float(np.mean(totals)),
        "total_std_ms": float(np.std(totals)),
        "target_ms": TARGET_MS,
        "regions": regions,
        "views": num_views,
    }

    table = Table(
        title=f"area3d_semantics: {num_views} views at {width}x{height}, {regions} regions"
    )
    for column in ("stage", "ms", "target ms", "target / measured"):
        table.add_column(column, justify="right" if column != "stage" else "left")
    table.add_row("heuristic analyzer (answer text)", f"{best['heuristic_ms']:.1f}", "-", "-")
    table.add_row("parse answer", f"{best['parse_ms']:.2f}", "", "")
    table.add_row("masks + weight maps", f"{best['weights_ms']:.2f}", "", "")
    table.add_row("U_sem", f"{best['usem_ms']:.2f}", "", "")
    table.add_row(
        "parse + weights + U_sem", f"{total:.1f}", f"{TARGET_MS:.0f}", f"{TARGET_MS / total:.1f}x"
    )
    Console().print(table)
    print(
        f"parse + weights + U_sem over {repeats} repeats: mean {figures['total_mean_ms']:.1f} "
        f"+- {figures['total_std_ms']:.1f} ms (sum of the best stages {total:.1f} ms), "
        f"target {TARGET_MS:.0f} ms"
    )
    return figures


if __name__ == "__main__":
    run_bench()
