"""The planner's map saved and loaded (`map_io`): a mission resumed from a saved map chooses the
views of the mission never stopped; a map that does not fit is refused and the running map kept."""

import re
import zipfile

import numpy as np
import pytest

from area3d_msgs_py import mapfile
from area3d_msgs_py.camera_pose import look_at
from area3d_msgs_py.errors import InputError
from area3d_planner import map_io
from area3d_planner.requests import PlanRequest
from area3d_planner.scheduler import PlannerScheduler, SchedulerConfig
from area3d_planner.server import NextBestViewServer
from area3d_planner.test.conftest import WALL_K, server_config
from tests.map_files import MISSING, rewrite_map


def config(**kw):
    return server_config(**{"budget": 30, "mode": "closed_loop", **kw})


def frame(i: int):
    """Frame i: a camera moving along y looking at a slanted wall, confidence falling with i."""
    y = 0.15 + 0.09 * (i % 9)
    T = look_at(np.array([0.1, y, 0.4 + 0.03 * (i % 4)]), np.array([1.0, y, 0.5]))
    cols = np.linspace(0.0, 1.0, 64, dtype=np.float32)
    depth = np.tile(0.45 + 0.2 * cols * (1 + (i % 3)) / 3, (48, 1)).astype(np.float32)
    depth[:, :4] = np.nan  # no return at one edge
    conf = np.full_like(depth, 0.5 + 0.04 * (i % 5))
    return (i + 1) * 10**8, depth, conf, WALL_K, T


def semantic(i: int):
    u = np.zeros((48, 64), np.float32)
    u[10 + i : 30, 20:40] = 0.8
    return u


def step(srv: NextBestViewServer | PlannerScheduler, i: int, sem_late: bool = False) -> tuple:
    """Fuse frame i (its semantic map before, or with sem_late after, the frame), then ask for the
    next view from it."""
    stamp, depth, conf, K_, T = frame(i)
    if i % 3 == 0 and not sem_late:
        srv.add_semantic(stamp, semantic(i))  # waits for its frame
    srv.add_frame(stamp, depth, conf, K_, T)
    if i % 3 == 0 and sem_late:
        srv.add_semantic(stamp, semantic(i))
    plan = srv.plan_views(PlanRequest(T, stamp, 1))
    assert plan.reason == ""
    return np.array(plan.poses), np.array(plan.gains)


def run(srv: NextBestViewServer | PlannerScheduler, steps: range) -> list:
    return [step(srv, i, sem_late=i % 2 == 0) for i in steps]


@pytest.mark.parametrize(
    "kw",
    [
        {},  # closed loop, masks pipelined
        {"pipeline_masks": False},
        {"policy": "uniform"},  # a sequential policy: its remaining views are saved
        {"mode": "batch", "budget": 40},
    ],
)
def test_a_mission_resumed_from_a_saved_map_chooses_the_views_of_the_mission_never_stopped(
    tmp_path, kw
):
    whole = NextBestViewServer(config(**kw))
    first = NextBestViewServer(config(**kw))
    run(whole, range(4))
    run(first, range(4))
    # a semantic map for a frame not yet fused (kept pending) and a re-analysis of a fused one
    for srv in (whole, first):
        srv.add_semantic(frame(7)[0], semantic(7))
        srv.add_semantic(frame(0)[0], semantic(2))
    path = tmp_path / "planner.a3map"
    written, size, header = map_io.save(first, path)
    assert written == path and size == path.stat().st_size > 0
    assert header["frames"] == 4 and header["committed"] == 4
    resumed = NextBestViewServer(config(**kw))
    map_io.restore(resumed, map_io.read(resumed, path))
    assert resumed.status()["budget"] == whole.status()["budget"]
    for a, b in zip(run(whole, range(4, 9)), run(resumed, range(4, 9)), strict=True):
        np.testing.assert_array_equal(a[0], b[0])
        np.testing.assert_array_equal(a[1], b[1])
    for name in map_io.VOXEL_FIELDS:
        np.testing.assert_array_equal(getattr(whole.grid, name), getattr(resumed.grid, name))


def test_a_map_saved_from_a_server_with_the_background_worker_resumes_there_too(tmp_path):
    kw = config()
    whole, first = (
        NextBestViewServer(kw),
        PlannerScheduler(kw, SchedulerConfig(refresh_interval_s=0.0)),
    )
    resumed = PlannerScheduler(kw, SchedulerConfig(refresh_interval_s=0.0))
    try:
        run(whole, range(3))
        run(first, range(3))
        path = tmp_path / "planner.a3map"
        map_io.save(first.core, path)
        map_io.restore(resumed.core, map_io.read(resumed.core, path))
        resumed.loaded()
        for a, b in zip(run(whole, range(3, 7)), run(resumed, range(3, 7)), strict=True):
            np.testing.assert_array_equal(a[0], b[0])
            np.testing.assert_array_equal(a[1], b[1])
    finally:
        first.close()
        resumed.close()


def saved(tmp_path, **kw):
    srv = NextBestViewServer(config(**kw))
    run(srv, range(2))
    path = tmp_path / "planner.a3map"
    map_io.save(srv, path)
    return path


@pytest.mark.parametrize(
    ("kw", "field"),
    [
        ({"voxel_size": 0.04}, "voxel_size"),
        ({"roi_min": (0.2, 0.0, 0.0)}, "roi_min"),
        ({"roi_max": (0.9, 1.0, 1.0)}, "shape"),  # the grid grows with it
        ({"workspace_max": (1.2, 1.0, 1.0)}, "origin|shape"),  # the room grid spans it
    ],
)
def test_a_map_of_another_grid_or_region_is_refused_naming_the_field(tmp_path, kw, field):
    path = saved(tmp_path)
    other = NextBestViewServer(config(**kw))
    with pytest.raises(InputError, match=field):
        map_io.read(other, path)


def test_truncated_foreign_missing_and_future_files_are_refused(tmp_path):
    path = saved(tmp_path)
    srv = NextBestViewServer(config())
    data = path.read_bytes()
    truncated = tmp_path / "truncated.a3map"
    truncated.write_bytes(data[: len(data) // 2])
    with pytest.raises(InputError, match="complete area3d map file"):
        map_io.read(srv, truncated)
    foreign = tmp_path / "foreign.ply"
    foreign.write_text("ply\nformat ascii 1.0\nend_header\n")
    with pytest.raises(InputError, match="complete area3d map file .not a zip archive") as info:
        map_io.read(srv, foreign)
    assert "pickle" not in str(info.value)  # numpy's advice to load it unsafely
    with pytest.raises(InputError, match="existing map file"):
        map_io.read(srv, tmp_path / "nowhere.a3map")
    future = tmp_path / "future.a3map"
    mapfile.write_map(future, "planner", {"x": 1}, {})
    with zipfile.ZipFile(future) as z:
        header = z.read("header.npy")
    assert b'"version": 1' in header
    other = tmp_path / "other.a3map"
    mapfile.write_map(other, "reconstruction", {}, {})
    with pytest.raises(InputError, match="content"):
        map_io.read(srv, other)


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"semantic_frames": MISSING}, "semantic_frames: got 'missing', expected an integer >= 0"),
        ({"frames": "ten"}, "frames: got 'ten', expected an integer >= 0"),
        ({"committed": -1}, "committed: got -1, expected an integer >= 0"),
        ({"has_sequence": 1}, "has_sequence: got 1, expected true or false"),
        ({"handed_out": [1, 2]}, "handed_out: got [1, 2], expected 3 integers or null"),
        ({"base": "x"}, "base: got 'x', expected a list of integers or null"),
        ({"camera": {"hfov_deg": 90.0}}, "camera: got"),
        ({"first_gain": "x"}, "first_gain: got 'x', expected a finite number >= 0 or null"),
        ({"first_gain": -1.0}, "first_gain: got -1.0, expected a finite number >= 0 or null"),
    ],
)
def test_a_header_entry_missing_or_of_another_kind_is_refused_naming_it(tmp_path, change, message):
    path = rewrite_map(saved(tmp_path), tmp_path / "bad.a3map", header=change)
    with pytest.raises(InputError, match=re.escape(message)):
        map_io.read(NextBestViewServer(config()), path)


def test_the_first_planned_gain_is_kept_and_a_file_without_it_loads_with_none(tmp_path):
    # what `coverage_below` compares each later gain with
    srv = NextBestViewServer(config())
    run(srv, range(2))
    srv.context.first_gain = 12.5
    path = tmp_path / "planner.a3map"
    map_io.save(srv, path)
    resumed = NextBestViewServer(config())
    map_io.restore(resumed, map_io.read(resumed, path))
    assert resumed.context.first_gain == 12.5
    older = rewrite_map(path, tmp_path / "older.a3map", header={"first_gain": MISSING})
    resumed = NextBestViewServer(config())
    map_io.restore(resumed, map_io.read(resumed, older))
    assert resumed.context.first_gain is None and resumed.grid.frames == 2


def test_an_array_of_nan_is_refused_naming_it(tmp_path):
    path = saved(tmp_path)
    with np.load(path) as archive:
        conf = np.full_like(archive["voxel_conf_sum"], np.nan)
    bad = rewrite_map(path, tmp_path / "nan.a3map", arrays={"voxel_conf_sum": conf})
    with pytest.raises(InputError, match="voxel_conf_sum'. got 'NaN or inf', expected finite"):
        map_io.read(NextBestViewServer(config()), bad)


@pytest.mark.parametrize(
    ("name", "scale", "message"),
    [
        ("voxel_hit_count", -1.0, "voxel_hit_count'. got '.* values outside, from -.*expected values >= 0"),
        ("voxel_log_residual", -1.0, "voxel_log_residual'. got .*expected values <= 0"),
        ("voxel_best_confidence", 3.0, "voxel_best_confidence'. got .*expected values in .0, 1.0001."),
        ("range_hits", -1.0, "range_hits'. got .*expected values >= 0"),
    ],
)  # fmt: skip
def test_evidence_no_fusion_can_hold_is_refused_naming_the_array_and_its_range(
    tmp_path, name, scale, message
):
    """A negative count or a confidence above 1 (a damaged file whose checksum was made again)
    would plan from evidence that never was; the saved map itself loads."""
    path = saved(tmp_path)
    srv = NextBestViewServer(config())
    map_io.read(srv, path)  # its own values are within every range
    with np.load(path) as archive:
        original = archive[name]
    changed = original * scale
    assert np.any(changed != original)
    bad = rewrite_map(path, tmp_path / "bad.a3map", arrays={name: changed})
    with pytest.raises(InputError, match=message):
        map_io.read(srv, bad)


def test_a_map_is_saved_only_under_its_own_suffix(tmp_path):
    srv = NextBestViewServer(config())
    run(srv, range(1))
    with pytest.raises(InputError, match=r"mesh.ply', expected a file name ending in .a3map"):
        map_io.save(srv, tmp_path / "mesh.ply")
    assert not (tmp_path / "mesh.ply").exists()
    assert map_io.save(srv, tmp_path / "MAP.A3MAP")[1] > 0


def test_a_saved_map_gets_the_mode_of_a_new_file_or_keeps_the_one_it_replaces(tmp_path):
    srv = NextBestViewServer(config())
    run(srv, range(1))
    new = tmp_path / "new.a3map"
    map_io.save(srv, new)
    assert new.stat().st_mode & 0o777 == 0o666 & ~mapfile.UMASK
    for mode in (0o640, 0o444):  # a read-only file is replaced (as `mv` would) and stays so
        kept = tmp_path / f"kept{mode:o}.a3map"
        kept.write_bytes(b"")
        kept.chmod(mode)
        map_io.save(srv, kept)
        assert kept.stat().st_mode & 0o777 == mode and kept.stat().st_size > 0


def test_a_file_of_a_newer_format_version_is_refused(tmp_path, monkeypatch):
    monkeypatch.setattr(mapfile, "VERSION", 2)
    path = saved(tmp_path)
    monkeypatch.setattr(mapfile, "VERSION", 1)
    with pytest.raises(InputError, match="version: got 2, expected 1"):
        map_io.read(NextBestViewServer(config()), path)


def test_a_save_that_fails_leaves_the_previous_file_and_no_temporary_one(tmp_path, monkeypatch):
    path = saved(tmp_path)
    before = path.read_bytes()
    srv = NextBestViewServer(config())
    run(srv, range(3))

    def broken(*args, **kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(np, "savez", broken)
    with pytest.raises(OSError, match="No space") as raised:
        map_io.save(srv, path)
    assert str(path) in str(raised.value)  # the answer names the file (ENOSPC names none)
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == [path.name]


def test_a_file_name_of_the_longest_length_a_file_system_takes_is_saved(tmp_path):
    """255 bytes: the temporary file beside it has a name of its own that is no longer."""
    srv = NextBestViewServer(config())
    run(srv, range(2))
    path, size, _ = map_io.save(srv, tmp_path / ("m" * 249 + ".a3map"))
    assert path.is_file() and size > 0 and [p.name for p in tmp_path.iterdir()] == [path.name]


def test_unwritable_paths_are_refused_by_name(tmp_path):
    srv = NextBestViewServer(config())
    with pytest.raises(InputError, match="existing directory"):
        map_io.save(srv, tmp_path / "missing" / "planner.a3map")
    with pytest.raises(InputError, match="not a directory"):
        map_io.save(srv, tmp_path)
    with pytest.raises(InputError, match="path"):
        map_io.save(srv, "")
    with pytest.raises(InputError, match=r"planner.a3map/', expected a file path, not a directory"):
        map_io.save(srv, f"{tmp_path}/planner.a3map/")  # a directory's name: not planner.a3map
    assert not (tmp_path / "planner.a3map").exists()


def test_a_map_saved_in_one_world_frame_is_refused_by_a_node_in_another(tmp_path):
    """A map saved in `map` loaded by a graph whose world_frame is `odom` would put every voxel
    where `odom` has it: refused by name; a file that records no frame (written before the
    frame was recorded) is taken."""
    srv = NextBestViewServer(config())
    run(srv, range(2))
    path, _, _ = map_io.save(srv, tmp_path / "planner.a3map", "map")
    with pytest.raises(InputError, match="world_frame: got 'map', expected 'odom'"):
        map_io.read(NextBestViewServer(config()), path, "odom")
    assert map_io.read(NextBestViewServer(config()), path, "map").header["world_frame"] == "map"
    unrecorded, _, _ = map_io.save(srv, tmp_path / "old.a3map")
    assert "world_frame" not in map_io.read(srv, unrecorded, "odom").header
