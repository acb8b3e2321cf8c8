"""The planner node over rclpy (in-process, real topics): the hard regions of the fused map on
area3d/planner/hard_regions and as boxes, counted in the status; its diagnostics go ERROR when a
mask rebuild or a frame's fusion fails, or its fusion worker dies, and back to OK by the rules."""

from __future__ import annotations

import itertools
import json
import threading
import time

import numpy as np
import pytest
import rclpy
from rclpy.executors import MultiThreadedExecutor
from rclpy.parameter import Parameter

from area3d_msgs_py import codecs, msgs, qos, services, topics
from area3d_msgs_py.diagnostics import DIAGNOSTICS_TOPIC, ERROR, OK
from area3d_msgs_py.spinning import Spinner
from area3d_planner import map_io
from area3d_planner.node import PlannerNode
from area3d_planner.test.conftest import WALL_DIRECTIONS, WALL_K, banded_wall_view

TIMEOUT_S = 120.0  # generous: a loaded machine is slow (every wait ends once its condition holds)
OPTICAL = "camera_optical_frame"
REQUEST_IDS = itertools.count(1)  # select_views request ids, one per request
# The planner's grid over the unit cube at 5 cm starts half a voxel below the region's corner
# (config.PlannerConfig.grid_spec): voxel centres at multiples of 5 cm. The wall x = 0.65 lies
# mid-voxel; its two bands of low confidence cover 3 x 9 voxel centres each.
WALL_X = 0.65
BANDS_Y = ((0.125, 0.275), (0.725, 0.875))
BAND_Z = (0.275, 0.725)
PARAMETERS = {
    "roi_min": [0.0, 0.0, 0.0],
    "roi_max": [1.0, 1.0, 1.0],
    "workspace_min": [-1.0, -1.0, -1.0],
    "workspace_max": [2.0, 2.0, 2.0],
    "voxel_size": 0.05,
}


class Rig:
    """The planner under test and a peer node that feeds frames and records the outputs."""

    def __init__(self, parameters: dict):
        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        overrides = [Parameter(k, value=v) for k, v in {**PARAMETERS, **parameters}.items()]
        self.planner = PlannerNode(context=self.context, parameter_overrides=overrides)
        self.peer = rclpy.create_node("feeder", context=self.context)
        self.regions, self.boxes, self.status, self.diagnostics = [], [], [], []
        for topic, into in (
            (topics.HARD_REGIONS, self.regions),
            (topics.HARD_REGION_MARKERS, self.boxes),
        ):
            self.peer.create_subscription(topic.msg_type, topic.name, into.append, topic.qos())
        self.peer.create_subscription(
            msgs.String,
            topics.PLANNER_STATUS.name,
            lambda m: self.status.append(json.loads(m.data)),
            topics.PLANNER_STATUS.qos(),
        )
        self.peer.create_subscription(
            msgs.DiagnosticArray,
            DIAGNOSTICS_TOPIC,
            lambda m: self.diagnostics.extend(s for s in m.status if s.name == "planner: status"),
            qos.reliable(100),
        )
        self.pubs = {
            key: self.peer.create_publisher(topic.msg_type, topic.name, topic.qos())
            for key, topic in (
                ("depth", topics.PERCEPTION_DEPTH),
                ("confidence", topics.PERCEPTION_CONFIDENCE),
                ("pose", topics.POSE),
                ("info", topics.CAMERA_INFO),
            )
        }
        self.executor = MultiThreadedExecutor(num_threads=4, context=self.context)
        self.executor.add_node(self.planner)
        self.executor.add_node(self.peer)
        self.spinner = Spinner(self.executor)
        assert self.wait(lambda: all(p.get_subscription_count() >= 1 for p in self.pubs.values()))

    @staticmethod
    def wait(done, timeout_s: float = TIMEOUT_S) -> bool:
        deadline = time.monotonic() + timeout_s
        while not done() and time.monotonic() < deadline:
            time.sleep(0.02)
        return bool(done())

    def frame(self, stamp: int, depth: np.ndarray, confidence: np.ndarray, T: np.ndarray) -> None:
        h, w = depth.shape
        self.pubs["info"].publish(codecs.intrinsics_to_camera_info(WALL_K, w, h, stamp, OPTICAL))
        self.pubs["pose"].publish(
            msgs.PoseStamped(header=codecs.header(stamp, "world"), pose=codecs.matrix_to_pose(T))
        )
        self.pubs["depth"].publish(codecs.image_to_msg(depth, "32FC1", stamp, OPTICAL))
        self.pubs["confidence"].publish(codecs.image_to_msg(confidence, "32FC1", stamp, OPTICAL))

    def wall(self, first_stamp: int, directions=WALL_DIRECTIONS) -> list[int]:
        """The banded wall from each direction; the stamps."""
        stamps = []
        for i, (azimuth, elevation) in enumerate(directions):
            depth, confidence, T = banded_wall_view(azimuth, elevation, WALL_X, BANDS_Y, BAND_Z)
            stamps.append(first_stamp + i * 1_000_000)
            self.frame(stamps[-1], depth, confidence, T)
        return stamps

    def fused(self, count: int) -> bool:
        return self.wait(lambda: self.status and self.status[-1]["frames_fused"] >= count)

    def levels(self) -> list[int]:
        return [int.from_bytes(s.level, "little") for s in list(self.diagnostics)]

    def close(self):
        self.planner.stop()
        self.spinner.stop(TIMEOUT_S)  # a loaded machine is slow
        self.peer.destroy_node()
        self.planner.destroy_node()
        self.context.try_shutdown()


@pytest.fixture
def rig(request):
    made: list[Rig] = []

    def make(**parameters) -> Rig:
        made.append(Rig(parameters))
        return made[-1]

    yield make
    for r in made:
        r.close()


def test_the_hard_regions_of_the_fused_map_are_published_drawn_and_counted(rig):
    r = rig(eager_cache=False)
    stamps = r.wall(1_000_000_000)
    assert r.wait(
        lambda: r.regions and codecs.stamp_to_ns(r.regions[-1].header.stamp) == stamps[-1]
    )
    message = r.regions[-1]
    assert message.header.frame_id == "world"
    regions = codecs.msg_to_hard_regions(message)
    # the two bands no direction resolved: 3 x 9 voxels each, on the wall's voxel layer
    assert list(regions["voxel_count"]) == [27, 27]
    by_y = regions[np.argsort(regions["centroid"][:, 1])]
    np.testing.assert_allclose(by_y["centroid"], [[0.65, 0.2, 0.5], [0.65, 0.8, 0.5]], atol=1e-9)
    np.testing.assert_allclose(by_y["extent"], [[0.05, 0.15, 0.45]] * 2, atol=1e-9)
    assert np.all(regions["direction_count"] >= 3)
    assert np.all((regions["mean_uncertainty"] > 0) & (regions["mean_uncertainty"] <= 1))
    # the same regions as boxes, after a DELETEALL of the namespace
    assert r.wait(lambda: r.boxes and len(r.boxes[-1].markers) == 3)
    markers = r.boxes[-1].markers
    assert markers[0].action == msgs.Marker.DELETEALL
    for marker, region in zip(markers[1:], regions, strict=True):
        assert marker.type == msgs.Marker.CUBE and marker.header.frame_id == "world"
        p, s = marker.pose.position, marker.scale
        np.testing.assert_allclose([p.x, p.y, p.z], region["centroid"])
        np.testing.assert_allclose([s.x, s.y, s.z], region["extent"])
    # counted in the status, beside the hard voxels they hold
    assert r.fused(len(stamps))
    assert r.wait(lambda: r.status[-1]["hard_regions"] == 2)
    assert r.status[-1]["hard_voxels"] == 54


def test_at_most_hard_regions_max_are_published_and_all_are_counted(rig):
    r = rig(eager_cache=False, hard_regions_max=1)
    stamps = r.wall(2_000_000_000)
    assert r.wait(
        lambda: r.regions and codecs.stamp_to_ns(r.regions[-1].header.stamp) == stamps[-1]
    )
    assert len(r.regions[-1].regions) == 1 and r.regions[-1].regions[0].voxel_count == 27
    assert r.fused(len(stamps)) and r.wait(lambda: r.status[-1]["hard_regions"] == 2)


def test_a_failed_mask_rebuild_is_an_error_on_diagnostics_then_ok_again(rig):
    r = rig(eager_cache=True, refresh_interval_s=0.0)
    build = r.planner.scheduler.core.context.build
    calls = []

    def failing_once(*args, **kwargs):
        calls.append(1)
        if len(calls) == 1:
            raise RuntimeError("out of memory building masks")
        return build(*args, **kwargs)

    r.planner.scheduler.core.context.build = failing_once
    assert r.wait(lambda: OK in r.levels()), "no OK status before the failure"
    r.wall(3_000_000_000, WALL_DIRECTIONS[:1])
    assert r.wait(lambda: ERROR in r.levels()), "no ERROR after the failed rebuild"
    error = next(s for s in r.diagnostics if int.from_bytes(s.level, "little") == ERROR)
    assert "rebuild_failures +1" in error.message
    values = {kv.key: kv.value for kv in error.values}
    assert values["rebuild_failures"] == "1"
    assert "out of memory building masks" in values["last_rebuild_error"]
    assert values["workers.rebuild"] == "true" and values["workers.fusion"] == "true"
    # the worker keeps going: the next frame's rebuild succeeds, and the level returns to OK
    seen = len(r.diagnostics)
    r.wall(3_100_000_000, WALL_DIRECTIONS[1:2])
    assert r.wait(lambda: OK in r.levels()[seen:]), "no OK after the rebuild recovered"
    assert r.wait(lambda: len(calls) >= 2 and r.status[-1]["cache_ready"])


@pytest.mark.filterwarnings("ignore::pytest.PytestUnhandledThreadExceptionWarning")
def test_a_failed_fusion_is_an_error_and_a_dead_fusion_worker_stays_one(rig):
    r = rig(eager_cache=False)
    add_frame = r.planner.scheduler.add_frame

    def failing_once(stamp, *args):
        if stamp == 4_000_000_000:
            raise RuntimeError("numba kernel crashed")
        return add_frame(stamp, *args)

    r.planner.scheduler.add_frame = failing_once
    r.wall(4_000_000_000, WALL_DIRECTIONS[:1])
    assert r.wait(lambda: ERROR in r.levels()), "no ERROR after the failed fusion"
    error = next(s for s in r.diagnostics if int.from_bytes(s.level, "little") == ERROR)
    assert "fusion_failures +1" in error.message
    # the frames after it are fused, and a period later the level is OK again
    seen = len(r.diagnostics)
    r.wall(4_100_000_000, WALL_DIRECTIONS[1:2])
    assert r.fused(1)
    assert r.wait(lambda: OK in r.levels()[seen:])
    # a fusion worker whose thread ends (its publishing raised) is an error until the node stops
    r.planner._publish_state = lambda stamp: (_ for _ in ()).throw(RuntimeError("encoder bug"))
    r.wall(4_200_000_000, WALL_DIRECTIONS[2:3])
    assert r.wait(lambda: not r.planner.fusion.alive)

    def first_dead() -> int | None:  # a line computed before the death may still arrive first
        return next(
            (i for i, s in enumerate(r.diagnostics) if "worker fusion died" in s.message), None
        )

    assert r.wait(lambda: first_dead() is not None)
    seen = first_dead() + 1
    assert r.wait(lambda: len(r.diagnostics) >= seen + 2)
    dead = r.diagnostics[seen:]  # every line after it stays an error
    assert all(int.from_bytes(s.level, "little") == ERROR for s in dead)
    assert all("worker fusion died" in s.message for s in dead)


def test_a_reset_empties_the_map_and_what_waits_and_the_same_frames_fuse_again(rig):
    r = rig(eager_cache=True, refresh_interval_s=0.0)
    stamps = r.wall(5_000_000_000)
    assert r.fused(len(stamps)) and r.wait(lambda: r.status[-1]["hard_regions"] == 2)
    # a part whose partners have not come yet: the reset drops it
    depth, _, _ = banded_wall_view(*WALL_DIRECTIONS[0], WALL_X, BANDS_Y, BAND_Z)
    lone = 5_900_000_000
    r.pubs["depth"].publish(codecs.image_to_msg(depth, "32FC1", lone, OPTICAL))
    assert r.wait(lambda: lone in r.planner.inputs.sync.pending("depth"))
    views, frustums = [], []
    for topic, into in ((topics.NEXT_VIEWS, views), (topics.VIEW_MARKERS, frustums)):
        r.peer.create_subscription(topic.msg_type, topic.name, into.append, topic.qos())
    client = r.peer.create_client(topics.PLANNER_RESET.srv_type, topics.PLANNER_RESET.name)
    assert client.wait_for_service(timeout_sec=TIMEOUT_S)
    answer = services.call(client, msgs.Trigger.Request(), TIMEOUT_S)
    assert answer.success, answer.message
    assert f"map cleared (reset 1): {len(stamps)} frames fused" in answer.message
    assert "and 1 parts of frames dropped" in answer.message
    # the empty map's status and hard regions go out (the latched ones no longer hold the wall)
    assert r.wait(lambda: r.status[-1]["resets"] == 1)
    assert r.status[-1]["frames_fused"] == 0 and r.status[-1]["hard_voxels"] == 0
    assert r.wait(lambda: len(r.regions[-1].regions) == 0)
    # and no planned view: an empty path, the frustums deleted
    assert r.wait(lambda: views and frustums)
    assert views[-1].poses == [] and views[-1].header.frame_id == "world"
    assert [m.action for m in frustums[-1].markers] == [msgs.Marker.DELETEALL]
    # the lone part's partners now make no frame; the same frames as before fuse into the new map
    _, confidence, T = banded_wall_view(*WALL_DIRECTIONS[0], WALL_X, BANDS_Y, BAND_Z)
    r.pubs["confidence"].publish(codecs.image_to_msg(confidence, "32FC1", lone, OPTICAL))
    r.pubs["pose"].publish(
        msgs.PoseStamped(header=codecs.header(lone, "world"), pose=codecs.matrix_to_pose(T))
    )
    for i, direction in enumerate(WALL_DIRECTIONS):
        r.frame(stamps[i], *banded_wall_view(*direction, WALL_X, BANDS_Y, BAND_Z))
    assert r.fused(len(stamps)) and r.wait(lambda: r.status[-1]["hard_regions"] == 2)
    assert r.status[-1]["frames_fused"] == len(stamps)  # not the lone frame
    assert r.status[-1]["last_fused_stamp_ns"] == stamps[-1]
    assert r.planner.inputs.sync.pending("confidence") == [lone]  # still waiting for its depth
    assert r.planner.inputs.sync.pending("depth") == []


def _ask(r: Rig, T: np.ndarray, stamp: int, resend_s: float = services.RESEND_S) -> tuple:
    """One closed-loop view from the planner's select_views service: (poses, gains). The request
    carries an id of its own: a resend of it (a slow answer) is answered as it was."""
    client = r.peer.create_client(topics.SELECT_VIEWS.srv_type, topics.SELECT_VIEWS.name)
    assert client.wait_for_service(timeout_sec=TIMEOUT_S)
    request = codecs.view_request_to_msg(1, T, stamp, "world", request_id=next(REQUEST_IDS))
    answer = codecs.msg_to_view_answer(services.call(client, request, TIMEOUT_S, resend_s))
    assert answer.success, answer.message
    return np.array(answer.views), np.array(answer.gains)


def test_a_view_request_resent_while_it_waits_is_answered_as_it_was_and_counted_once(rig):
    """A client that resends its request while the planner waits for the request's frame (every
    0.2 s here; a reply late on a loaded machine) gets the answer the request got sent once; the
    resends, with the request's id, are not planned again (a closed-loop request from the same
    frame would mean views not captured). A new id from the same frame is planned anew."""
    views = [banded_wall_view(*d, WALL_X, BANDS_Y, BAND_Z) for d in WALL_DIRECTIONS[:2]]
    stamps = [7_000_000_000, 7_100_000_000]
    parameters = {"mode": "closed_loop", "budget": 20}
    once = rig(**parameters)
    once.frame(stamps[0], *views[0])
    assert once.fused(1)
    _ask(once, views[0][2], stamps[0])
    once.frame(stamps[1], *views[1])
    assert once.fused(2)
    expected = _ask(once, views[1][2], stamps[1])
    once.close()
    once.close = lambda: None  # the fixture closes it again

    r = rig(**parameters)
    r.frame(stamps[0], *views[0])
    assert r.fused(1)
    _ask(r, views[0][2], stamps[0])
    client = r.peer.create_client(topics.SELECT_VIEWS.srv_type, topics.SELECT_VIEWS.name)
    assert client.wait_for_service(timeout_sec=TIMEOUT_S)
    sent = []
    send = client.call_async
    client.call_async = lambda request: sent.append(request) or send(request)
    request_id = next(REQUEST_IDS)
    request = codecs.view_request_to_msg(1, views[1][2], stamps[1], "world", request_id=request_id)
    answers = []
    asking = threading.Thread(
        target=lambda: answers.append(services.call(client, request, TIMEOUT_S, resend_s=0.2))
    )
    asking.start()
    assert r.wait(lambda: len(sent) >= 3)  # sent three times before its frame comes
    r.frame(stamps[1], *views[1])
    asking.join(TIMEOUT_S)
    got = codecs.msg_to_view_answer(answers[0])
    assert got.success, got.message
    np.testing.assert_array_equal(got.views, expected[0])
    np.testing.assert_array_equal(got.gains, expected[1])
    assert r.planner.scheduler.answered(request_id) is not None
    assert r.wait(lambda: r.status[-1]["budget"]["handed_out"] == 2)  # one view a request
    # a new request from the same frame: the view handed out was not captured, another is planned
    again = _ask(r, views[1][2], stamps[1])
    assert not np.array_equal(again[0], expected[0])
    assert r.wait(lambda: r.status[-1]["budget"]["handed_out"] == 2)


def _map_call(r: Rig, service: topics.Service, path) -> object:
    client = r.peer.create_client(service.srv_type, service.name)
    assert client.wait_for_service(timeout_sec=TIMEOUT_S)
    return services.call(client, service.srv_type.Request(path=str(path)), TIMEOUT_S)


def test_a_mission_resumed_from_a_saved_map_over_the_services_chooses_the_same_views(rig, tmp_path):
    """Save the planner's map over area3d/planner/save_map mid-mission, stop the planner, load
    the map into a new one over load_map: the views it answers with from there are those of the
    mission never stopped. A file that does not fit is refused and the running map kept."""
    views = [banded_wall_view(*d, WALL_X, BANDS_Y, BAND_Z) for d in WALL_DIRECTIONS]
    stamps = [6_000_000_000 + i * 10**8 for i in range(len(views))]
    parameters = {"mode": "closed_loop", "budget": 20}  # masks rebuilt in the background

    def continue_mission(r: Rig, steps: range) -> list:
        answers = []
        for i in steps:
            r.frame(stamps[i], *views[i])
            assert r.fused(i + 1)
            answers.append(_ask(r, views[i][2], stamps[i]))
        return answers

    first = rig(**parameters)
    continue_mission(first, range(2))
    saved = _map_call(first, topics.PLANNER_SAVE_MAP, tmp_path / "planner.a3map")
    assert saved.success and "saved 2 fused frames and 2 views" in saved.message, saved.message
    never_stopped = continue_mission(first, range(2, 5))
    first.close()
    first.close = lambda: None  # the fixture closes it again

    resumed = rig(**parameters)
    (tmp_path / "foreign.a3map").write_bytes(b"PK\x03\x04 not a whole zip")
    refused = _map_call(resumed, topics.PLANNER_LOAD_MAP, tmp_path / "foreign.a3map")
    assert not refused.success and "complete area3d map file" in refused.message

    # a file that passes the checks and still fails to load (a bug): said, the node runs on
    def broken(*args):
        raise RuntimeError("a file the checks let through")

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(map_io, "restore", broken)
        failed = _map_call(resumed, topics.PLANNER_LOAD_MAP, tmp_path / "planner.a3map")
    assert not failed.success and "could not be done: RuntimeError" in failed.message
    loaded = _map_call(resumed, topics.PLANNER_LOAD_MAP, tmp_path / "planner.a3map")
    assert loaded.success and "loaded 2 fused frames" in loaded.message, loaded.message
    assert "17 views remain" in loaded.message  # 20 - (1 initial + 2 handed out)
    for (a, ga), (b, gb) in zip(never_stopped, continue_mission(resumed, range(2, 5)), strict=True):
        np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(ga, gb)
