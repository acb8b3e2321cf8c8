"""The soak benchmark on a short stream: every frame the camera sends is accounted for (published
by perception and fused by the planner, or dropped, counted and logged), the mission manager (a
process of its own) gets a plan for each request, and each stage reports how old its frames
were. Its figures (memory, latency) are the benchmark's to print, not this test's to assert."""

from __future__ import annotations

import numpy as np
import pytest

from area3d_bench.soak import run_bench
from sim_bridge.holdout_scenes import write_holdout_scene


@pytest.mark.parametrize("scene", ["single_object", "generated tabletop"])
def test_a_short_stream_loses_no_frame_and_every_request_gets_a_plan(scene, tmp_path):
    if scene.startswith("generated"):  # a scene file by path, without metadata
        scene = str(write_holdout_scene("tabletop", tmp_path / "tabletop", seed=1))
    # 30 frames at 5 Hz, half a driver's rate. Perception holds 16 frames in its backlog and,
    # by design, drops (and counts) a frame only when it falls that far behind for good, which
    # a 2-core machine busy with other work can make happen: the test asks that every frame be
    # accounted for, not that the machine keep up. What the stream does at driver rates is the
    # benchmark's to measure (`area3d bench soak`).
    f = run_bench(
        frames=30,
        duration_s=60.0,
        rate_hz=5.0,
        plan_every_s=0.5,
        scene_name=scene,
        print_table=False,
    )
    assert f["frames_sent"] == 30 and f["caught_up"]
    perception_dropped = sum(f["perception_frames_dropped"].values())
    planner_dropped = f["planner_frames_dropped_backlog"] + f["planner_frames_dropped_no_pose"]
    assert f["frames_published_by_perception"] + perception_dropped == 30
    assert f["frames_fused"] + planner_dropped == f["frames_published_by_perception"]
    assert f["frames_fused"] >= 1 and f["planner_parts_dropped"] == 0
    # a frame dropped is said in the log (at most once a second), with its stamp and the reason
    said = [line for line in f["drop_lines"] if "frame at stamp" in line]
    assert bool(said) == (perception_dropped + planner_dropped > 0), f["drop_lines"]
    assert f["plan_requests"] >= 1 and f["plan_failures"] == []
    assert len(f["plan_splits_s"]) == f["plan_requests"]
    for split in f["plan_splits_s"]:
        assert {"wait_fused", "wait_cache", "select"} <= set(split)
    for name in ("perception", "planner_paired", "planner"):
        p50, p95, top = f["frame_age_s"][name]
        assert np.isfinite(top) and 0 < p50 <= p95 <= top
    # a frame is whole at the planner before it is fused, and fusing it takes time
    assert f["frame_age_s"]["planner_paired"][0] < f["frame_age_s"]["planner"][0]
    p50, p95, top = f["fusion_s"]
    assert 0 < p50 <= p95 <= top
