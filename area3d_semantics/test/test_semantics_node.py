"""The semantics node over rclpy (in-process, real topics): one query with the initial views,
regions JSON, one weight map and one U_sem per frame with the frame's stamp, re-query on request;
its diagnostics go ERROR while the VLM fails and back to OK once it answers."""

import json
import socket
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import numpy as np
import pytest
import rclpy
from rclpy.executors import MultiThreadedExecutor
from rclpy.parameter import Parameter

from area3d_msgs_py import codecs, msgs, qos, services, topics
from area3d_msgs_py.diagnostics import DIAGNOSTICS_TOPIC, ERROR, OK
from area3d_msgs_py.spinning import Spinner
from area3d_semantics.backends import HeuristicBackend
from area3d_semantics.node import SemanticsNode
from area3d_semantics.weights import semantic_uncertainty, sigma_from_confidence

H, W = 60, 80
TIMEOUT_S = 120.0  # generous: a loaded machine is slow (every wait ends once its condition holds)


class Rig:
    """The node under test plus a peer node that feeds frames and records the outputs."""

    def __init__(self, parameters: dict):
        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        # most tests send a frame's confidence after its analysis (a view without it); the
        # streaming test below keeps the default, views only with perception's confidence
        parameters = {"require_confidence": False, **parameters}
        overrides = [Parameter(k, value=v) for k, v in parameters.items()]
        self.semantics = SemanticsNode(context=self.context, parameter_overrides=overrides)
        self.peer = rclpy.create_node("feeder", context=self.context)
        self.regions, self.weights, self.usem, self.diagnostics = [], {}, {}, []
        self.peer.create_subscription(
            msgs.DiagnosticArray,
            DIAGNOSTICS_TOPIC,
            lambda m: self.diagnostics.extend(s for s in m.status if s.name == "semantics: status"),
            qos.reliable(100),
        )
        self.peer.create_subscription(
            msgs.String,
            topics.SEMANTIC_REGIONS.name,
            self.regions.append,
            qos.latched(qos.DEFAULT_DEPTH),
        )
        self.peer.create_subscription(
            msgs.Image, topics.SEMANTIC_WEIGHT.name, self._store(self.weights), qos.reliable(64)
        )
        self.peer.create_subscription(
            msgs.Image, topics.SEMANTIC_UNCERTAINTY.name, self._store(self.usem), qos.reliable(64)
        )
        self.color = self.peer.create_publisher(msgs.Image, topics.COLOR.name, qos.reliable(64))
        self.depth = self.peer.create_publisher(msgs.Image, topics.DEPTH.name, qos.reliable(64))
        self.conf = self.peer.create_publisher(
            msgs.Image, topics.PERCEPTION_CONFIDENCE.name, qos.graph_frames(64)
        )
        self.request = self.peer.create_publisher(
            msgs.String, topics.SEMANTIC_REQUEST.name, qos.reliable()
        )
        self.executor = MultiThreadedExecutor(context=self.context)
        self.executor.add_node(self.semantics)
        self.executor.add_node(self.peer)
        self.spinner = Spinner(self.executor)
        # discovery: every publisher matched before anything is sent
        assert self.spin(
            lambda: all(
                p.get_subscription_count() >= 1
                for p in (self.color, self.depth, self.conf, self.request)
            )
        )

    @staticmethod
    def _store(into):
        def store(msg):
            # decoded first, then published to the test in one assignment: the test thread reads
            # `into` while this runs, and must never find a stamp without its image
            stamp, image = codecs.stamp_to_ns(msg.header.stamp), codecs.msg_to_image(msg)
            into[stamp] = [*into.get(stamp, []), image]

        return store

    def spin(self, done, timeout_s=TIMEOUT_S) -> bool:
        """Wait until `done()` holds (True) or `timeout_s` passes (False)."""
        deadline = time.monotonic() + timeout_s
        while not done() and time.monotonic() < deadline:
            time.sleep(0.02)
        return bool(done())

    def frame(self, stamp, image, depth, confidence=None):
        self.color.publish(codecs.image_to_msg(image, "rgb8", stamp, "camera_optical_frame"))
        self.depth.publish(codecs.image_to_msg(depth, "32FC1", stamp, "camera_optical_frame"))
        if confidence is not None:
            self.conf.publish(
                codecs.image_to_msg(confidence, "32FC1", stamp, "camera_optical_frame")
            )

    def close(self):
        self.spinner.stop(TIMEOUT_S)  # a loaded machine is slow
        self.peer.destroy_node()
        self.semantics.destroy_node()
        self.context.try_shutdown()


def frames(n):
    rng = np.random.default_rng(7)
    out = []
    for k in range(n):
        image = np.full((H, W, 3), 128, np.uint8)
        image[:, : W // 2] = rng.integers(60, 200, (H, W // 2, 3), dtype=np.uint8)
        depth = np.full((H, W), 2.0, np.float32)
        confidence = np.full((H, W), 0.5, np.float32)
        confidence[:, : W // 4] = 0.9
        out.append((1_000_000_000 + k * 1_000_000, image, depth, confidence))
    return out


def closed_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_initial_views_are_analysed_once_and_each_frame_gets_weight_and_usem():
    rig = Rig({"num_initial_views": 3, "backend": "heuristic", "sigma_source": "confidence"})
    try:
        data = frames(4)
        for stamp, image, depth, confidence in data[:3]:
            rig.frame(stamp, image, depth, confidence)
        stamps = [d[0] for d in data[:3]]
        assert rig.spin(lambda: rig.regions and all(s in rig.usem for s in stamps))
        assert len(rig.regions) == 1
        payload = json.loads(rig.regions[0].data)
        assert payload["prompt_version"] == "v1" and payload["backend"] == "heuristic"
        assert payload["fallback_used"] is None
        assert [img["stamp_ns"] for img in payload["images"]] == stamps
        # The flat grey right half is textureless: the heuristic reports it.
        assert any(
            r["type"] == "TEXTURE" and r["column"] == "right"
            for r in payload["images"][0]["regions"]
        )
        for stamp, _, _, confidence in data[:3]:
            (weight,) = rig.weights[stamp]
            assert weight.shape == (H, W) and weight.max() == pytest.approx(1.0)
            (usem,) = rig.usem[stamp]
            expected = semantic_uncertainty(sigma_from_confidence(confidence), weight, 1.0)
            np.testing.assert_allclose(usem, expected, atol=1e-6)
        # A frame after O_0 triggers no new query.
        rig.frame(*data[3])
        rig.spin(lambda: False, 1.0)
        assert len(rig.regions) == 1 and data[3][0] not in rig.weights
        # A request re-runs the query on everything collected so far.
        rig.request.publish(msgs.String(data="again"))
        assert rig.spin(lambda: len(rig.regions) >= 2 and data[3][0] in rig.weights)
        again = json.loads(rig.regions[-1].data)
        assert [img["stamp_ns"] for img in again["images"]] == [d[0] for d in data]
    finally:
        rig.close()


def test_with_a_streaming_camera_the_initial_views_are_perceptions_keyframes_not_the_first_frames():
    """30 frames streamed; perception integrates (sends confidence for) every tenth: the initial
    query analyses those keyframes, not the first num_initial_views frames of the stream."""
    rig = Rig({"num_initial_views": 3, "backend": "heuristic", "require_confidence": True})
    try:
        rng = np.random.default_rng(3)
        _, image, depth, confidence = frames(1)[0]
        keyframes = []
        for k in range(30):
            stamp = 1_000_000_000 + k * 33_000_000
            noisy = np.clip(image + rng.integers(0, 3, image.shape), 0, 255).astype(np.uint8)
            rig.frame(stamp, noisy, depth, confidence if k % 10 == 0 else None)
            keyframes += [stamp] if k % 10 == 0 else []
        assert rig.spin(lambda: rig.regions)
        payload = json.loads(rig.regions[0].data)
        assert [img["stamp_ns"] for img in payload["images"]] == keyframes
        # every keyframe's weights arrive (a loaded machine is slow), then nothing more does
        assert rig.spin(lambda: set(rig.weights) >= set(keyframes))
        rig.spin(lambda: False, 0.5)
        assert len(rig.regions) == 1 and set(rig.weights) == set(keyframes)
    finally:
        rig.close()


def test_unreachable_vlm_falls_back_and_the_node_keeps_running():
    url = f"http://127.0.0.1:{closed_port()}/v1"
    rig = Rig(
        {
            "num_initial_views": 2,
            "backend": "openai",
            "base_url": url,
            "retries": 0,
            "fallback": "zeros",
        }
    )
    try:
        data = frames(2)
        for stamp, image, depth, _ in data:
            rig.frame(stamp, image, depth)  # confidence arrives later
        assert rig.spin(lambda: rig.regions and all(d[0] in rig.weights for d in data))
        payload = json.loads(rig.regions[0].data)
        assert payload["backend"] == "openai" and payload["fallback_used"] == "zeros"
        assert url in payload["error"]
        assert all(not rig.weights[d[0]][0].any() for d in data)
        # the default sigma is perception's: U_sem waits for each frame's confidence, then with
        # zero weights it is Norm(1 - confidence)
        assert not rig.usem
        for stamp, _, _, confidence in data:
            rig.conf.publish(
                codecs.image_to_msg(confidence, "32FC1", stamp, "camera_optical_frame")
            )
        assert rig.spin(lambda: all(d[0] in rig.usem for d in data))
        for stamp, _, _, confidence in data:
            sigma = 1.0 - confidence
            np.testing.assert_allclose(rig.usem[stamp][0], sigma / sigma.max(), atol=1e-6)
    finally:
        rig.close()


class HeldBackend(HeuristicBackend):
    """The heuristic analyser, held at its first call until released."""

    def __init__(self):
        super().__init__()
        self.entered, self.release, self.calls = threading.Event(), threading.Event(), 0

    def analyze(self, images, depths=None):
        self.calls += 1
        if self.calls == 1:
            self.entered.set()
            assert self.release.wait(TIMEOUT_S)
        return super().analyze(images, depths)


def _held_requery(rig: Rig, initial: list) -> HeldBackend:
    """The initial views analysed, then a re-query of them held in the analyser."""
    for stamp, image, depth, _ in initial:
        rig.frame(stamp, image, depth)
    assert rig.spin(lambda: len(rig.regions) == 1)
    held = HeldBackend()
    rig.semantics.backend = held
    rig.request.publish(msgs.String(data="again"))
    assert held.entered.wait(TIMEOUT_S)
    return held


def test_requests_arriving_while_a_query_runs_are_answered_by_one_more_query():
    rig = Rig({"num_initial_views": 2, "backend": "heuristic"})
    try:
        data = frames(3)
        held = _held_requery(rig, data[:2])
        rig.frame(*data[2][:3])  # a new frame, then two requests while the first query runs
        assert rig.spin(lambda: len(rig.semantics.views.complete) == 3)
        rig.request.publish(msgs.String(data="second"))
        rig.request.publish(msgs.String(data="third"))
        assert rig.spin(lambda: rig.semantics.requests == 3)  # both taken while the first runs
        assert rig.semantics.worker.pending
        held.release.set()
        assert rig.spin(lambda: len(rig.regions) >= 3)
        rig.spin(lambda: False, 1.0)
        # the running query, then one more for both waiting requests, with every frame by then
        assert len(rig.regions) == 3 and held.calls == 2
        last = json.loads(rig.regions[-1].data)
        assert [img["stamp_ns"] for img in last["images"]] == [d[0] for d in data]
    finally:
        rig.close()


class VLMServer:
    """An OpenAI-compatible chat-completions server on 127.0.0.1:`port` that answers `answer`."""

    def __init__(self, port: int, answer: str):
        class Handler(BaseHTTPRequestHandler):
            def log_message(self, *args):
                pass

            def do_POST(self):
                self.rfile.read(int(self.headers["Content-Length"]))
                message = {"role": "assistant", "content": answer}
                body = json.dumps({"choices": [{"index": 0, "message": message}]}).encode()
                self.send_response(200)
                self.send_header("Content-Type", "application/json")
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                self.wfile.write(body)

        self.server = ThreadingHTTPServer(("127.0.0.1", port), Handler)
        self.thread = threading.Thread(target=self.server.serve_forever, daemon=True)
        self.thread.start()

    def close(self):
        self.server.shutdown()
        self.server.server_close()


def test_a_vlm_that_fails_is_an_error_on_diagnostics_until_it_answers_again():
    port = closed_port()
    url = f"http://127.0.0.1:{port}/v1"
    rig = Rig(
        {
            "num_initial_views": 4,
            "backend": "openai",
            "base_url": url,
            "retries": 0,
            "fallback": "zeros",
        }
    )
    server = None

    def levels(since: int = 0) -> list[int]:
        return [int.from_bytes(s.level, "little") for s in rig.diagnostics[since:]]

    try:
        assert rig.spin(lambda: OK in levels()), "no OK status before the first query"
        data = frames(4)
        for stamp, image, depth, _ in data:
            rig.frame(stamp, image, depth)
        assert rig.spin(lambda: rig.regions and ERROR in levels()), "no ERROR after the fallback"
        error = next(s for s in rig.diagnostics if s.level == ERROR.to_bytes(1, "little"))
        assert error.message.startswith("backend failed: ") and url in error.message
        values = {kv.key: kv.value for kv in error.values}
        assert url in values["backend_error"] and values["workers.analysis"] == "true"
        # it stays an error while the VLM's answer is not used (heartbeats, not only the change)
        seen = len(rig.diagnostics)
        assert rig.spin(lambda: len(rig.diagnostics) >= seen + 2)
        assert set(levels(seen)) == {ERROR}
        # the server comes back on its address; a re-query uses its answer: OK again
        answer = (Path(__file__).parent / "corpus" / "01_internvl3_strict.txt").read_text()
        server = VLMServer(port, answer)
        seen = len(rig.diagnostics)
        rig.request.publish(msgs.String(data="again"))
        assert rig.spin(lambda: len(rig.regions) >= 2)
        assert json.loads(rig.regions[-1].data)["fallback_used"] is None
        assert rig.spin(lambda: OK in levels(seen)), "no OK once the VLM answered"
        ok = [s for s in rig.diagnostics[seen:] if s.level == OK.to_bytes(1, "little")][-1]
        assert {kv.key: kv.value for kv in ok.values}["backend_error"] == ""
    finally:
        rig.close()
        if server is not None:
            server.close()


def test_a_vlm_that_comes_up_after_a_failed_query_is_used_without_a_request():
    """`retry_after_s`: the initial query fails (nothing listens at the address), the fallback's
    weights are published, and the same frames are queried again after the delay until the
    server, started later, answers; no request was sent. A reset drops a retry pending."""
    port = closed_port()
    rig = Rig(
        {
            "num_initial_views": 4,
            "backend": "openai",
            "base_url": f"http://127.0.0.1:{port}/v1",
            "retries": 0,
            "fallback": "zeros",
            "retry_after_s": 1.0,
        }
    )
    server = None
    try:
        data = frames(4)
        for stamp, image, depth, _ in data:
            rig.frame(stamp, image, depth)
        assert rig.spin(lambda: rig.regions), "no analysis published"
        first = json.loads(rig.regions[0].data)
        assert first["fallback_used"] == "zeros"
        answer = (Path(__file__).parent / "corpus" / "01_internvl3_strict.txt").read_text()
        server = VLMServer(port, answer)
        assert rig.spin(
            lambda: any(json.loads(r.data)["fallback_used"] is None for r in rig.regions)
        ), "the server's answer was never used"
        used = next(
            json.loads(r.data) for r in rig.regions if not json.loads(r.data)["fallback_used"]
        )
        stamps = [[image["stamp_ns"] for image in a["images"]] for a in (first, used)]
        assert stamps[0] == stamps[1] == [d[0] for d in data]
        assert rig.semantics.requests == 0 and rig.semantics._retry is None
        # once an answer is used no retry is pending; the number of analyses stays put
        count = len(rig.regions)
        time.sleep(3 * rig.semantics.retry_after_s)
        assert len(rig.regions) == count
    finally:
        rig.close()
        if server is not None:
            server.close()


def test_a_reset_or_the_nodes_end_drops_a_pending_retry():
    rig = Rig({"backend": "openai", "base_url": f"http://127.0.0.1:{closed_port()}/v1",
               "retries": 0, "fallback": "zeros", "retry_after_s": 3600.0})  # fmt: skip
    try:
        for stamp, image, depth, _ in frames(4):
            rig.frame(stamp, image, depth)
        assert rig.spin(lambda: rig.regions and rig.semantics._retry is not None)
        timer = rig.semantics._retry
        rig.semantics._on_reset(msgs.Trigger.Request(), msgs.Trigger.Response())
        assert rig.semantics._retry is None and timer.finished.is_set()
        for stamp, image, depth, _ in frames(4):
            rig.frame(stamp + 10**9, image, depth)
        assert rig.spin(lambda: len(rig.regions) >= 2 and rig.semantics._retry is not None)
        timer = rig.semantics._retry
    finally:
        rig.close()
    assert timer.finished.is_set() and rig.semantics._retry is None


@pytest.mark.filterwarnings("ignore::pytest.PytestUnhandledThreadExceptionWarning")
def test_an_analysis_that_raises_is_an_error_and_the_next_one_restarts_the_worker():
    rig = Rig({"num_initial_views": 2, "backend": "heuristic"})
    try:
        data = frames(2)
        for stamp, image, depth, _ in data:
            rig.frame(stamp, image, depth)
        assert rig.spin(lambda: len(rig.regions) == 1)
        publish = rig.semantics._publish_analysis
        rig.semantics._publish_analysis = lambda *a: (_ for _ in ()).throw(RuntimeError("bug"))
        rig.request.publish(msgs.String(data="again"))
        assert rig.spin(lambda: rig.semantics.worker.failures == 1)
        assert rig.spin(
            lambda: any(
                s.level == ERROR.to_bytes(1, "little") and "analysis_failures +1" in s.message
                for s in rig.diagnostics
            )
        )
        dead = [s for s in rig.diagnostics if s.level == ERROR.to_bytes(1, "little")][-1]
        assert {kv.key: kv.value for kv in dead.values}["workers.analysis"] == "false"
        # the next request runs on a new worker thread, which finishes: healthy, and OK again
        rig.semantics._publish_analysis = publish
        seen = len(rig.diagnostics)
        rig.request.publish(msgs.String(data="once more"))
        assert rig.spin(lambda: len(rig.regions) == 2)
        assert rig.spin(
            lambda: any(s.level == OK.to_bytes(1, "little") for s in rig.diagnostics[seen:])
        )
        assert rig.semantics.worker.healthy
    finally:
        rig.close()


def test_a_reset_drops_the_views_and_a_running_analysis_and_the_next_views_are_the_initial_ones():
    rig = Rig({"num_initial_views": 2, "backend": "heuristic"})
    try:
        data = frames(4)
        held = _held_requery(rig, data[:2])  # an analysis of frames 0 and 1 runs
        client = rig.peer.create_client(
            topics.SEMANTICS_RESET.srv_type, topics.SEMANTICS_RESET.name
        )
        assert client.wait_for_service(timeout_sec=TIMEOUT_S)
        answer = services.call(client, msgs.Trigger.Request(), TIMEOUT_S)
        assert answer.success
        assert answer.message == "views cleared: 2 complete frames dropped"
        held.release.set()
        assert rig.spin(lambda: not rig.semantics.worker.busy)
        assert len(rig.regions) == 1  # the analysis from before the reset went unpublished
        assert rig.semantics.analyses == 1 and rig.semantics.resets == 1
        # the next two frames are the initial views again: one analysis of them alone
        for stamp, image, depth, _ in data[2:]:
            rig.frame(stamp, image, depth)
        assert rig.spin(lambda: len(rig.regions) == 2)
        assert held.calls == 2
        payload = json.loads(rig.regions[-1].data)
        assert [img["stamp_ns"] for img in payload["images"]] == [d[0] for d in data[2:]]
    finally:
        rig.close()


def test_a_query_that_ends_after_the_node_was_destroyed_publishes_nothing_and_raises_nothing():
    rig = Rig({"num_initial_views": 2, "backend": "heuristic"})
    try:
        held = _held_requery(rig, frames(2))  # a re-query runs in the VLM worker
        worker = rig.semantics.worker
        rig.semantics.destroy_node()  # its publishers are gone ...
        held.release.set()  # ... when the query ends
        assert worker.join(TIMEOUT_S)
        # it ended as an analysis, not as an exception from a destroyed publisher
        assert worker.failures == 0 and worker.healthy and worker.runs == 2
        assert len(rig.regions) == 1 and rig.semantics.analyses == 1
    finally:
        rig.close()


def test_a_distorted_cameras_images_are_undistorted_as_perception_undistorts_them():
    """`undistort` on: colour and depth of a camera whose camera_info has lens distortion are
    remapped into its pinhole k, as perception remaps them, so that a frame's weight map and U_sem
    lie on the pixels of perception's confidence; without a camera_info, or with `undistort`
    off (the default), they are used as they come."""
    from area3d_msgs_py.lens import undistortion

    K = np.array([[W / 2, 0, W / 2], [0, W / 2, H / 2], [0, 0, 1.0]])
    d = [-0.3, 0.1, 0.0, 0.0, 0.0]
    lens, _ = undistortion(K, W, H, "plumb_bob", d)
    stamp, image, depth, _ = frames(1)[0]
    depth = depth + np.linspace(0.0, 1.0, W, dtype=np.float32)[None]  # a slanted wall
    context = rclpy.Context()
    rclpy.init(context=context)
    try:
        for undistort in (True, False):
            node = SemanticsNode(
                context=context,
                parameter_overrides=[
                    Parameter("undistort", value=undistort), Parameter("backend", value="heuristic"),
                ],
            )  # fmt: skip
            try:
                info = codecs.intrinsics_to_camera_info(K, W, H, stamp, "camera_optical_frame")
                info.d = d
                node.on_color(codecs.image_to_msg(image, "rgb8", stamp, "camera_optical_frame"))
                before = node.views.get(stamp).rgb  # no camera_info yet: as it came
                np.testing.assert_array_equal(before, image)
                node.on_camera_info(info)
                later = stamp + 1_000
                node.on_color(codecs.image_to_msg(image, "rgb8", later, "camera_optical_frame"))
                node.on_depth(codecs.image_to_msg(depth, "32FC1", later, "camera_optical_frame"))
                view = node.views.get(later)
                if undistort:
                    np.testing.assert_array_equal(view.rgb, lens.color(image))
                    np.testing.assert_array_equal(view.depth, lens.depth(depth))
                    assert node._status()["undistorted"] == "plumb_bob"
                else:
                    np.testing.assert_array_equal(view.rgb, image)
                    np.testing.assert_array_equal(view.depth, depth)
                    assert node._status()["undistorted"] is None
            finally:
                node.destroy_node()
    finally:
        context.try_shutdown()
