"""The semantics node: one VLM query with the initial views -> regions, weight maps, U_sem.

Subscribes color, depth and perception confidence; once the first num_initial_views frames are in,
asks the backend once with all of them (on a worker thread, so callbacks keep running), publishes
the regions as JSON, one weight map per frame and, as each frame's confidence arrives, its U_sem.
Any message on the request topic re-runs the query on the frames collected so far. Topic names
are relative: `__ns` moves them all.
"""

from __future__ import annotations

import json
import threading
from collections.abc import Sequence
from typing import Any

import cv2
import numpy as np
from rclpy.node import Node

from area3d_msgs_py import codecs, msgs, qos
from area3d_msgs_py.guard import Rejections, guarded
from area3d_msgs_py.inputs import (
    COLOR_ENCODINGS,
    DEPTH_ENCODINGS,
    FLOAT_ENCODINGS,
    check_frame_id,
    check_stamp,
    check_unit_range,
    decode_image,
)
from area3d_msgs_py.lifecycle import PublishGate, exit_process, run_node
from area3d_msgs_py.parameters import (
    MAX_STAMP_AHEAD_PARAM,
    Param,
    declare_parameters,
    report_unknown_parameters,
)
from area3d_msgs_py.status import StatusPublisher, status_topic
from area3d_semantics.analysis import FALLBACKS, Analysis, analyze_views
from area3d_semantics.backends import (
    BACKEND_NAMES,
    HeuristicBackend,
    NoneBackend,
    VLMError,
    make_backend,
)
from area3d_semantics.views import ViewCollector
from area3d_semantics.weights import (
    SemanticParams,
    semantic_uncertainty,
    sigma_from_confidence,
    weight_map,
)

COLOR_TOPIC = "area3d/camera/color/image_raw"
DEPTH_TOPIC = "area3d/camera/depth/image_raw"
CONFIDENCE_TOPIC = "area3d/perception/confidence"
REQUEST_TOPIC = "area3d/semantics/request"
REGIONS_TOPIC = "area3d/semantics/regions"
WEIGHT_TOPIC = "area3d/semantics/weight"
UNCERTAINTY_TOPIC = "area3d/semantics/uncertainty"
STATUS_TOPIC = status_topic("semantics")
IMAGE_QUEUE_DEPTH = 64  # the initial views (15 at room level) can arrive in one burst

PARAMS = (
    Param("backend", "heuristic", "region analyser", choices=BACKEND_NAMES),
    Param("base_url", "http://127.0.0.1:8000/v1", "OpenAI-compatible server (backend openai)"),
    Param("model", "OpenGVLab/InternVL3-8B", "VLM name (paper: InternVL3)"),
    Param("api_key_env", "OPENAI_API_KEY", "environment variable holding the API key"),
    Param("timeout_s", 60.0, "VLM request timeout, seconds", range=(0.1, 3600.0)),
    Param("retries", 2, "VLM request retries", range=(0, 100)),
    Param("max_tokens", 2048, "VLM answer length limit", range=(16, 65536)),
    Param("model_dir", "", "local model directory (backend transformers)"),
    Param("device", "auto", "torch device (backend transformers)"),
    Param("trust_remote_code", False, "let transformers run the model's own code"),
    # |O_0| = 4 at object level (paper, Sec. 4); the runner sets 15 for rooms.
    Param(
        "num_initial_views", 4, "views in the one initial VLM query (paper: |O_0|)", range=(1, 1000)
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
    MAX_STAMP_AHEAD_PARAM,
    # sigma of U_sem = Norm(sigma (1 + lambda W)): "constant" (1: U_sem carries the VLM's weights
    # alone, independent of the depth backbone, so the no-feed-forward and no-VLM ablations each
    # remove one thing) or "confidence" (1 - perception confidence, the paper's backbone sigma).
    Param(
        "sigma_source",
        "constant",
        "backbone uncertainty sigma in U_sem",
        choices=("constant", "confidence"),
    ),
    *(
        Param(
            name,
            float(value),
            f"SemanticParams {name} (area3d_semantics/weights.py)",
            range=(0.0, 1e6),
        )
        for name, value in SemanticParams().to_flat().items()
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
        options = {
            key: p[key]
            for key in (
                "base_url", "model", "api_key_env", "timeout_s", "retries", "max_tokens",
                "model_dir", "device", "trust_remote_code",
            )
        }  # fmt: skip
        self.num_initial_views = p["num_initial_views"]
        self.params = SemanticParams.from_flat({k: p[k] for k in SemanticParams().to_flat()})
        self.require_depth = p["require_depth"]
        self.sigma_source = p["sigma_source"]
        self.max_stamp_ahead_s = p["max_stamp_ahead_s"]
        self.rejections = Rejections(on_count=lambda: self.status.changed())
        try:
            self.backend = make_backend(self.backend_name, **options)
        except (VLMError, ValueError) as exc:
            fallback = HeuristicBackend() if self.fallback == "heuristic" else NoneBackend()
            log.error(
                f"{self.backend_name} backend unavailable ({exc}); using {fallback.name} instead"
            )
            self.backend = fallback

        self.views = ViewCollector(require_depth=self.require_depth)
        self.weights: dict[int, np.ndarray] = {}  # stamp -> weight map of the latest analysis
        self.published_usem: set[int] = set()
        self.queried = False
        self.analyses = 0
        self._lock = threading.Lock()
        self._worker: threading.Thread | None = None
        self.gate = PublishGate()  # the VLM worker publishes only while the node runs
        self._pending_request = False

        self.pub_regions = self.create_publisher(msgs.String, REGIONS_TOPIC, qos.latched())
        self.pub_weight = self.create_publisher(
            msgs.Image, WEIGHT_TOPIC, qos.graph_frames(IMAGE_QUEUE_DEPTH)
        )
        self.pub_usem = self.create_publisher(
            msgs.Image, UNCERTAINTY_TOPIC, qos.graph_frames(IMAGE_QUEUE_DEPTH)
        )
        self.status = StatusPublisher(self, STATUS_TOPIC, self._status)
        frames = qos.reliable(IMAGE_QUEUE_DEPTH)
        for msg_type, topic, callback, profile in (
            (msgs.Image, COLOR_TOPIC, self.on_color, frames),
            (msgs.Image, DEPTH_TOPIC, self.on_depth, frames),
            (msgs.Image, CONFIDENCE_TOPIC, self.on_confidence, qos.graph_frames(IMAGE_QUEUE_DEPTH)),
            (msgs.String, REQUEST_TOPIC, self.on_request, qos.reliable()),
        ):
            self.create_subscription(
                msg_type, topic, guarded(self, callback, topic, self.rejections), profile
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
        with self._lock:
            return {
                "node": "semantics",
                "backend": self.backend.name,
                "views_complete": len(self.views.complete),
                "analyses": self.analyses,
                "usem_published": len(self.published_usem),
                "rejected": self.rejections.snapshot(),
            }

    def _stamp(self, msg) -> int:
        return check_stamp(msg, self.get_clock().now().nanoseconds, self.max_stamp_ahead_s)

    # callbacks -----------------------------------------------------------------------------
    def on_color(self, msg) -> None:
        stamp = self._stamp(msg)
        frame_id = check_frame_id(msg)
        rgb = decode_image(msg, COLOR_ENCODINGS)
        with self._lock:
            self.views.add_color(stamp, rgb, frame_id)
        self._maybe_start_initial()

    def on_depth(self, msg) -> None:
        stamp = self._stamp(msg)
        depth = decode_image(msg, DEPTH_ENCODINGS)
        with self._lock:
            self.views.add_depth(stamp, depth)
        self._maybe_start_initial()

    def on_confidence(self, msg) -> None:
        stamp = self._stamp(msg)
        confidence = check_unit_range(decode_image(msg, FLOAT_ENCODINGS), "confidence")
        with self._lock:
            self.views.add_confidence(stamp, confidence)
            self._publish_usem(stamp)

    def _requery_stamps(self) -> list[int]:
        """The frames a re-query analyses (lock held)."""
        stamps = self.views.complete
        if self.requery_scope == "latest":
            stamps = stamps[-self.num_initial_views :]
        return list(stamps)

    def on_request(self, msg) -> None:
        with self._lock:
            stamps = self._requery_stamps()
        if not stamps:
            self.get_logger().warning(
                "semantics request: no complete frames yet, nothing to analyse"
            )
            return
        self._start(stamps, reason="request")

    # work ------------------------------------------------------------------------------------
    def _maybe_start_initial(self) -> None:
        with self._lock:
            if self.queried or len(self.views.complete) < self.num_initial_views:
                return
            self.queried = True
            stamps = self.views.complete[: self.num_initial_views]
        self._start(stamps, reason="initial views")

    def _start(self, stamps: list[int], reason: str) -> None:
        with self._lock:
            if self._worker is not None:  # running: it takes this request next
                self._pending_request = True
                return
            self._worker = threading.Thread(
                target=self._run, args=(stamps, reason), name="semantics-vlm", daemon=True
            )
            self._worker.start()

    def _run(self, stamps: list[int], reason: str) -> None:
        """Analyse `stamps`; a request that arrived meanwhile runs next in this same worker (with
        every frame complete by then), so no request is lost."""
        while True:
            self._analyse(stamps, reason)
            with self._lock:
                if not self._pending_request:
                    self._worker = None
                    return
                self._pending_request = False
                stamps, reason = self._requery_stamps(), "request"

    def _analyse(self, stamps: list[int], reason: str) -> None:
        log = self.get_logger()
        with self._lock:
            views = [self.views.get(s) for s in stamps]
        views = [v for v in views if v is not None and v.rgb is not None]
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
        self._publish(analysis, views)

    def _publish(self, analysis: Analysis, views: list) -> None:
        with self.gate as running:
            if running:  # a query that ends after the node stopped publishes nothing
                self._publish_analysis(analysis, views)

    def _publish_analysis(self, analysis: Analysis, views: list) -> None:
        payload = analysis.to_json([v.stamp_ns for v in views])
        self.pub_regions.publish(msgs.String(data=json.dumps(payload)))
        with self._lock:
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
        weight = self.weights[stamp]
        if by_confidence:
            sigma = sigma_from_confidence(view.confidence)
        else:
            sigma = np.ones(weight.shape, np.float32)
        if weight.shape != sigma.shape:
            # Perception may run at another resolution; the mask is smooth, so resampling is exact enough.
            weight = cv2.resize(
                weight, (sigma.shape[1], sigma.shape[0]), interpolation=cv2.INTER_LINEAR
            )
        usem = semantic_uncertainty(sigma, weight, self.params.lam)
        self.pub_usem.publish(codecs.image_to_msg(usem, "32FC1", stamp, view.frame_id))
        self.published_usem.add(stamp)


def main(args: Sequence[str] | None = None) -> int:
    return run_node(SemanticsNode, "semantics", args, on_stop=lambda node: node.gate.close())


if __name__ == "__main__":
    exit_process(main())
