"""The planner node's scheduling around its synchronous core (`server.NextBestViewServer`): a
request waits for its frame and for masks that cover it, plans run one at a time, and with
`background=True` the masks are rebuilt on a thread of their own after the map changes
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
from collections.abc import Callable

import numpy as np

from area3d_msgs_py.scheduling import BackgroundSteps, StateWaits
from area3d_planner.config import PlannerConfig
from area3d_planner.server import CACHE_WAIT_S, NextBestViewServer, Plan, PlanRequest

REBUILD_THREAD = "planner-cache-refresh"


class PlannerScheduler:
    """`core`: the map and the planning; this: when they run. `on_refresh` (optional) is called
    from the rebuild thread after each rebuild. Call `close()` to stop it."""

    def __init__(
        self,
        config: PlannerConfig,
        background: bool = False,
        on_refresh: Callable[[], None] | None = None,
        refresh_interval_s: float = 0.0,
        mask_lag_s: float = 0.0,
        rebuild_nice: int = 0,
    ) -> None:
        self.core = NextBestViewServer(config, background=background, mask_lag_s=mask_lag_s)
        self._plan_lock = threading.Lock()  # plans one at a time
        if background:
            self.waits: StateWaits = BackgroundSteps(
                self.core.rebuild_due,
                self.core.rebuild,
                REBUILD_THREAD,
                interval_s=refresh_interval_s,
                nice=rebuild_nice,
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
        return self.waits.wait_for(lambda: self.core.masks_cover(target), timeout_s, closed=True)

    # ------------------------------------------------------------------ planning
    def plan(self, request: PlanRequest) -> tuple[list[np.ndarray], str]:
        """(poses, reason) of `plan_views` (without the gains)."""
        plan = self.plan_views(request)
        return plan.poses, plan.reason

    def plan_views(self, request: PlanRequest) -> Plan:
        """The request checked, its masks waited for (those of the previous request's frame when
        pipelined, else those of its own; `CACHE_WAIT_S` at most), then planned
        (`NextBestViewServer.finish_plan`). Plans run one at a time."""
        with self._plan_lock:
            ticket = self.core.begin_plan(request)
            if isinstance(ticket, Plan):
                return ticket
            stamp = request.stamp_ns
            base_ready = bool(ticket.base) and self.wait_cache(stamp, CACHE_WAIT_S, ticket.base)
            # without the previous request's masks, the request waits for those of its own frame
            ready = base_ready or self.wait_cache(stamp, CACHE_WAIT_S)
            return self.core.finish_plan(ticket, base_ready, ready)
