"""Compile the numba kernels into their on-disk cache, ahead of the nodes that use them.

`make install` runs it once (`python -m area3d_bringup.kernels --part P ...`: the masks while
the ROS 2 interfaces build, the episodes after), so the first episode's node
processes load the kernels instead of compiling them while the graph runs (on a 2-core machine
compiling them all takes about 40 s of one core); the test suite runs it at its start
(`conftest.py`), where with the cache warm it takes a few seconds. Tiny in-process episodes and
the evaluation of one run every kernel family the nodes and the report use. A kernel whose
source changed later is compiled again where it is first called.

The work is split in three parts (`PARTS`) that compile different kernels, so that processes
running them at once share the compiling (numba compiles on one core; a cache file is written
whole by one process, so two processes compiling the same small kernel leave a valid cache):
- "masks": the planner's visibility masks of a box, built, then updated after the box changed
  (the incremental update's kernel alone takes 15-20 s to compile), and what the planner node
  loads when it starts (`greedy.warm_up_kernels`: the scoring of a list of views, which no
  episode's request uses, and the lazy greedy); no ROS 2 interface needed, so `make install`
  runs it while the interfaces build;
- "camera": an episode with camera depth and the area3d policy, budget 5 (one planned view: the
  masks built, never updated): the simulation, the sensor model, fusion, the selection;
- "stereo": an episode with stereo depth and the uniform policy (no masks) and its evaluation:
  the simulated pair, stereo matching, the metrics; and a frame integrated into a TSDF volume, as
  the reconstruction node integrates each frame (`_tsdf`).
The two episodes run the nodes' code in one process, which needs the interfaces. `main` runs the
three at once.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

SMALL = {"width": 160, "height": 120}
PARTS = ("masks", "camera", "stereo")


def warm_kernels(parts: tuple[str, ...] = PARTS) -> float:
    """Run the kernel families of `parts` once, in this process; returns the seconds it took."""
    t0 = time.monotonic()
    if "masks" in parts:
        _masks()
    for part in ("camera", "stereo"):
        if part in parts:
            _episode(part)
    if "stereo" in parts:
        _tsdf()
    return time.monotonic() - t0


def _masks() -> None:
    """The planner's visibility masks of a box in its region, built, then updated after part of
    the box turned free and a new part appeared (`incremental.py`), as the planner's context
    builds them (no frame fused: fusion is the other part's)."""
    import numpy as np

    from area3d_planner.config import PlannerConfig
    from area3d_planner.fusion import FREE, OCCUPIED, UNKNOWN

    config = PlannerConfig(mode="closed_loop", width=SMALL["width"], height=SMALL["height"])
    context = config.planning_context(config.fused_grid())
    occupancy = np.full(context.grid.spec.shape, FREE, np.int8)
    n = np.asarray(occupancy.shape)
    lo, hi = n * 2 // 5, n * 3 // 5
    box = (slice(lo[0], hi[0]), slice(lo[1], hi[1]), slice(0, hi[2]))
    occupancy[box] = OCCUPIED
    occupancy[lo[0] + 1 : hi[0] - 1, lo[1] + 1 : hi[1] - 1, : hi[2] - 1] = UNKNOWN
    context.install(*context.build(occupancy.ravel(), ("roi_not_free",)))
    occupancy[lo[0] : hi[0] // 2 + 1, lo[1] : hi[1], : hi[2]] = FREE
    occupancy[hi[0] : hi[0] + 2, lo[1] : hi[1], : hi[2] // 2] = OCCUPIED
    _, caches = context.build(occupancy.ravel(), ("roi_not_free",))
    if not caches["roi_not_free"].report.get("updated"):
        raise RuntimeError("the masks were not updated: the update's kernel was not compiled")
    from area3d_planner.greedy import warm_up_kernels

    warm_up_kernels()  # the planner node's own, at its start


def _tsdf() -> None:
    """One frame of a plane 0.5 m ahead, integrated with a confidence into a TSDF volume (the
    reconstruction node's and the evaluation's weighted integration)."""
    import numpy as np

    from area3d_eval.reconstruct import TsdfFusion

    h, w = 12, 16
    K = np.array([[10.0, 0.0, w / 2], [0.0, 10.0, h / 2], [0.0, 0.0, 1.0]])
    fusion = TsdfFusion()
    fusion.integrate(
        np.full((h, w, 3), 128, np.uint8),
        np.full((h, w), 0.5, np.float32),
        K,
        np.eye(4),
        np.full((h, w), 0.8, np.float32),
    )
    if fusion.num_frames != 1:
        raise RuntimeError("the TSDF frame was not integrated")


def _episode(part: str) -> None:
    from area3d_bringup.inprocess import run_inprocess_episode
    from area3d_eval.evaluate import evaluate_run

    with tempfile.TemporaryDirectory(prefix="area3d-kernels-") as out:
        if part == "camera":
            run_inprocess_episode(
                "single_object", "area3d", 0, Path(out), budget=5, run_name="camera",
                overrides={"sim_bridge": SMALL, "planner": SMALL}, depth_source="estimated",
            )  # fmt: skip
            return
        stereo = {
            "sim_bridge": {**SMALL, "stereo": True},
            "perception": {"backend": "stereo"},
            "planner": SMALL,
        }
        run = run_inprocess_episode(
            "single_object", "uniform", 0, Path(out), budget=6, run_name="stereo",
            overrides=stereo, depth_source="estimated",
        )  # fmt: skip
        evaluate_run(run, checkpoints=[6], eval_width=64, eval_height=48, write=False)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--part", choices=PARTS, action="append", help="this part (repeat: several; default: all)"
    )
    parser.add_argument("--here", action="store_true", help="in this process, one after another")
    args = parser.parse_args(argv)
    parts = tuple(args.part or PARTS)
    if args.here:
        seconds = warm_kernels(parts)
        print(f"numba kernels ({', '.join(parts)}) compiled or loaded in {seconds:.1f} s")
        return 0
    t0 = time.monotonic()
    command = [sys.executable, "-m", "area3d_bringup.kernels", "--here", "--part"]
    workers = [subprocess.Popen([*command, part]) for part in parts]
    failed = [part for part, w in zip(parts, workers, strict=True) if w.wait() != 0]
    if failed:
        print(f"compiling the numba kernels failed: part {', '.join(failed)}", file=sys.stderr)
        return 1
    print(f"numba kernels compiled or loaded into their cache in {time.monotonic() - t0:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
