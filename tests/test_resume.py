"""Resume loses nothing, whatever the time between the saved frames and however late it starts.

Time is injected (the runner's capture clock), not slept: the saved frames lie hours apart, further
than every pairing horizon in the graph (perception 5 s, planner 60 s of stamp time), and the
resumed episode captures a day after them."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

from area3d_bringup.runner import EpisodeConfig, run_episode
from area3d_eval import rundir
from sim_bridge.render import RgbdRenderer
from sim_bridge.scenes import load_scene

W, H = 160, 120
HOUR_NS = 3600 * 10**9
SMALL = {"sim_bridge": {"width": W, "height": H}, "planner": {"width": W, "height": H}}


@pytest.fixture(autouse=True)
def own_domain(monkeypatch):
    """The graph on a domain of its own, picked free as `area3d run` picks one: the test asks
    that every frame a node names dropped be the run's, and the test process's domain has
    carried other tests' nodes (a stale frame of an earlier test reached a node once)."""
    monkeypatch.delenv("ROS_DOMAIN_ID")


class SteppingClock:
    """Capture stamps that move `step_ns` forward at every capture, from `start_ns`."""

    def __init__(self, start_ns: int, step_ns: int) -> None:
        self.now_ns, self.step_ns = start_ns, step_ns

    def __call__(self) -> int:
        self.now_ns += self.step_ns
        return self.now_ns


def _crashed_run(run_dir: Path, budget: int, saved_stamps: list[int]) -> None:
    """The run directory an episode leaves when it dies right after its initial views."""
    scene = load_scene("single_object")
    renderer = RgbdRenderer(scene, width=W, height=H)
    views = []
    for index, (T, stamp) in enumerate(zip(scene.initial_views, saved_stamps, strict=True)):
        rgb, depth = renderer.render(T)
        rundir.write_frame(run_dir, index, rgb, depth, renderer.K, T, stamp_ns=stamp)
        views.append({"index": index, "stamp_ns": stamp, "T_world_cam": T, "kind": "initial"})
    renderer.close()
    rundir.write_episode(
        run_dir,
        {"scene": scene.name, "policy": "area3d", "seed": 0, "budget": budget,
         "level": scene.level, "mode": "closed_loop", "views": views, "timings_s": {},
         "recorded": {}},
    )  # fmt: skip


def test_a_resume_a_day_later_of_frames_hours_apart_loses_and_repeats_no_view(tmp_path):
    run_dir = tmp_path / "crashed"
    saved = [k * 3 * HOUR_NS for k in range(1, 5)]  # 3 h apart
    _crashed_run(run_dir, budget=6, saved_stamps=saved)
    clock = SteppingClock(start_ns=saved[-1] + 24 * HOUR_NS, step_ns=HOUR_NS)
    config = EpisodeConfig(record=False, overrides=SMALL, clock=clock)

    run_episode(config, resume=run_dir)

    episode = json.loads((run_dir / "episode.json").read_text())
    log = (run_dir / "nodes.log").read_text()
    views = episode["views"]
    stamps = [v["stamp_ns"] for v in views]
    assert stamps[:4] == saved  # the saved views are kept as they were
    assert [v["kind"] for v in views] == ["initial"] * 4 + ["planned"] * 2
    assert stamps[4] > saved[-1] + 24 * HOUR_NS and stamps[5] - stamps[4] >= HOUR_NS
    assert len(set(stamps)) == 6 and len(rundir.frame_files(run_dir)) == 6
    for view in views[4:]:  # a new view, not one of the saved ones taken again
        assert all(
            np.linalg.norm(
                np.array(view["T_world_cam"])[:3, 3] - np.array(old["T_world_cam"])[:3, 3]
            )
            > 0.05
            for old in views[:4]
        )
    # every view reached the planner once, with the semantic maps of the initial views
    assert episode["planner_status"]["frames_fused"] == 6, log[-3000:]
    assert episode["planner_status"]["semantic_frames_fused"] == 4, log[-3000:]
    # nothing lost: a replayed frame that perception answered late is sent again, and the copy's
    # parts are dropped; any frame named dropped is one of the run's, fused above all the same
    dropped = {int(s) for s in re.findall(r"at stamp (\d+) dropped", log)}
    assert dropped <= set(stamps), log[-3000:]
    assert episode["planner_status"]["frames_dropped_backlog"] == 0
    assert episode["planner_status"]["frames_dropped_without_camera_info"] == 0


def test_a_resumed_episode_chooses_the_views_of_the_episode_never_stopped(tmp_path):
    """An episode stopped after one planned view (the run directory a Ctrl-C leaves) and resumed
    chooses the views of the same episode never stopped, and its camera gives the same frames:
    the planner is asked again for each saved planned view before it is replayed (replayed all at
    once, every saved frame counted as an initial view, none as handed out, and other views
    followed), and the camera's noise goes on after the saved captures (`noise_skip`)."""
    full = run_episode(
        EpisodeConfig(budget=6, record=False, overrides=SMALL, out_dir=tmp_path, run_name="full")
    )
    saved = json.loads((full / "episode.json").read_text())
    stopped = tmp_path / "stopped"
    kept = saved["views"][:5]  # the 4 initial views and 1 planned one
    for view in kept:
        frame = rundir.read_frame(rundir.frame_path(full, view["index"]))
        rundir.write_frame(stopped, view["index"], *frame, stamp_ns=frame.stamp_ns)
    rundir.write_episode(stopped, {**saved, "views": kept})

    run_episode(EpisodeConfig(record=False, overrides=SMALL), resume=stopped)

    resumed = json.loads((stopped / "episode.json").read_text())["views"]
    assert len(resumed) == len(saved["views"]) == 6
    for index, (a, b) in enumerate(zip(saved["views"], resumed, strict=True)):
        assert np.allclose(a["T_world_cam"], b["T_world_cam"], rtol=0, atol=1e-9), index
        x = rundir.read_frame(rundir.frame_path(full, index))
        y = rundir.read_frame(rundir.frame_path(stopped, index))
        assert np.array_equal(x.depth, y.depth, equal_nan=True), index
        assert np.array_equal(x.rgb, y.rgb), index
    assert "chose another view" not in (stopped / "nodes.log").read_text()
