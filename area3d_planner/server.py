"""The planner's state and the next-best-view service logic, without transport or threads.

`NextBestViewServer` fuses frames (paired by stamp upstream), keeps a bounded per-stamp cache so
semantic maps arriving later can be back-projected with their own depth and pose, rebuilds seeds
and visibility masks, and answers plan requests with `(poses, reason)`: an empty pose list always
comes with the reason. Everything runs when it is called, on the caller's thread; a lock keeps
the map consistent when the node calls it from several (fusion, requests, the rebuild). Waiting
for a frame or for masks, and rebuilding in the background: `scheduler.py`; the masks' versions
and rebuilds: `rebuilds.py`; requests, answers and their checks: `requests.py`; the grid and
planning context a configuration describes: `config.py`.
"""

from __future__ import annotations

import threading
import time
from collections import OrderedDict
from dataclasses import dataclass, field, replace

import numpy as np

from area3d_msgs_py.errors import InputError
from area3d_planner.config import PlannerConfig
from area3d_planner.context import SelectedViews
from area3d_planner.fusion import FusedGrid
from area3d_planner.policies import make_policy
from area3d_planner.rebuilds import MaskRebuilds
from area3d_planner.requests import Plan, PlanRequest, PlanTicket, check_request, repeats_note

CACHE_WAIT_S = 120.0  # a request waits at most this long for the background rebuild of the masks
# A camera's field of view within this of the planner's (degrees) is the same camera: the
# intrinsics of a 90 degree camera, fx = (W / 2) / tan(45 deg), give back 90 to within 1e-13.
CAMERA_FOV_EPS = 1e-6


@dataclass
class CachedFrame:
    """A fused frame's depth, intrinsics and pose, kept for its semantic map."""

    depth: np.ndarray
    K: np.ndarray
    T: np.ndarray


@dataclass
class NextBestViewServer(MaskRebuilds):
    """Planner state. With `background=True` seeds, visibility masks and the utility field are
    rebuilt by `rebuild()` calls after the map changed (a scheduler's thread: bursts of frames
    coalesce into one rebuild), and a request plans from the masks in place: its caller waits for
    the ones that cover its stamp first (`masks_target`, `masks_cover`). Without it they are
    rebuilt at the first request after the map changed.
    """

    config: PlannerConfig
    background: bool = False
    # A request accepts masks built from a map whose newest frame was captured at most this long
    # before the request's frame (0: it waits for masks that cover its frame). The uncertainty
    # field is always the current one; only which voxels each candidate sees may lag.
    mask_lag_s: float = 0.0
    grid: FusedGrid = field(init=False)
    committed: int = field(init=False, default=0)
    # the last closed-loop plan's views, until a frame comes: (request stamp, frames fused, count)
    _handed_out: tuple[int, int, int] | None = field(init=False, default=None)
    # frames fused before the first request (the working distance's), and how many of them the
    # budget counts as initial views (at most `initial_views`)
    initial_frames: int | None = field(init=False, default=None)
    initial_counted: int = field(init=False, default=0)
    last_fused_stamp: int = field(init=False, default=0)
    _sequence: SelectedViews | None = field(
        init=False, default=None
    )  # a sequential policy's remaining views
    # seconds the last plan spent waiting for the masks and selecting views; the node adds the
    # wait for the request's frame (`last_request_s`, in the status)
    last_plan_s: dict = field(init=False, default_factory=dict)
    last_request_s: dict = field(init=False, default_factory=dict)

    def __post_init__(self) -> None:
        c = self.config
        c.validate()
        self.budget = c.resolved_budget()
        self.initial_limit = c.resolved_initial_views()
        # every view handed out: (pose, request stamp), to say when one repeats (`_repeats`)
        self._answered: list[tuple[np.ndarray, int]] = []
        self._fused_order: list[int] = []  # fused stamps in fusion order (context.camera_poses')
        self.grid = c.fused_grid()
        self.context = c.planning_context(self.grid)
        self.context.visibility.validate()
        self.context.greedy.validate()
        self.policy = make_policy(c.policy)
        self._lock = threading.RLock()  # the map, the caches and the bookkeeping
        self._frames: OrderedDict[int, CachedFrame] = OrderedDict()
        self._pending_semantic: OrderedDict[int, np.ndarray] = OrderedDict()
        self._semantic_of: dict[int, tuple] = {}  # stamp -> its semantic contribution
        self._fused_stamps: set[int] = set()
        self._map_version = 0  # occupancy changes (fused frames)
        self._stamp_version: dict[int, int] = {}  # map version that holds each stamp
        self._cache_version = 0  # map version of the installed seeds and masks
        self._cache_stamp = 0  # newest frame stamp in the map the installed masks were built from
        # pipeline_masks: the map version of the last closed-loop request's frame (the next
        # request plans from its masks), and the masks installed before the current ones
        self._pipeline_base = 0
        self._previous_masks: tuple | None = None  # (map version, stamp, (candidates, caches))
        self._pipeline_map: tuple | None = None  # (map version, stamp, occupancy) to build first
        self._base_map: tuple | None = None  # (map version, stamp, occupancy) at the base
        self._building_version = 0  # the map version `rebuild` is building (0: none)
        self.refresh_count = 0  # background rebuilds run so far
        self.rebuild_failures = 0  # background rebuilds that raised (the request path rebuilds)
        self.last_rebuild_error = ""
        # the last background rebuild: its seconds and what it did (`VisibilityCache.report`)
        self.last_rebuild: dict = {}

    # ------------------------------------------------------------------ fusion
    def add_frame(
        self, stamp_ns: int, depth: np.ndarray, conf: np.ndarray, K: np.ndarray, T: np.ndarray
    ) -> bool:
        """Fuse one frame and remember its depth/pose for a semantic map of the same stamp.

        A frame is fused once: the same stamp again (a replay after a restart, a resent frame)
        changes nothing and returns False, so replaying every saved frame never doubles evidence.
        The frame's evidence is computed without the lock (back-projection and carving are most of
        the cost) and added under it in a few milliseconds, so a plan in progress and a frame
        arriving do not wait for each other."""
        with self._lock:
            if int(stamp_ns) in self._fused_stamps:
                return False
        if self.config.uniform_confidence:
            conf = np.isfinite(np.asarray(depth)).astype(np.float32)
        observation = self.grid.observe_depth(
            depth,
            conf,
            K,
            T,
            self.config.max_range,
            self.config.carve_stride,
        )
        with self._lock:
            if int(stamp_ns) in self._fused_stamps:  # the same stamp, fused meanwhile
                return False
            pipelined = self._pipelines()
            if pipelined and self._pipeline_base == self._map_version:
                # the map at the last request's frame, which the next request plans from (a
                # saved map keeps it: `map_io`)
                self._base_map = (self._map_version, self.last_fused_stamp, self.grid.occupancy())
                if (
                    self._cache_version < self._map_version
                    and self._building_version != self._map_version
                ):
                    # its masks: built now without the background rebuild; with it, the map is
                    # kept for `rebuild`, which may not have started on it (it coalesces frames)
                    # before this frame changes it
                    if self.background:
                        self._pipeline_map = self._base_map
                    else:
                        self._update_masks()
            self._adopt_camera(K, np.shape(depth))
            self.grid.apply_depth(observation)
            self._frames[int(stamp_ns)] = CachedFrame(
                np.asarray(depth, np.float32), np.asarray(K, float), np.asarray(T, float)
            )
            while len(self._frames) > self.config.frame_cache:
                old_stamp, _ = self._frames.popitem(last=False)
                self._semantic_of.pop(old_stamp, None)
            self._fused_stamps.add(int(stamp_ns))
            self.context.camera_positions.append(np.asarray(T, float)[:3, 3].copy())
            self.context.camera_poses.append(np.asarray(T, float).copy())
            self._fused_order.append(int(stamp_ns))
            self.last_fused_stamp = max(self.last_fused_stamp, int(stamp_ns))
            self._map_version += 1
            self._stamp_version[int(stamp_ns)] = self._map_version
            if self.background or pipelined:
                self.context.invalidate_fields()  # masks stay until the rebuild replaces them
            else:
                self.context.invalidate()
            pending = self._pending_semantic.pop(int(stamp_ns), None)
            if pending is not None:
                self._fuse_semantic(int(stamp_ns), pending, self._frames[int(stamp_ns)])
            return True

    def camera(self) -> tuple[float, int, int]:
        """(horizontal field of view in degrees, width, height) of the candidate views: the
        camera's, once a frame has been fused (`_adopt_camera`), the hfov_deg, width and height
        parameters before."""
        v = self.context.visibility
        return v.hfov_deg, v.width, v.height

    def _adopt_camera(self, K: np.ndarray, shape: tuple) -> None:
        """Plan candidate views for the camera that took the frames: its size and its horizontal
        field of view 2 atan(W / 2 fx) (lock held). The frustum is taken as symmetric with square
        pixels: the vertical field of view follows from the aspect ratio (fy = fx) and the
        principal point is the image centre, whatever cx, cy and fy say. A change replaces the
        candidates and masks (rebuilt with the next frame's); the same camera changes nothing."""
        height, width = int(shape[0]), int(shape[1])
        hfov_deg = float(np.degrees(2.0 * np.arctan(0.5 * width / float(K[0][0]))))
        v = self.context.visibility
        if (width, height) == (v.width, v.height) and abs(hfov_deg - v.hfov_deg) < CAMERA_FOV_EPS:
            return
        camera = replace(v, hfov_deg=hfov_deg, width=width, height=height)
        camera.validate()
        self.context.visibility = camera
        self.context.invalidate()

    def add_semantic(self, stamp_ns: int, u_sem: np.ndarray) -> bool:
        """Fuse U_sem (H, W) with the depth and pose of the same stamp; held back (bounded) until
        that frame arrives. Returns True if it was fused now."""
        with self._lock:
            frame = self._frames.get(int(stamp_ns))
            if frame is None:
                self._pending_semantic[int(stamp_ns)] = np.asarray(u_sem, np.float32)
                while len(self._pending_semantic) > self.config.frame_cache:
                    self._pending_semantic.popitem(last=False)
                return False
            self._fuse_semantic(int(stamp_ns), u_sem, frame)
            self.context.invalidate_fields()
            return True

    def _fuse_semantic(self, stamp_ns: int, u_sem: np.ndarray, frame: CachedFrame) -> None:
        """A semantic map replaces the one fused earlier for the same frame (a re-query's newer
        analysis), rather than being averaged with it (lock held)."""
        old = self._semantic_of.pop(stamp_ns, None)
        if old is not None:
            self.grid.retract_semantic(*old)
        self._semantic_of[stamp_ns] = self.grid.integrate_semantic(
            u_sem, frame.depth, frame.K, frame.T
        )

    def covers(self, stamp_ns: int, pose: np.ndarray | None = None, near=None) -> bool:
        """The map holds the frame `stamp_ns` (0 = none asked): it was fused, or, with `near`
        (a streaming camera's keyframe rule, `KeyframeConfig.near`: the frame may have been
        skipped), a frame at or after that stamp was, or one taken near `pose` (lock held or
        not: a read of append-only state)."""
        if stamp_ns <= 0 or stamp_ns in self._fused_stamps:
            return True
        if near is None:
            return False
        if self.last_fused_stamp >= stamp_ns:
            return True
        return pose is not None and any(near(pose, T) for T in self.context.camera_poses[::-1])

    def stale_note(self, stamp_ns: int, waited_s: float) -> str:
        """What an answer planned without the request's frame says: the newest frame it planned
        from and how much older it is."""
        with self._lock:
            last = self.last_fused_stamp
        if last == 0:
            return f"frame {stamp_ns} not fused within {waited_s:g} s, and none before it"
        return (
            f"frame {stamp_ns} not fused within {waited_s:g} s: planned from the map up to frame "
            f"{last}, {(stamp_ns - last) / 1e9:.2f} s older"
        )

    # ------------------------------------------------------------------ planning
    def remaining_budget(self) -> int:
        """Views the budget still allows: budget - (initial views + views handed out). Before
        the first request the frames fused so far count as the initial views (at most
        `initial_views`); frames a streaming camera sends in between never count."""
        return max(0, self.budget - self.views_spent())

    def views_spent(self) -> int:
        """Initial views + views handed out (and not released)."""
        if self.initial_frames is None:
            return min(self.grid.frames, self.initial_limit) + self.committed
        return self.initial_counted + self.committed

    def status(self) -> dict:
        return {
            "frames_fused": self.grid.frames,
            "last_fused_stamp_ns": self.last_fused_stamp,
            "semantic_frames_fused": self.grid.semantic_frames,
            "mode": self.config.mode,
            "policy": self.config.policy,
            "level": self.context.visibility.level,
            "voxel_size": self.grid.spec.voxel_size,
            "committed_views": self.committed,
            "budget": {
                "views": self.budget,
                "initial": self.initial_counted
                if self.initial_frames is not None
                else min(self.grid.frames, self.initial_limit),
                "handed_out": self.committed,
                "spent": self.views_spent(),
            },
            "remaining_budget": self.remaining_budget(),
            "hard_voxels": int(self.grid.hard().sum()),
            "rebuild_failures": self.rebuild_failures,
            "last_rebuild_error": self.last_rebuild_error,
            "camera": dict(zip(("hfov_deg", "width", "height"), self.camera(), strict=True)),
            "cache_ready": self.cache_ready(),
            "last_request_s": self.last_request_s,
        }

    def plan(self, request: PlanRequest) -> tuple[list[np.ndarray], str]:
        """(poses, reason) of `plan_views` (without the gains)."""
        plan = self.plan_views(request)
        return plan.poses, plan.reason

    def plan_views(self, request: PlanRequest) -> Plan:
        """`begin_plan` and `finish_plan` at once: with the background rebuild, from the masks in
        place, whether or not they cover the request's frame (`scheduler.py` waits for them)."""
        ticket = self.begin_plan(request)
        return ticket if isinstance(ticket, Plan) else self.finish_plan(ticket)

    def begin_plan(self, request: PlanRequest) -> PlanTicket | Plan:
        """Check a request and count what it tells the budget (`_settle`): its ticket for
        `finish_plan`, or an empty plan with the reason it gets none."""
        with self._lock:
            self._settle(request)
            checked = self._check_request(request)
            if isinstance(checked, str):
                return Plan([], [], checked)
            want, remaining = checked
            target = self._stamp_version.get(int(request.stamp_ns), self._map_version)
            pipelines = self._pipelines(request)
            base = self._pipeline_base
            # the first request, or the same frame again: masks of its own frame
            base = base if pipelines and 0 < base < target else 0
            closed_loop = (request.mode or self.config.mode) == "closed_loop"
            return PlanTicket(
                request, want, remaining, closed_loop, target, pipelines, base, time.perf_counter()
            )

    def finish_plan(self, ticket: PlanTicket, base_ready: bool = True, ready: bool = True) -> Plan:
        """Poses (T_world_cam, optical frame) for a checked request, their predicted gains, and a
        reason ("" when all is well). With the background rebuild the caller says whether the
        masks of the previous request's frame (`base_ready`, pipelined) or those of its own frame
        (`ready`) were rebuilt in time.

        Empty plan when: the request asks for more views than there are candidates, no valid
        candidate seed, masks not rebuilt in time, or no candidate sees the region of interest.

        A policy that selects from a snapshot (`Policy.map_free`: AREA3D and the other greedy
        fields) does so outside the map's lock, so frames arriving meanwhile are fused at once;
        the map is only locked to take the snapshot (the field of the current evidence) and to
        keep the committed views afterwards. Plans are to run one at a time.
        """
        request, want, remaining = ticket.request, ticket.want, ticket.remaining
        snapshot = None
        with self._lock:
            pipelined = self._pipelined_masks(ticket.base) if ticket.base and base_ready else None
            if pipelined is None:
                if not ready:
                    return Plan([], [], f"visibility cache: not rebuilt within {CACHE_WAIT_S} s")
                if self._pipelines() and not self.background:
                    if self._cache_version < self._map_version:
                        self._update_masks()
                version, stamp, masks = self._cache_version, self._cache_stamp, None
            else:
                version, stamp, masks = pipelined
            if ticket.pipelines:
                self._pipeline_base = ticket.target  # the next request plans from these masks
            t1 = time.perf_counter()
            behind = 0  # fused frames the masks leave out
            if self.background or self._pipelines():
                behind = max(0, self._map_version - version)
            # published whole, never changed after: the node reads it from other threads
            timings = {"wait_cache": t1 - ticket.started, "masks_frames_behind": behind}
            if request.stamp_ns > 0:  # how far the masks planned with lag the request's frame
                timings["masks_behind"] = max(0, int(request.stamp_ns) - stamp) / 1e9
            self.last_plan_s = timings
            start = None if request.start is None else np.asarray(request.start, float)
            self.context.start = start
            try:
                seeds, rotations = masks[0] if masks else self.context.candidates()
                # positions the frames the masks leave out show too close to geometry
                self.context.blocked_seeds = (
                    ~self.context.valid_positions(seeds, self.grid.occupancy())
                    if behind > 0 and self.policy.map_free
                    else None
                )
                if seeds.shape[0] == 0:
                    return Plan(
                        [],
                        [],
                        "workspace: no valid candidate seed (empty or degenerate workspace, or all of it too close to geometry)",
                    )
                candidates = seeds.shape[0] * rotations.shape[1]
                if want > candidates:
                    return Plan(
                        [],
                        [],
                        f"{request.count_field}: got {want}, expected at most the {candidates} "
                        "candidate views",
                    )
                if self.policy.sequential:
                    if self._sequence is None:  # planned once, handed out in order
                        self._sequence = self.policy.select_views(self.context, remaining)
                    views, self._sequence = self._sequence.split(want)
                elif self.policy.map_free:
                    snapshot = self.context.snapshot(self.policy, masks)
                else:
                    views = self.policy.select_views(self.context, want)
            except InputError as exc:
                return Plan([], [], str(exc))
        if snapshot is not None:  # the selection itself: fusion goes on meanwhile
            try:
                views = self.policy.select_views(snapshot, want)
            except InputError as exc:
                return Plan([], [], str(exc))
        with self._lock:
            if snapshot is not None:
                self.context.adopt(snapshot)
            self.last_plan_s = timings | {"select": time.perf_counter() - t1}
            if not views.poses:
                return Plan([], [], "no candidate view sees the region of interest")
            self.committed += len(views.poses)
            self._handed_out = (
                (int(request.stamp_ns), self.grid.frames, len(views.poses))
                if ticket.closed_loop and request.stamp_ns > 0
                else None
            )
            note = "; ".join(n for n in (views.note, self._repeats(views.poses)) if n)
            self._answered += [(np.array(T, float), int(request.stamp_ns)) for T in views.poses]
            return Plan(list(views.poses), list(views.gains), "", note)

    def _repeats(self, poses: list) -> str:
        """`requests.repeats_note` for views about to be handed out (lock held)."""
        g = self.context.greedy
        fused = list(zip(self._fused_order, self.context.camera_poses, strict=False))
        return repeats_note(poses, self._answered, fused, g.nms_radius, g.nms_angle_deg)

    def _settle(self, request: PlanRequest) -> None:
        """What a request tells the budget's bookkeeping, before it is checked (lock held): the
        frames fused before the first request are the initial views; a closed-loop request
        releases the views of the last plan if they were not captured (`_release_uncaptured`)."""
        if self.grid.frames == 0:
            return
        if self.initial_frames is None:
            self.initial_frames = self.grid.frames
            self.initial_counted = min(self.grid.frames, self.initial_limit)
            self.context.initial_views = self.initial_frames
        if (request.mode or self.config.mode) == "closed_loop":
            self._release_uncaptured(request)

    def _release_uncaptured(self, request: PlanRequest) -> None:
        """A closed-loop request from the same frame as the last plan, with no frame fused since,
        means the views handed out then were not captured (the camera refused them: inside
        geometry it knows and the map does not, out of reach): they no longer count against the
        budget (their decay stays, so the next plan looks elsewhere). Lock held."""
        last = self._handed_out
        if last is not None and int(request.stamp_ns) == last[0] and self.grid.frames == last[1]:
            self.committed -= last[2]
            self._handed_out = None

    def _check_request(self, request: PlanRequest) -> tuple[int, int] | str:
        """`requests.check_request` on this map (lock held, after `_settle`; changes nothing)."""
        spent = (
            f"budget: all {self.budget} views are spent ({self.initial_counted} initial, "
            f"{self.committed} handed out)"
        )
        sums = {"geometric": self.grid.conf_sum, "semantic": self.grid.sem_sum}
        remaining = self.remaining_budget()
        return check_request(request, self.grid.frames, self.config.mode, remaining, spent, sums)
