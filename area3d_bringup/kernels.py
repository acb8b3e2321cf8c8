"""Compile the numba kernels into their on-disk cache, ahead of the nodes that use them.

`make install` runs this once (`python -m area3d_bringup.kernels`), so the first episode's node
processes load the kernels instead of compiling them while the graph runs (on a 2-core machine
the first compile takes about 40 s); the test suite runs it at its start (`conftest.py`), where
with the cache warm it takes a few seconds. A tiny in-process episode with camera depth and one
with stereo depth, and the evaluation of one, run every kernel family the nodes and the report
use. A kernel whose source changed later is compiled again where it is first called.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

SMALL = {"width": 160, "height": 120}


def warm_kernels() -> float:
    """Run every kernel family once; returns the seconds it took."""
    from area3d_bringup.inprocess import run_inprocess_episode
    from area3d_eval.evaluate import evaluate_run

    t0 = time.monotonic()
    with tempfile.TemporaryDirectory(prefix="area3d-kernels-") as out:
        for name, overrides in (
            ("camera", {"sim_bridge": SMALL, "planner": SMALL}),
            (
                "stereo",
                {
                    "sim_bridge": {**SMALL, "stereo": True},
                    "perception": {"backend": "stereo"},
                    "planner": SMALL,
                },
            ),
        ):
            run = run_inprocess_episode(
                "single_object", "area3d", 0, Path(out), budget=6, overrides=overrides,
                run_name=name, depth_source="estimated",
            )  # fmt: skip
        evaluate_run(run, checkpoints=[6], eval_width=64, eval_height=48, write=False)
    return time.monotonic() - t0


def main() -> None:
    print(f"numba kernels compiled or loaded into their cache in {warm_kernels():.1f} s")


if __name__ == "__main__":
    main()
