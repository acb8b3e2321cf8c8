"""The kernel warm-up's command line (`area3d_bringup.kernels`), as `make install` calls it: each
part named runs in a process of its own, all of them by default, and a part that fails fails the
whole."""

from __future__ import annotations

import pytest

from area3d_bringup import kernels


class FakeProcess:
    started: list[list[str]] = []
    failing: set[str] = set()

    def __init__(self, command: list[str]) -> None:
        self.command = command
        FakeProcess.started.append(command)

    def wait(self) -> int:
        return 1 if self.command[-1] in FakeProcess.failing else 0


@pytest.fixture
def processes(monkeypatch):
    FakeProcess.started, FakeProcess.failing = [], set()
    monkeypatch.setattr(kernels.subprocess, "Popen", FakeProcess)
    return FakeProcess


@pytest.mark.parametrize(
    ("argv", "parts"),
    [
        ([], list(kernels.PARTS)),
        (["--part", "masks"], ["masks"]),
        (["--part", "camera", "--part", "stereo"], ["camera", "stereo"]),
    ],
)
def test_each_part_named_runs_in_a_process_of_its_own(processes, argv, parts):
    assert kernels.main(argv) == 0
    assert [c[-3:] for c in processes.started] == [["--here", "--part", p] for p in parts]
    assert all(c[1:3] == ["-m", "area3d_bringup.kernels"] for c in processes.started)


def test_a_part_that_fails_fails_the_warm_up_and_is_named(processes, capsys):
    processes.failing = {"stereo"}
    assert kernels.main(["--part", "camera", "--part", "stereo"]) == 1
    assert "part stereo" in capsys.readouterr().err


def test_an_unknown_part_is_refused(capsys):
    with pytest.raises(SystemExit):
        kernels.main(["--part", "everything"])
    assert "invalid choice: 'everything'" in capsys.readouterr().err


def test_the_warm_up_compiles_what_the_planner_and_reconstruction_nodes_run_first():
    """In a fresh process (as `make install` runs a part): the masks part leaves the planner
    node's own warm-up compiled (the scoring of a list of views, the lazy greedy with the
    writable rotations every request passes), the stereo part's TSDF frame the weighted
    integration. Before, a fresh install's first graph compiled them while its first frames
    waited (over 5 s on a 2-core machine)."""
    import json
    import subprocess
    import sys

    script = (
        "import json; from area3d_bringup import kernels; "
        "kernels._masks(); kernels._tsdf(); "
        "from area3d_planner import lazy, masks; from area3d_eval import reconstruct; "
        "print(json.dumps({'lazy': [s[9].mutable for s in lazy.lazy_select.signatures], "
        "'score_view_list': len(masks.score_view_list.signatures), "
        "'tsdf': len(reconstruct._integrate_weighted.signatures)}))"
    )
    out = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=600, check=True
    )
    compiled = json.loads(out.stdout.strip().splitlines()[-1])
    assert compiled == {"lazy": [True], "score_view_list": 1, "tsdf": 1}, out.stderr


def test_the_rotations_of_one_seed_are_writable_as_those_of_many():
    import numpy as np

    from area3d_msgs_py.grid import GridSpec
    from area3d_planner.candidates import VisibilityParams, orientation_bins
    from area3d_planner.visibility import VisibilityCache

    spec = GridSpec.from_bounds(np.zeros(3), np.ones(3), 0.25)
    occupancy = np.zeros(spec.num_voxels, np.int8)
    params = VisibilityParams(level="room", face_res=16, yaw_bins=2, pitch_bins=1)
    rotations = orientation_bins(params)[1]
    for seeds in (np.array([[0.5, 0.5, 0.9]]), np.array([[0.5, 0.5, 0.9], [0.4, 0.5, 0.9]])):
        cache = VisibilityCache.build(spec, occupancy, seeds, rotations, params)
        assert cache.rotations.shape == (len(seeds), 2, 3, 3)
        assert cache.rotations.flags.writeable and cache.rotations.flags.c_contiguous
