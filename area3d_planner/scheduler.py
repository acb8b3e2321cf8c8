"""The planner node's scheduling around its synchronous core (`server.NextBestViewServer`): a
request waits for its frame and for masks that cover it, plans run one at a time, and with
`eager_cache` the masks are rebuilt on a thread of their own after the map changes
(`area3d_msgs_py.scheduling.BackgroundSteps`). No ROS here.

With `refresh_interval_s` > 0 a rebuild starts at most that often while no request waits for one:
a camera streaming at 10 Hz would otherwise keep a core busy rebuilding masks that no request
reads; a waiting request still starts its rebuild at once. With `rebuild_nice` > 0 the rebuild
runs that much nicer than the process (its threads yield the CPU to fusion and requests): for a
streaming camera with `mask_lag_s` > 0, where no request waits for a rebuild, fusing every frame
on time comes first; with 0, a request waits on it.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial

import numpy as np

from area3d_msgs_py.param_fields import described
from area3d_msgs_py.scheduling import BackgroundSteps, StateWaits
from area3d_planner.config import PlannerConfig
from area3d_planner.requests import Plan, PlanRequest
from area3d_planner.server import CACHE_WAIT_S, NextBestViewServer

REBUILD_THREAD = "planner-cache-refresh"
# Answers kept by request id: a request with the id of one of them gets that answer again instead
# of a new plan. A ROS 2 client that has no reply within a few seconds may send its request again
# (`area3d_msgs_py.services.call`: a reply Fast DDS dropped right after discovery never comes);
# planned anew, a closed-loop request from the same frame means views that were not captured
# (`NextBestViewServer._release_uncaptured`), and the answer changes.
ANSWERS_KEPT = 64


@dataclass
class SchedulerConfig:
    """When the planner rebuilds its masks and how long a request waits for them (the planner
    node's parameters)."""

    eager_cache: bool = described(
        True, "rebuild seeds and visibility masks right after each fused frame"
    )
    refresh_interval_s: float = described(
        0.5, "eager rebuilds start at most this often unless a request waits for one", "seconds",
        range=(0.0, 60.0),
    )  # fmt: skip
    mask_lag_s: float = described(
        0.0,
        "a request plans from masks built up to this long (in capture time) before its frame "
        "instead of waiting for a rebuild; 0 = masks that cover its frame (a streaming camera: "
        "0.5)",
        "seconds",
        range=(0.0, 60.0),
    )
    rebuild_nice: int = described(
        0,
        "the background rebuild runs this much nicer (lower CPU priority) than the node, so "
        "fusion comes first (a streaming camera with mask_lag_s > 0: 10); 0 = the same",
        "nice levels",
        range=(0, 19),
    )


class PlannerScheduler:
    """`core`: the map and the planning; this: when they run (`scheduling`). `on_refresh`
    (optional) is called from the rebuild thread after each rebuild. Call `close()` to stop it."""

    def __init__(
        self,
        config: PlannerConfig,
        scheduling: SchedulerConfig | None = None,
        on_refresh: Callable[[], None] | None = None,
    ) -> None:
        s = scheduling or SchedulerConfig()
        self.core = NextBestViewServer(config, background=s.eager_cache, mask_lag_s=s.mask_lag_s)
        self._plan_lock = threading.Lock()  # plans one at a time
        self._answers: OrderedDict[int, Plan] = OrderedDict()  # by request id (`ANSWERS_KEPT`)
        self._answers_lock = threading.Lock()  # not the plan lock: a plan may wait minutes
        if s.eager_cache:
            self.waits: StateWaits = BackgroundSteps(
                self.core.rebuild_due,
                self.core.rebuild,
                REBUILD_THREAD,
                interval_s=s.refresh_interval_s,
                nice=s.rebuild_nice,
                warm_up=self.core.warm_up,
                after=on_refresh,
            )
        else:
            self.waits = StateWaits()

    @property
    def background(self) -> bool:
        return self.core.background

    @property
    def rebuild(self) -> BackgroundSteps | None:
        """The background rebuild's thread (None without it)."""
        return self.waits if isinstance(self.waits, BackgroundSteps) else None

    @property
    def worker_alive(self) -> bool:
        """The background rebuild runs, or was stopped by `close` (False: it died)."""
        return self.rebuild is None or self.rebuild.alive

    def close(self, timeout_s: float | None = None) -> None:
        """Stop the background rebuild (one in flight finishes first, or is left to die with the
        process after `timeout_s`) and end every wait: a request waiting for masks plans from
        those in place."""
        if self.rebuild is not None:
            self.rebuild.close(timeout_s)
        else:
            self.waits.close()

    # ------------------------------------------------------------------ the map changes
    def add_frame(
        self, stamp_ns: int, depth: np.ndarray, conf: np.ndarray, K: np.ndarray, T: np.ndarray
    ) -> bool:
        """`NextBestViewServer.add_frame`, then wake whoever waits on the map."""
        fused = self.core.add_frame(stamp_ns, depth, conf, K, T)
        self.waits.changed()
        return fused

    def add_semantic(self, stamp_ns: int, u_sem: np.ndarray) -> bool:
        """`NextBestViewServer.add_semantic`."""
        return self.core.add_semantic(stamp_ns, u_sem)

    def loaded(self) -> None:
        """A saved map was restored into the core (`map_io.restore`): its masks are due."""
        self.waits.changed()

    # ------------------------------------------------------------------ waits
    def wait_fused(
        self, stamp_ns: int, timeout_s: float, pose: np.ndarray | None = None, near=None
    ) -> bool:
        """Block until the map covers the frame `stamp_ns` (`NextBestViewServer.covers`), or
        timeout; True if it does."""
        return self.waits.wait_for(lambda: self.core.covers(stamp_ns, pose, near), timeout_s)

    def wait_cache(
        self, stamp_ns: int = 0, timeout_s: float | None = None, version: int = 0
    ) -> bool:
        """Background mode: block until the masks cover the frame `stamp_ns` (`masks_target`),
        or timeout; True if they do (and once closed). Always True without background."""
        if not self.background:
            return True
        target = self.core.masks_target(stamp_ns, version)
        if target is None:
            return True
        covered = partial(self.core.masks_cover, target)
        return self.waits.wait_for(covered, timeout_s, closed=True, urgent=True)

    # ------------------------------------------------------------------ planning
    def plan(self, request: PlanRequest) -> tuple[list[np.ndarray], str]:
        """(poses, reason) of `plan_views` (without the gains)."""
        plan = self.plan_views(request)
        return plan.poses, plan.reason

    def answered(self, request_id: int) -> Plan | None:
        """The answer given to the request `request_id` (`ANSWERS_KEPT`); None for 0 or an id
        not answered (or forgotten)."""
        if not request_id:
            return None
        with self._answers_lock:
            return self._answers.get(request_id)

    def plan_views(self, request: PlanRequest, note: str = "") -> Plan:
        """The request checked, its masks waited for (those of the previous request's frame when
        pipelined, else those of its own; `CACHE_WAIT_S` at most), then planned
        (`NextBestViewServer.finish_plan`), `note` added to a plan with views. Plans run one at
        a time; a request with the id of one answered gets that answer again (`ANSWERS_KEPT`)."""
        with self._plan_lock:
            answered = self.answered(request.request_id)
            if answered is not None:
                return answered
            plan = self._plan(request)
            if not plan.reason and note:
                plan = plan._replace(note="; ".join(n for n in (note, plan.note) if n))
            if request.request_id:
                with self._answers_lock:
                    self._answers[request.request_id] = plan
                    while len(self._answers) > ANSWERS_KEPT:
                        self._answers.popitem(last=False)
            return plan

    def _plan(self, request: PlanRequest) -> Plan:
        ticket = self.core.begin_plan(request)
        if isinstance(ticket, Plan):
            return ticket
        stamp = request.stamp_ns
        base_ready = bool(ticket.base) and self.wait_cache(stamp, CACHE_WAIT_S, ticket.base)
        # without the previous request's masks, the request waits for those of its own frame
        ready = base_ready or self.wait_cache(stamp, CACHE_WAIT_S)
        return self.core.finish_plan(ticket, base_ready, ready)
