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
