"""The semantics node: one VLM query with the initial views -> regions, weight maps, U_sem.

Subscribes color, depth and perception confidence; once the first num_initial_views frames are in,
asks the backend once with all of them (on a worker thread, so callbacks keep running), publishes
the regions as JSON, one weight map per frame and, as each frame's confidence arrives, its U_sem.
Any message on the request topic re-runs the query on the frames collected so far.
"""

from __future__ import annotations

import json
import threading
from collections.abc import Sequence

import cv2
import numpy as np

from area3d_msgs_py import codecs, msgs
from area3d_msgs_py.node import Node, run_node
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

IMAGE = "sensor_msgs/msg/Image"
STRING = "std_msgs/msg/String"
IMAGE_QUEUE_DEPTH = 64  # the initial views (15 at room level) can arrive in one burst


SIGMA_SOURCES = ("constant", "confidence")


class SemanticsNode:
    NODE_NAME = "semantics"

    def __init__(self, node: Node) -> None:
        self.node = node
        log = node.get_logger()
        p = node.declare_parameter
        self.backend_name = p("backend", "heuristic")
        if self.backend_name not in BACKEND_NAMES:
            log.error(
                f"backend: got {self.backend_name!r}, expected one of {BACKEND_NAMES}; using heuristic"
            )
            self.backend_name = "heuristic"
        options = {
            "base_url": p("base_url", "http://127.0.0.1:8000/v1"),
            "model": p("model", "OpenGVLab/InternVL3-8B"),  # the paper's VLM (InternVL3)
            "api_key_env": p("api_key_env", "OPENAI_API_KEY"),
            "timeout_s": p("timeout_s", 60.0),
            "retries": p("retries", 2),
            "max_tokens": p("max_tokens", 2048),
            "model_dir": p("model_dir", ""),
            "device": p("device", "auto"),
            "trust_remote_code": p("trust_remote_code", False),
        }
        # |O_0| = 4 at object level (paper, Sec. 4); the runner sets 15 for rooms.
        self.num_initial_views = int(p("num_initial_views", 4))
        self.fallback = p("fallback", "heuristic")
        if self.fallback not in FALLBACKS:
            log.error(
                f"fallback: got {self.fallback!r}, expected one of {FALLBACKS}; using heuristic"
            )
            self.fallback = "heuristic"
        self.requery_scope = p("requery_scope", "all")  # "all" frames so far | "latest" N
        defaults = SemanticParams().to_flat()
        self.params = SemanticParams.from_flat({k: p(k, v) for k, v in defaults.items()})
        self.require_depth = bool(p("require_depth", True))
        # sigma of U_sem = Norm(sigma (1 + lambda W)): "constant" (1: U_sem carries the VLM's
        # weights alone, independent of the depth backbone, so the no-feed-forward and no-VLM
        # ablations each remove one thing) or "confidence" (1 - perception confidence).
        self.sigma_source = p("sigma_source", "constant")
        if self.sigma_source not in SIGMA_SOURCES:
            log.error(
                f"sigma_source: got {self.sigma_source!r}, expected one of {SIGMA_SOURCES}; using constant"
            )
            self.sigma_source = "constant"
        topics = {
            "color": p("color_topic", "/area3d/camera/color/image_raw"),
            "depth": p("depth_topic", "/area3d/camera/depth/image_raw"),
            "confidence": p("confidence_topic", "/area3d/perception/confidence"),
            "request": p("request_topic", "/area3d/semantics/request"),
            "regions": p("regions_topic", "/area3d/semantics/regions"),
            "weight": p("weight_topic", "/area3d/semantics/weight"),
            "uncertainty": p("uncertainty_topic", "/area3d/semantics/uncertainty"),
        }

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
        self._pending_request = False

        self.pub_regions = node.create_publisher(STRING, topics["regions"], latched=True, depth=1)
        self.pub_weight = node.create_publisher(IMAGE, topics["weight"], depth=IMAGE_QUEUE_DEPTH)
        self.pub_usem = node.create_publisher(IMAGE, topics["uncertainty"], depth=IMAGE_QUEUE_DEPTH)
        node.create_subscription(IMAGE, topics["color"], self.on_color, depth=IMAGE_QUEUE_DEPTH)
        node.create_subscription(IMAGE, topics["depth"], self.on_depth, depth=IMAGE_QUEUE_DEPTH)
        node.create_subscription(
            IMAGE, topics["confidence"], self.on_confidence, depth=IMAGE_QUEUE_DEPTH
        )
        node.create_subscription(STRING, topics["request"], self.on_request)
        log.info(
            f"backend={self.backend.name} fallback={self.fallback} num_initial_views={self.num_initial_views} "
            f"lambda={self.params.lam}"
        )

    # callbacks -----------------------------------------------------------------------------
    def on_color(self, msg) -> None:
        stamp = codecs.stamp_to_ns(msg.header.stamp)
        with self._lock:
            self.views.add_color(stamp, codecs.msg_to_image(msg), msg.header.frame_id)
        self._maybe_start_initial()

    def on_depth(self, msg) -> None:
        stamp = codecs.stamp_to_ns(msg.header.stamp)
        with self._lock:
            self.views.add_depth(stamp, codecs.msg_to_image(msg))
        self._maybe_start_initial()

    def on_confidence(self, msg) -> None:
        stamp = codecs.stamp_to_ns(msg.header.stamp)
        with self._lock:
            self.views.add_confidence(stamp, codecs.msg_to_image(msg))
            self._publish_usem(stamp)

    def on_request(self, msg) -> None:
        with self._lock:
            stamps = self.views.complete
            if self.requery_scope == "latest":
                stamps = stamps[-self.num_initial_views :]
        if not stamps:
            self.node.get_logger().warning(
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
            if self._worker is not None and self._worker.is_alive():
                self._pending_request = True
                return
            self._worker = threading.Thread(
                target=self._run, args=(stamps, reason), name="semantics-vlm", daemon=True
            )
            self._worker.start()

    def _run(self, stamps: list[int], reason: str) -> None:
        log = self.node.get_logger()
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
        with self._lock:
            again, self._pending_request = self._pending_request, False
        if again:
            self.on_request(None)

    def _publish(self, analysis: Analysis, views: list) -> None:
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
        self.node.get_logger().info(
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


def main(argv: Sequence[str] | None = None) -> int:
    return run_node(SemanticsNode, argv, name=SemanticsNode.NODE_NAME)


if __name__ == "__main__":
    raise SystemExit(main())
