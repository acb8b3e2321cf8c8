"""The visibility masks brought up to date after each frame (`VisibilityCache.update`) equal a full
rebuild's, entry by entry: an object scene and a room, several closed-loop frames in a row, and
random maps whose candidate positions come and go."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from area3d_msgs_py.grid import GridSpec
from area3d_perception.sensor_model import rgbd_confidence
from area3d_planner.candidates import (
    VisibilityParams,
    lattice_positions,
    orientation_bins,
    shell_positions,
    shell_rotations,
    valid_seeds,
)
from area3d_planner.config import PlannerConfig
from area3d_planner.fusion import FREE
from area3d_planner.requests import PlanRequest
from area3d_planner.server import NextBestViewServer
from area3d_planner.visibility import VisibilityCache

ARRAYS = ("indptr", "voxel_ids", "weights", "range_bins", "direction_bins", "record_ids", "seeds")


def assert_same_masks(updated: VisibilityCache, full: VisibilityCache) -> None:
    """Same candidates, and every view's mask holds the same entries in the same (voxel) order."""
    for name in ARRAYS:
        np.testing.assert_array_equal(getattr(updated, name), getattr(full, name), err_msg=name)
    np.testing.assert_array_equal(updated.rotations, full.rotations)
    for view in range(0, full.num_views, max(1, full.num_views // 50)):
        ids, weights = updated.mask(view)
        order = np.argsort(ids)
        full_ids, full_weights = full.mask(view)
        full_order = np.argsort(full_ids)
        np.testing.assert_array_equal(ids[order], full_ids[full_order])
        np.testing.assert_array_equal(weights[order], full_weights[full_order])


def full_build(context, occupancy: np.ndarray) -> VisibilityCache:
    """The masks built from nothing, as the planner's context asks for them."""
    relevant = context.grid.roi_mask & (occupancy != FREE) & context.occluders(occupancy)
    occluders = context.occluders(occupancy)
    if (seen_into := context.seen_into(occupancy)) is not None:
        relevant |= context.grid.roi_mask & seen_into
    return VisibilityCache.build(
        context.grid.spec,
        occupancy,
        *context.candidates(),
        context.visibility,
        relevant=relevant,
        occluders=occluders,
    )


def closed_loop_reports(scene_name: str, frames: int, **overrides) -> list[dict]:
    """Run the closed loop on a bundled scene (frames rendered at 160 x 120); after each frame
    compare the planner's updated masks with a full build. Returns the updates' reports."""
    from area3d_bringup.launch_description import planner_region
    from sim_bridge.render import RgbdRenderer
    from sim_bridge.scenes import load_scene

    scene = load_scene(scene_name)
    region = {k: tuple(v) if isinstance(v, list) else v for k, v in planner_region(scene).items()}
    config = PlannerConfig(
        **{**region, "mode": "closed_loop", "budget": 10**6, "pipeline_masks": False, **overrides}
    )  # each plan from masks of its own frame, which the test compares with a full build
    server = NextBestViewServer(config)
    renderer = RgbdRenderer(scene, 160, 120)
    reports = []
    try:
        stamp = 0
        T = scene.initial_views[0]
        for stamp, T in enumerate(scene.initial_views, start=1):
            _, depth = renderer.render(T)
            server.add_frame(stamp, depth, rgbd_confidence(depth, renderer.K), renderer.K, T)
        for _ in range(frames + 1):
            poses, reason = server.plan(PlanRequest(T, stamp, 1))
            assert reason == "" and len(poses) == 1
            cache = server.context._cache("roi_not_free")  # the masks the plan used
            assert_same_masks(cache, full_build(server.context, server.grid.occupancy()))
            reports.append(cache.report)
            T = poses[0]
            _, depth = renderer.render(T)
            stamp += 1
            server.add_frame(stamp, depth, rgbd_confidence(depth, renderer.K), renderer.K, T)
    finally:
        renderer.close()
    return reports[1:]  # the first plan built its masks in full


@pytest.mark.parametrize("see_through", [0.0, 0.03])
def test_object_scene_masks_updated_frame_after_frame_equal_a_full_build(see_through):
    # with see-through, the occluding layer lies deeper in unknown space and moves as it is carved
    reports = closed_loop_reports("clutter7_a", 5, unknown_see_through=see_through)
    # the shells stay put; a position on them comes or goes as space near it is mapped
    assert all(r["updated"] >= 0.9 * r["positions"] for r in reports)
    # positions are re-examined where a frame's change shows, and only some of them change
    changed = [r["positions_changed"] for r in reports]
    assert sum(changed) > 0
    assert min(changed) < reports[0]["positions"]


def test_room_masks_updated_frame_after_frame_equal_a_full_build():
    # coarser than the planner's defaults so that the full builds compared against stay quick
    reports = closed_loop_reports("living_room", 3, seed_spacing=0.75, face_res=96)
    assert all(r["updated"] > 0 for r in reports)
    assert sum(r["pixels_reset"] for r in reports) > 0  # carved space: occluders left
    assert sum(r["voxels_changed"] for r in reports) > 0


def random_map(rng, spec: GridSpec) -> np.ndarray:
    """A room of boxes: free where carved, occupied shells, unknown insides and shadows."""
    occ = np.zeros(spec.shape, np.int8)
    for _ in range(6):
        lo = rng.integers(1, np.asarray(spec.shape) - 5)
        hi = lo + rng.integers(2, 6, 3)
        occ[lo[0] : hi[0], lo[1] : hi[1], lo[2] : hi[2]] = 1
        occ[lo[0] + 1 : hi[0] - 1, lo[1] + 1 : hi[1] - 1, lo[2] + 1 : hi[2] - 1] = -1
        occ[hi[0] : hi[0] + 3, lo[1] : hi[1], lo[2] : hi[2]] = -1
    return occ.ravel()


def evolve(rng, spec: GridSpec, occ: np.ndarray) -> np.ndarray:
    """The next map: a region carved free, unknown voxels turned occupied, a new box."""
    occ = occ.reshape(spec.shape).copy()
    lo = rng.integers(0, np.asarray(spec.shape) - 4)
    hi = lo + rng.integers(2, 5, 3)
    occ[lo[0] : hi[0], lo[1] : hi[1], lo[2] : hi[2]] = 0
    unknown = np.flatnonzero(occ.ravel() == -1)
    if unknown.size:
        occ.reshape(-1)[rng.choice(unknown, min(40, unknown.size), replace=False)] = 1
    lo = rng.integers(1, np.asarray(spec.shape) - 4)
    occ[lo[0] : lo[0] + 2, lo[1] : lo[1] + 3, lo[2] : lo[2] + 2] = 1
    return occ.ravel()


@pytest.mark.parametrize(
    "level, incidence, unknown_occludes",
    [("room", False, True), ("room", True, True), ("room", False, False), ("object", True, True)],
)
def test_random_maps_updated_again_and_again_equal_a_full_build(level, incidence, unknown_occludes):
    rng = np.random.default_rng(7)
    spec = GridSpec.from_bounds(np.zeros(3), np.ones(3), 0.05)
    params = VisibilityParams(
        level=level,
        yaw_bins=6,
        pitch_bins=2,
        face_res=48,
        incidence=incidence,
        unknown_occludes=unknown_occludes,
        shell_elevations_deg=(0.0, 30.0, 60.0),
    )
    centre = np.full(3, 0.5)
    occ = random_map(rng, spec)
    cache = None
    kept = built = 0
    for _ in range(6):
        if level == "room":  # a lattice inside the map: positions come and go with the map
            points = lattice_positions(np.full(3, 0.05), np.full(3, 0.95), 0.15)
            points = points[valid_seeds(points, spec, occ, np.zeros(3), np.ones(3), 0.05)]
            rotations = orientation_bins(params)[1]
        else:  # shells around and beyond the grid: buffers cropped, grown as the map changes
            points = shell_positions(centre, 0.8, dataclasses.replace(params))
            rotations = shell_rotations(points, centre, params.fan_deg)
        if unknown_occludes:
            free = (occ == 0).reshape(spec.shape)
            near = np.zeros_like(free)
            for axis in range(3):
                near |= np.roll(free, 1, axis) | np.roll(free, -1, axis)
            occluders = (occ != 0) & near.ravel()
        else:
            occluders = occ == 1
        relevant = (occ != 0) & occluders if unknown_occludes else occ != 0
        args = (occ, points, rotations)
        full = VisibilityCache.build(
            spec, *args, params, relevant=relevant, occluders=occluders, threads=1
        )
        if cache is None:
            cache = VisibilityCache.build(
                spec, *args, params, relevant=relevant, occluders=occluders, incremental=True
            )
        else:
            cache = cache.update(*args, relevant=relevant, occluders=occluders, threads=2)
            kept += cache.report["updated"]
            built += cache.report["built"]
        assert_same_masks(cache, full)
        assert full.voxel_ids.size > 0
        occ = evolve(rng, spec, occ)
    assert kept > 0
    if level == "room":
        assert built > 0  # positions that came with the map were built in full


def test_an_update_moves_the_buffers_so_a_second_update_of_the_same_cache_builds_in_full():
    rng = np.random.default_rng(3)
    spec = GridSpec.from_bounds(np.zeros(3), np.ones(3), 0.05)
    params = VisibilityParams(level="room", yaw_bins=4, pitch_bins=1, face_res=32)
    occ = random_map(rng, spec)
    seeds = np.array([[0.02, 0.02, 0.5], [0.97, 0.5, 0.97]])
    rotations = orientation_bins(params)[1]
    cache = VisibilityCache.build(spec, occ, seeds, rotations, params, incremental=True)
    later = evolve(rng, spec, occ)
    first = cache.update(later, seeds, rotations)
    again = cache.update(later, seeds, rotations)
    assert first.report["updated"] == 2 and again.report["built"] == 2
    assert_same_masks(again, first)
    plain = VisibilityCache.build(spec, occ, seeds, rotations, params)  # no buffers kept
    assert plain.update(later, seeds, rotations).report["built"] == 2


def test_buffers_are_gathered_into_a_new_pool_when_it_holds_much_unused():
    """Buffers: a buffer added goes to the end of the pool, which grows when full and keeps
    what it held; `compacted` gathers the positions' data, crops and offsets into a new pool
    once the pool holds more than twice what is in use (plus SPARE_VALUES), else keeps it."""
    from area3d_planner.incremental import SPARE_VALUES, Buffers

    rng = np.random.default_rng(7)

    def buffers(count: int, dead: int) -> Buffers:
        b = Buffers.empty(count, 32)
        b.rects[:] = -1  # empty faces (i1 < i0) ...
        b.rects[:, :, 0] = 0
        for s in range(count):  # ... but two of each position's
            for f in rng.choice(6, 2, replace=False):
                i0, j0 = rng.integers(0, 16, 2)
                b.rects[s, f] = (i0, i0 + rng.integers(0, 16), j0, j0 + rng.integers(0, 16))
        sizes = np.where(
            b.rects[:, :, 1] >= b.rects[:, :, 0],
            (b.rects[:, :, 1] - b.rects[:, :, 0] + 1) * (b.rects[:, :, 3] - b.rects[:, :, 2] + 1),
            0,
        )
        b.append(rng.random(dead).astype(np.float32))  # unused data ahead of the positions'
        for s in range(count):  # one at a time: the pool grows several times
            offsets = np.concatenate(([0], np.cumsum(sizes[s])[:-1]))
            b.offsets[s] = offsets + b.append(rng.random(sizes[s].sum()).astype(np.float32))
        assert b.used == dead + sizes.sum() <= b.pool.size
        return b

    def data(b: Buffers, s: int) -> np.ndarray:
        first, end = b.spans()
        return b.pool[first[s] : end[s]]

    kept = buffers(40, dead=1000)
    assert kept.compacted() is kept
    b = buffers(40, dead=SPARE_VALUES + 400_000)
    c = b.compacted()
    first, end = c.spans()
    assert c is not b and c.used == (end - first).sum() == end.max() <= c.pool.size
    assert c.used < b.used
    np.testing.assert_array_equal(c.rects, b.rects)
    for s in range(b.offsets.shape[0]):
        np.testing.assert_array_equal(data(c, s), data(b, s))
        # each face at the same place relative to the position's first
        np.testing.assert_array_equal(c.offsets[s] - first[s], b.offsets[s] - b.spans()[0][s])
    # a buffer appended after gathering lands after the data in use, which stays
    before = [data(c, s).copy() for s in range(40)]
    at = c.append(np.full(c.pool.size, 5.0, np.float32))  # more than the spare room
    assert at == end.max() and np.all(c.pool[at : c.used] == 5.0)
    for s in range(40):
        np.testing.assert_array_equal(data(c, s), before[s])
