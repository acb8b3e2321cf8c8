"""The semantics node: one VLM query with the initial views -> regions, weight maps, U_sem.

Subscribes color, depth (with the QoS `camera_qos` chooses) and perception confidence; a frame is
a view once all three are in (perception publishes confidence for the frames it integrates, so a
streaming camera's views are its keyframes, chosen by motion, not every frame); once the first
num_initial_views views are in, asks the backend once with all of them (on a worker thread, so callbacks keep running), publishes
the regions as JSON, one weight map per frame and, as each frame's confidence arrives, its U_sem.
Any message on the request topic re-runs the query on the frames collected so far. Topics:
`area3d_msgs_py/topics.py`; names are relative: `__ns` moves them all.
"""

from __future__ import annotations

import json
import threading
from collections.abc import Sequence
from typing import Any

import numpy as np
from rclpy.node import Node

from area3d_msgs_py import codecs, msgs, topics
from area3d_msgs_py.guard import Rejections, subscribe
from area3d_msgs_py.inputs import (
    COLOR_ENCODINGS,
    FLOAT_ENCODINGS,
    check_frame_id,
    check_stamp,
    check_unit_range,
    decode_camera_depth,
    decode_camera_info,
    decode_image,
)
from area3d_msgs_py.lens import Remap, camera_undistortion
from area3d_msgs_py.lifecycle import PublishGate, exit_process, run_node
from area3d_msgs_py.parameters import (
    CAMERA_QOS_PARAM,
    MAX_STAMP_AHEAD_PARAM,
    Param,
    declare_parameters,
    report_unknown_parameters,
)
from area3d_msgs_py.scheduling import AnalysisWorker
from area3d_msgs_py.status import StatusPublisher
from area3d_semantics.analysis import FALLBACKS, Analysis, analyze_views
from area3d_semantics.backends import (
    BACKEND_NAMES,
    Backend,
    HeuristicBackend,
    NoneBackend,
    VLMError,
    make_backend,
)
from area3d_semantics.views import ViewCollector
from area3d_semantics.weights import SIGMA_SOURCES, SemanticParams, frame_uncertainty, weight_map

IMAGE_QUEUE_DEPTH = 64  # the initial views (15 at room level) can arrive in one burst

PARAMS = (
    Param("backend", "heuristic", "region analyser", choices=BACKEND_NAMES),
    Param("base_url", "http://127.0.0.1:8000/v1", "OpenAI-compatible server (backend openai)"),
    Param("model", "OpenGVLab/InternVL3-8B", "VLM name (paper: InternVL3)"),
    Param("api_key_env", "OPENAI_API_KEY", "environment variable holding the API key"),
    Param(
        "timeout_s",
        60.0,
        "VLM request timeout: each attempt's whole answer within it, seconds",
        range=(0.1, 3600.0),
    ),
    Param("retries", 2, "VLM request retries after a failure, count", range=(0, 100)),
    Param(
        "retry_after_s",
        30.0,
        "after an analysis whose VLM answer was not used (a server down or late, an answer "
        "refused), query the same frames again this long after it, until one is used (0 = only "
        "on a request), seconds",
        range=(0.0, 86400.0),
    ),
    Param(
        "max_tokens",
        8192,
        "VLM answer length limit, tokens (5-8 regions of about 45 tokens per image: a room's "
        "15 views need about 5,000; an answer cut there is refused)",
        range=(16, 65536),
    ),
    Param("model_dir", "", "local model directory (backend transformers)"),
    Param("device", "auto", "torch device (backend transformers)"),
    Param("trust_remote_code", False, "let transformers run the model's own code"),
    # |O_0| = 4 at object level (paper, Sec. 4); the runner sets 15 for rooms.
    Param(
        "num_initial_views",
        4,
        "views in the one initial VLM query (paper: |O_0|), views",
        range=(1, 1000),
    ),
    Param(
        "fallback",
        "heuristic",
        "what replaces an unusable VLM answer",
        read_only=False,
        choices=FALLBACKS,
    ),
    Param(
        "requery_scope",
        "all",
        "frames a re-query analyses: all so far, or the latest num_initial_views",
        read_only=False,
        choices=("all", "latest"),
    ),
    Param("require_depth", True, "a view needs its depth before it is analysed"),
    Param(
        "undistort",
        False,
        "remap colour and depth of a camera whose camera_info has lens distortion into its "
        "pinhole k, as perception does, so that the weight maps lie on perception's pixels "
        "(off: used as they come, a few pixels off near the edges of a distorted image)",
    ),
    Param(
        "require_confidence",
        True,
        "a view needs perception's confidence before it is analysed: the views are the frames "
        "perception integrates (its keyframes), not every frame a camera streams",
    ),
    MAX_STAMP_AHEAD_PARAM,
    CAMERA_QOS_PARAM,
    Param(
        "sigma_source",
        "confidence",
        "backbone uncertainty sigma in U_sem (weights.SIGMA_SOURCES)",
        choices=SIGMA_SOURCES,
    ),
    *(
        Param(name, float(value), description, range=bounds)
        for name, value, description, bounds in SemanticParams.flat_parameters()
    ),
)


class SemanticsNode(Node):
    """Wires parameters, subscriptions and publishers around `analyze_views` and the weight maps."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__("semantics", **kwargs)
        p = declare_parameters(self, PARAMS)
        report_unknown_parameters(self)
        log = self.get_logger()
        self.backend_name = p["backend"]
        self.num_initial_views = p["num_initial_views"]
        self.params = semantic_params(p)
        self.require_depth = p["require_depth"]
        self.require_confidence = p["require_confidence"]
        self.sigma_source = p["sigma_source"]
        self.max_stamp_ahead_s = p["max_stamp_ahead_s"]
        self.rejections = Rejections(on_count=lambda: self.status.changed())
        self.backend, problem = backend_from_parameters(p)
        if problem:
            log.error(problem)
        # why the configured analyser is not in use (for the whole run), and why the last
        # analysis fell back: either is a failed backend (diagnostics: ERROR)
        self.backend_problem = problem
        self.analysis_error: str | None = None

        self.views = ViewCollector(self.require_depth, require_confidence=self.require_confidence)
        # the remap of the camera's images into k (`undistort`), from its latest camera_info
        self.undistort = p["undistort"]
        self.lens: Remap | None = None
        self.weights: dict[int, np.ndarray] = {}  # stamp -> weight map of the latest analysis
        self.published_usem: set[int] = set()
        self.queried = False
        self.analyses = 0
        self.resets = 0  # area3d/semantics/reset calls served
        self.requests = 0  # re-query requests received
        self._epoch = 0  # an analysis of views collected before the last reset is not published
        self.retry_after_s = float(p["retry_after_s"])
        self._retry: threading.Timer | None = None  # the next query after a failed one
        self._lock = threading.Lock()
        # the VLM query runs on a worker thread, so callbacks keep running meanwhile
        self.worker = AnalysisWorker(self._analyse, self._requery, "semantics-vlm")
        self.gate = PublishGate(self.context.ok)  # the worker publishes only while the node runs

        self.pub_regions, self.pub_weight, self.pub_usem = (
            self.create_publisher(topic.msg_type, topic.name, topic.qos())
            for topic in (
                topics.SEMANTIC_REGIONS, topics.SEMANTIC_WEIGHT, topics.SEMANTIC_UNCERTAINTY
            )
        )  # fmt: skip
        self.status = StatusPublisher(self, topics.SEMANTICS_STATUS, self._status)
        for topic, callback, depth in (
            (topics.COLOR, self.on_color, IMAGE_QUEUE_DEPTH),
            (topics.DEPTH, self.on_depth, IMAGE_QUEUE_DEPTH),
            (topics.PERCEPTION_CONFIDENCE, self.on_confidence, IMAGE_QUEUE_DEPTH),
            (topics.SEMANTIC_REQUEST, self.on_request, None),
            *([(topics.CAMERA_INFO, self.on_camera_info, None)] if p["undistort"] else []),
        ):
            subscribe(
                self, topic.msg_type, topic.name, callback,
                topic.reader_qos(p["camera_qos"], depth), self.rejections,
            )  # fmt: skip
        self.create_service(
            topics.SEMANTICS_RESET.srv_type, topics.SEMANTICS_RESET.name, self._on_reset
        )
        log.info(
            f"backend={self.backend.name} fallback={self.fallback} "
            f"num_initial_views={self.num_initial_views} lambda={self.params.lam}"
        )

    @property
    def fallback(self) -> str:
        return self.get_parameter("fallback").value

    @property
    def requery_scope(self) -> str:
        return self.get_parameter("requery_scope").value

    def _status(self) -> dict:
        running = self.worker.running_s
        with self._lock:
            return {
                "node": "semantics",
                "backend": self.backend.name,
                "views_complete": len(self.views.complete),
                "analyses": self.analyses,
                "resets": self.resets,
                "requests": self.requests,
                "usem_published": len(self.published_usem),
                "backend_error": self.backend_problem or self.analysis_error,
                "analysis_failures": self.worker.failures,
                # a query under way (null: none), and whether a request waits for it
                "analysis_running_s": None if running is None else round(running, 1),
                "analysis_pending": self.worker.pending,
                "analysis_retry_pending": self._retry is not None,
                "workers": {"analysis": self.worker.healthy},
                "undistorted": None if self.lens is None else self.lens.model,
                "rejected": self.rejections.snapshot(),
            }

    def _stamp(self, msg) -> int:
        return check_stamp(msg, self.get_clock().now().nanoseconds, self.max_stamp_ahead_s)

    # callbacks -----------------------------------------------------------------------------
    def on_color(self, msg) -> None:
        stamp = self._stamp(msg)
        frame_id = check_frame_id(msg)
        rgb = self._undistorted(decode_image(msg, COLOR_ENCODINGS), Remap.color)
        with self._lock:
            self.views.add_color(stamp, rgb, frame_id)
        self._maybe_start_initial()

    def on_depth(self, msg) -> None:
        stamp = self._stamp(msg)
        depth = self._undistorted(decode_camera_depth(msg), Remap.depth)
        with self._lock:
            self.views.add_depth(stamp, depth)
        self._maybe_start_initial()

    def on_camera_info(self, msg) -> None:
        """The camera's lens, as perception reads it (`area3d_msgs_py.lens`): its images are
        remapped into k from then on. A model the graph cannot undistort is perception's to
        warn of."""
        if not self.undistort:  # (not subscribed then)
            return
        self._stamp(msg)  # checked as perception checks it
        K, width, height = decode_camera_info(msg)
        self.lens, _ = camera_undistortion(K, width, height, msg.distortion_model, msg.d)

    def _undistorted(self, image: np.ndarray, remap) -> np.ndarray:
        lens = self.lens
        if lens is None or not lens.fits(image):  # another camera's: as it comes
            return image
        return remap(lens, image)

    def on_confidence(self, msg) -> None:
        stamp = self._stamp(msg)
        confidence = check_unit_range(decode_image(msg, FLOAT_ENCODINGS), "confidence")
        with self._lock:
            self.views.add_confidence(stamp, confidence)
            self._publish_usem(stamp)
        self._maybe_start_initial()

    def _requery(self) -> list[int]:
        """The frames a re-query analyses."""
        with self._lock:
            stamps = self.views.complete
            if self.requery_scope == "latest":
                stamps = stamps[-self.num_initial_views :]
            return list(stamps)

    def on_request(self, msg) -> None:
        with self._lock:
            self.requests += 1
        self.status.changed()
        stamps = self._requery()
        if not stamps:
            self.get_logger().warning(
                "semantics request: no complete frames yet, nothing to analyse"
            )
            return
        self.worker.submit(stamps, reason="request")

    def _on_reset(self, request, response):
        """area3d/semantics/reset (std_srvs/Trigger): forget the views and their analysis; an
        analysis running meanwhile finishes unpublished, and the next num_initial_views complete
        frames are analysed as the initial views."""
        with self._lock:
            views = len(self.views.complete)
            self.views = ViewCollector(
                self.require_depth, require_confidence=self.require_confidence
            )
            self.weights.clear()
            self.published_usem.clear()
            self.queried = False
            self._epoch += 1
            self.resets += 1
            self._cancel_retry()
        self.status.changed()
        response.success = True
        response.message = f"views cleared: {views} complete frames dropped"
        self.get_logger().info(f"{topics.SEMANTICS_RESET.name}: {response.message}")
        return response

    # work ------------------------------------------------------------------------------------
    def _maybe_start_initial(self) -> None:
        with self._lock:
            if self.queried or len(self.views.complete) < self.num_initial_views:
                return
            self.queried = True
            stamps = self.views.complete[: self.num_initial_views]
        self.worker.submit(stamps, reason="initial views")

    def _analyse(self, stamps: list[int], reason: str) -> None:
        log = self.get_logger()
        with self._lock:
            views = [self.views.get(s) for s in stamps]
            epoch = self._epoch
        views = [v for v in views if v is not None and v.rgb is not None]
        if not views:  # a re-query that waited while the views were reset
            log.info(f"no frames to analyse ({reason}); none since the reset")
            return
        log.info(f"querying {self.backend.name} with {len(views)} frames ({reason})")
        try:
            analysis = analyze_views(
                self.backend,
                [v.rgb for v in views],
                [v.depth for v in views],
                fallback=self.fallback,
            )
        except Exception as exc:  # bad frames must not kill the node
            log.error(f"region analysis failed: {exc}")
            analysis = Analysis([], len(views), self.backend.name, "zeros", str(exc))
        if analysis.fallback_used:
            log.warning(
                f"{self.backend.name} answer not used ({analysis.error}); fell back to {analysis.fallback_used}"
            )
        with self._lock:
            self.analysis_error = analysis.error if analysis.fallback_used else None
        self._publish(analysis, views, epoch)
        if analysis.fallback_used:
            self._schedule_retry([v.stamp_ns for v in views], epoch)

    def _schedule_retry(self, stamps: list[int], epoch: int) -> None:
        """Query `stamps` again `retry_after_s` from now (one retry pending at a time; none after
        a reset or once the node stops): a VLM server started after the graph, or one that was
        down for a while, is used without a request from the mission."""
        if self.retry_after_s <= 0:
            return
        with self._lock:
            if epoch != self._epoch or self._retry is not None or not self.context.ok():
                return
            timer = threading.Timer(self.retry_after_s, self._retry_now, args=(stamps, epoch))
            timer.name, timer.daemon = "semantics-retry", True
            self._retry = timer
        timer.start()
        self.get_logger().info(f"querying {len(stamps)} frames again in {self.retry_after_s:g} s")
        self.status.changed()

    def _retry_now(self, stamps: list[int], epoch: int) -> None:
        with self._lock:
            if self._retry is None or epoch != self._epoch:
                return  # cancelled: a reset, or the node stopped
            self._retry = None
        if self.context.ok():
            self.worker.submit(stamps, reason="retry after an answer not used")

    def _cancel_retry(self) -> None:
        """Drop a pending retry (call with the lock held)."""
        if self._retry is not None:
            self._retry.cancel()
            self._retry = None

    def destroy_node(self) -> None:
        """A query still running on the VLM worker when the node is destroyed publishes nothing
        (its publishers are gone: rclpy raised InvalidHandle on that thread), and a retry
        pending is dropped."""
        with self._lock:
            self._cancel_retry()
        self.gate.close()
        super().destroy_node()

    def _publish(self, analysis: Analysis, views: list, epoch: int) -> None:
        with self.gate as running:
            if running:  # a query that ends after the node stopped publishes nothing
                self._publish_analysis(analysis, views, epoch)

    def _publish_analysis(self, analysis: Analysis, views: list, epoch: int) -> None:
        payload = analysis.to_json([v.stamp_ns for v in views])
        with self._lock:  # a reset comes before all of it or after
            if epoch != self._epoch:
                self.get_logger().info(
                    f"the analysis of {len(views)} frames from before the reset is not published"
                )
                return
            self.pub_regions.publish(msgs.String(data=json.dumps(payload)))
            self.analyses += 1
            for i, view in enumerate(views):
                h, w = view.rgb.shape[:2]
                weight = weight_map(analysis.regions_of(i), h, w, self.params)
                self.weights[view.stamp_ns] = weight
                self.published_usem.discard(view.stamp_ns)
                self.pub_weight.publish(
                    codecs.image_to_msg(weight, "32FC1", view.stamp_ns, view.frame_id)
                )
                self._publish_usem(view.stamp_ns)
        self.status.changed()
        self.get_logger().info(
            f"published {len(analysis.regions)} regions over {len(views)} frames "
            f"(backend={analysis.backend}, fallback={analysis.fallback_used})"
        )

    def _publish_usem(self, stamp: int) -> None:
        """U_sem of one frame once both its weight map and its confidence are known (lock held)."""
        view = self.views.get(stamp)
        by_confidence = self.sigma_source == "confidence"
        if (
            stamp not in self.weights
            or view is None
            or (by_confidence and view.confidence is None)
            or stamp in self.published_usem
        ):
            return
        confidence = view.confidence if by_confidence else None
        usem = frame_uncertainty(self.weights[stamp], self.params.lam, confidence)
        self.pub_usem.publish(codecs.image_to_msg(usem, "32FC1", stamp, view.frame_id))
        self.published_usem.add(stamp)


def backend_from_parameters(p: dict) -> tuple[Backend, str | None]:
    """The region analyser this node's parameters `p` ask for, or its fallback when it cannot be
    made (with the reason, to log); also what `area3d_bringup.inprocess` analyses with."""
    options = {
        key: p[key]
        for key in (
            "base_url", "model", "api_key_env", "timeout_s", "retries", "max_tokens",
            "model_dir", "device", "trust_remote_code",
        )
    }  # fmt: skip
    try:
        return make_backend(p["backend"], **options), None
    except (VLMError, ValueError) as exc:
        fallback = HeuristicBackend() if p["fallback"] == "heuristic" else NoneBackend()
        return (
            fallback,
            f"{p['backend']} backend unavailable ({exc}); fallback {p['fallback']}: using the "
            f"{fallback.name} backend instead",
        )


def semantic_params(p: dict) -> SemanticParams:
    """The weight tables and lambda of this node's parameters `p`."""
    return SemanticParams.from_flat({k: p[k] for k in SemanticParams().to_flat()})


def main(args: Sequence[str] | None = None) -> int:
    return run_node(SemanticsNode, "semantics", args, on_stop=lambda node: node.gate.close())


if __name__ == "__main__":
    exit_process(main())
