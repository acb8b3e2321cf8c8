"""The output directory: refused at start when it cannot take a run; a run killed mid-write leaves a
run directory that reads back."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap

import pytest

from area3d_eval import rundir


def _run(out, *args: str) -> subprocess.CompletedProcess:
    """`area3d run` with its stderr unwrapped (the console wraps long lines)."""
    result = subprocess.run(
        [sys.executable, "-m", "area3d_bringup.cli", "run", "--out", str(out), "--no-evaluate",
         "--budget", "5", *args],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    result.stderr = " ".join(result.stderr.split())
    return result


def test_an_output_directory_that_cannot_be_created_is_refused_at_start(tmp_path):
    blocker = tmp_path / "a_file"
    blocker.write_text("not a directory")
    result = _run(blocker / "runs")
    assert result.returncode == 2
    assert "output directory: got" in result.stderr and "a_file" in result.stderr
    assert "expected a directory this process can write to" in result.stderr
    assert "Traceback" not in result.stderr


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes through directory permissions")
def test_a_read_only_output_directory_is_refused_at_start(tmp_path):
    out = tmp_path / "ro"
    out.mkdir()
    out.chmod(0o555)
    try:
        result = _run(out)
    finally:
        out.chmod(0o755)
    assert result.returncode == 2 and "can write to" in result.stderr
    assert not any(out.iterdir())


def test_an_output_directory_with_less_than_the_minimum_free_space_is_refused_at_start(tmp_path):
    result = _run(tmp_path, "--min-free-mb", str(1e12))  # an exabyte: no disk has it free
    assert result.returncode == 2
    assert "at least 1000000000000 MiB free" in result.stderr and "min_free_mb" in result.stderr
    assert not any(tmp_path.iterdir()), "a refused run must not leave a run directory"


def test_check_output_dir_names_the_minimum_and_accepts_a_writable_directory(tmp_path):
    rundir.check_output_dir(tmp_path / "new" / "runs", min_free_mb=1.0)  # created, writable
    assert (tmp_path / "new" / "runs").is_dir() and not any((tmp_path / "new" / "runs").iterdir())
    with pytest.raises(ValueError, match="expected at least .* MiB free"):
        rundir.check_output_dir(tmp_path, min_free_mb=1e12)


# Writes a run directory for three rounds (a frame, episode.json, the grid); in the last round the
# write named by argv[2] is cut off halfway and the process killed, as a crash or power cut would.
WRITER = textwrap.dedent(
    """
    import os, pathlib, signal, sys
    import numpy as np
    from area3d_eval import rundir

    run_dir, target = pathlib.Path(sys.argv[1]), sys.argv[2]

    def killed_halfway(write):
        def torn(path, *args, **kwargs):
            write(path, *args, **kwargs)
            data = pathlib.Path(path).read_bytes()
            pathlib.Path(path).write_bytes(data[: len(data) // 2])
            os.kill(os.getpid(), signal.SIGKILL)
        return torn

    cloud = np.zeros(1000, dtype=[(n, "f4") for n in rundir.GRID_FIELDS])
    views = []
    for i in range(3):
        if i == 2 and target == "frame":
            np.savez = killed_halfway(np.savez)
        rgb = np.full((24, 32, 3), i, np.uint8)
        rundir.write_frame(run_dir, i, rgb, np.ones((24, 32), np.float32), np.eye(3), np.eye(4), i)
        views.append({"index": i, "stamp_ns": i, "T_world_cam": np.eye(4), "kind": "initial"})
        if i == 2 and target == "episode":
            pathlib.Path.write_text = killed_halfway(pathlib.Path.write_text)
        rundir.write_episode(run_dir, {"scene": "s", "policy": "p", "views": views})
        if i == 2 and target == "grid":
            np.savez_compressed = killed_halfway(np.savez_compressed)
        cloud["x"] = i
        rundir.write_grid(run_dir / rundir.GRID_FINAL_FILE, cloud)
    """
)


@pytest.mark.parametrize(("target", "views"), [("frame", 2), ("episode", 2), ("grid", 3)])
def test_a_run_killed_mid_write_leaves_the_last_complete_version_of_every_file(
    tmp_path, target, views
):
    run_dir = tmp_path / "run"
    writer = subprocess.run(
        [sys.executable, "-c", WRITER, str(run_dir), target], capture_output=True, timeout=60
    )
    assert writer.returncode == -signal.SIGKILL, writer.stderr.decode()[-2000:]
    episode = rundir.read_episode(run_dir)  # parses: never half a file
    assert len(episode.views) == views
    # the frames on disk are whole (a torn temporary file is no frame), episode.json names them
    assert [f.index for f in rundir.iter_frames(run_dir)][:views] == list(range(views))
    for view in episode.views:
        frame = rundir.read_frame(rundir.frame_path(run_dir, view["index"]))
        assert frame.rgb.shape == (24, 32, 3) and int(frame.rgb[0, 0, 0]) == view["index"]
    grid = rundir.read_grid(run_dir / rundir.GRID_FINAL_FILE)
    assert grid is not None and grid["x"][0] == 1  # the round before the kill
