"""The seeds and visibility masks of `NextBestViewServer`: which map they are built from, rebuilt
when the server's caller asks (`rebuild`, a scheduler's thread) or at a request, and kept one step
behind for pipelined requests (`pipeline_masks`). A mixin: it reads and writes the server's map
versions, under the server's lock where a method says so.

Map versions: `_map_version` counts fused frames; the installed masks are those of map version
`_cache_version` (newest frame `_cache_stamp`); `_pipeline_base` is the version of the last
closed-loop request's frame, whose masks the next request plans from, kept in `_base_map` /
`_pipeline_map` until built and in `_previous_masks` once replaced.
"""

from __future__ import annotations

import time

from area3d_planner.greedy import warm_up_kernels
from area3d_planner.requests import PlanRequest


class MaskRebuilds:
    def rebuild_after_load(self) -> None:
        """Masks for a map `map_io.restore` put in place (lock held): first those of the map at
        the last closed-loop request's frame, which the next request plans from
        (`pipeline_masks`), then the current map's; by `rebuild` in the background, or the first
        now without it (the current map's then at the first request, as always)."""
        self.context.invalidate()
        base = self._base_map
        if base is None or base[0] != self._pipeline_base or not self._pipelines():
            base = None
        if self.background:
            self._pipeline_map = base
        elif base is not None:
            kinds = () if self.policy.relevant is None else (self.policy.relevant,)
            self._install(self.context.build(base[2], kinds))
            self._cache_version, self._cache_stamp = base[0], base[1]

    def cache_ready(self) -> bool:
        """True when seeds and masks reflect every fused frame (always False before the first)."""
        with self._lock:
            if self._map_version == 0:
                return False
            if self.background:
                return self._cache_version == self._map_version
            return self.context._candidates is not None

    def masks_target(self, stamp_ns: int = 0, version: int = 0) -> int | None:
        """The map version whose masks (or a newer one's) cover the frame `stamp_ns` (0 or a stamp
        not fused: every fused frame), or with `version` > 0 that version (`pipeline_masks`); None
        when the masks in place will do: with `mask_lag_s` > 0, built from a map whose newest
        frame is at most that much older than `stamp_ns`."""
        with self._lock:
            lag_ns = int(self.mask_lag_s * 1e9)
            if lag_ns > 0 and self._cache_version > 0 and stamp_ns - self._cache_stamp <= lag_ns:
                return None  # recent enough (`mask_lag_s`)
            return version or self._stamp_version.get(int(stamp_ns), self._map_version)

    def masks_cover(self, version: int) -> bool:
        """The masks in place were built from map version `version` or a newer one."""
        return self._cache_version >= version

    def rebuild_due(self) -> str | None:
        """What `rebuild` would do: "now" (the map at the last closed-loop request's frame waits:
        the next request plans from its masks), "due" (the masks lag the map) or None."""
        with self._lock:
            kept = self._pipeline_map
            if kept is not None and kept[0] <= self._cache_version:
                kept = self._pipeline_map = None  # built already
            if kept is not None:
                return "now"
            return "due" if self._map_version > self._cache_version else None

    def warm_up(self) -> None:
        """Load the compiled selection kernels (0.1-0.3 s), so that no request pays for it."""
        if self.policy.relevant is not None:
            warm_up_kernels()

    def rebuild(self) -> bool:
        """Rebuild seeds, visibility masks and, for the current map, the utility field: of the map
        at the last closed-loop request's frame when one is kept (`pipeline_masks`), else of the
        current map when the masks lag it; False when there was nothing to rebuild. The build
        runs outside the map's lock on a snapshot of the occupancy, so frames are fused meanwhile.
        A build that raises is counted (`rebuild_failures`) and the masks are left to the next
        request to rebuild."""
        kinds = () if self.policy.relevant is None else (self.policy.relevant,)
        with self._lock:
            kept = self._pipeline_map
            self._pipeline_map = None
            if kept is not None and kept[0] > self._cache_version:
                version, stamp, occupancy = kept  # the map at the last request's frame
            elif self._map_version > self._cache_version:
                version, stamp = self._map_version, self.last_fused_stamp
                occupancy = self.grid.occupancy()  # snapshot: fusion goes on meanwhile
            else:
                return False
            self._building_version = version
        started = time.perf_counter()
        try:
            built = self.context.build(occupancy, kinds)
        except Exception as exc:  # noqa: BLE001 - the request path rebuilds and reports it
            built = None
            self._rebuild_failed(exc)
        rebuild_s = time.perf_counter() - started
        with self._lock:
            if built is None:
                self.context.invalidate()
            else:
                self._install(built)
                if self.policy.relevant is not None and version == self._map_version:
                    try:  # the field of the current evidence, ready for the next request
                        self.context.policy_field(self.policy)
                        self.context.evidence()
                    except Exception as exc:  # noqa: BLE001 - reported by the request path
                        self.context.invalidate_fields()
                        self._rebuild_failed(exc)
            self._cache_version = version
            self._cache_stamp = stamp
            self._building_version = 0
            self.refresh_count += 1
            reports = [cache.report for cache in built[1].values()] if built else []
            self.last_rebuild = {"seconds": rebuild_s, "version": version}
            self.last_rebuild |= reports[0] if reports else {}
        return True

    def _update_masks(self) -> None:
        """Without the background worker: seeds and masks of the current map, built (updated
        from the installed ones) and installed now (lock held)."""
        kinds = () if self.policy.relevant is None else (self.policy.relevant,)
        self._install(self.context.build(self.grid.occupancy(), kinds))
        self._cache_version = self._map_version
        self._cache_stamp = self.last_fused_stamp

    def _install(self, built: tuple) -> None:
        """Install seeds and masks made by `PlanningContext.build`; while masks are pipelined
        the ones they replace are kept (with their map version) for the next request (lock
        held)."""
        if self._pipelines() and self._cache_version > 0:
            self._previous_masks = (self._cache_version, self._cache_stamp, self.context.masks())
        self.context.install(*built)

    def _pipelines(self, request: PlanRequest | None = None) -> bool:
        """Masks are pipelined (`pipeline_masks`, and no streaming camera's `mask_lag_s`, whose
        rule on the masks' age in capture time applies instead); with `request`: and it is a
        closed-loop request of a policy that selects from a snapshot."""
        if not self.config.pipeline_masks or self.mask_lag_s > 0:
            return False
        if request is None:
            return True
        return (request.mode or self.config.mode) == "closed_loop" and self.policy.map_free

    def _pipelined_masks(self, base: int) -> tuple[int, int, tuple | None]:
        """For a pipelined request (`_pipelines`), the masks of the previous request's frame, map
        version `base`: (their map version, the newest stamp in that map, (candidates, caches)
        when they are the ones the installed masks replaced, None when installed); lock held,
        with the background rebuild those masks were waited for."""
        if not self.background and self._cache_version < base:
            self._update_masks()  # frames came without a request between them: the newest
        previous = self._previous_masks
        if self._cache_version > base and previous is not None and previous[0] == base:
            candidates, caches = previous[2]
            if candidates is not None and self.policy.relevant in caches:
                return previous
        return self._cache_version, self._cache_stamp, None

    def _rebuild_failed(self, exc: Exception) -> None:
        self.rebuild_failures += 1
        self.last_rebuild_error = f"{exc.__class__.__name__}: {exc}"
