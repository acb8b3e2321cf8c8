"""The planning context every policy selects from: the fused grid, the workspace, the candidate
views (seeds and orientation bins) with their visibility masks, the views committed so far and
their decay; and `SelectedViews`, what a policy returns. Policies: `policies.py`.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

import numpy as np

from area3d_msgs_py.errors import InputError
from area3d_planner.candidates import (
    VisibilityParams,
    lattice_positions,
    orientation_bins,
    shell_positions,
    shell_rotations,
    valid_seeds,
)
from area3d_planner.fusion import FREE, UNKNOWN, FusedGrid
from area3d_planner.greedy import (
    GreedyParams,
    decay_committed,
    range_gain,
)
from area3d_planner.visibility import ViewEvidence, VisibilityCache

if TYPE_CHECKING:
    from area3d_planner.policies import GreedyFieldPolicy, Policy


@dataclass(frozen=True)
class SelectedViews:
    """A policy's choice: `poses` (4x4 T_world_cam, optical frame) best first, and `gains`, the
    predicted gain of each: the utility the greedy selection committed it with (the mask-weighted
    uncertainty it sees, times the range prior, plus the distance prior), before the committed
    view is turned to the centroid of what it sees. 0 for the policies that predict none (uniform,
    random). `note`: what the answer should tell the caller about how they were chosen (a
    coverage view, `policies.coverage_view`), or ""."""

    poses: list = field(default_factory=list)
    gains: list = field(default_factory=list)
    note: str = ""

    @classmethod
    def unscored(cls, poses: list) -> SelectedViews:
        return cls(list(poses), [0.0] * len(poses))

    def __len__(self) -> int:
        return len(self.poses)

    def split(self, n: int) -> tuple[SelectedViews, SelectedViews]:
        """(the first `n` views, the rest), each with its gains."""
        return (
            SelectedViews(self.poses[:n], self.gains[:n]),
            SelectedViews(self.poses[n:], self.gains[n:]),
        )


@dataclass
class PlanningContext:
    """Everything a policy needs. Caches are built on first use and reused until `invalidate()`.

    What the planner knows is what a robot has: the fused map (`grid`), the captured camera
    positions, the region of interest (the grid's ROI box) and the workspace box where the camera
    may go. Nothing of the simulator's geometry.
    """

    grid: FusedGrid
    workspace_lo: np.ndarray
    workspace_hi: np.ndarray
    clearance: float = 0.05  # metres from the camera centre to the nearest occupied voxel
    visibility: VisibilityParams = field(default_factory=VisibilityParams)
    greedy: GreedyParams = field(default_factory=GreedyParams)
    start: np.ndarray | None = None  # (4, 4) current camera pose or (3,) position
    rng_seed: int = 0
    committed_decay: np.ndarray | None = None  # (N,) decay of views committed so far
    aim_views: bool = True  # turn each committed view to the centroid of the utility it sees
    camera_positions: list = field(default_factory=list)  # (3,) centres of the fused frames
    camera_poses: list = field(default_factory=list)  # (4, 4) poses of the fused frames
    # how many of the fused frames were the initial views (set at the first plan): the working
    # distance is theirs, the operator's choice, and does not drift with the views planned since
    initial_views: int | None = None
    # the gain of the first view planned after them (`GreedyParams.coverage_below` compares with
    # it); None before the first plan
    first_gain: float | None = None
    # (S,) bool: candidate positions a view may not be taken from although the masks allow it
    # (the planner's newest frames, which the masks leave out, show them too close to geometry)
    blocked_seeds: np.ndarray | None = None
    _candidates: tuple | None = None
    _caches: dict = field(default_factory=dict)
    _fields: dict = field(default_factory=dict)
    _evidence: ViewEvidence | None = None
    _previous: dict = field(default_factory=dict)  # caches the next build brings up to date

    def invalidate(self) -> None:
        """Forget candidates, visibility masks and fields (the occupancy changed); the next
        build of the masks updates the ones forgotten (`VisibilityCache.update`)."""
        self._candidates = None
        self._previous.update(self._caches)
        self._caches.clear()
        self._fields.clear()
        self._evidence = None

    def invalidate_fields(self) -> None:
        """Forget the memoised utility fields and view evidence only (new evidence, masks still
        current)."""
        self._fields.clear()
        self._evidence = None

    def evidence(self) -> ViewEvidence:
        """What the fused frames weigh each mask entry by when views are scored (the grid's
        direction bits and range profile, `ViewEvidence`), memoised until the next frame."""
        if self._evidence is None:
            self._evidence = ViewEvidence.of_grid(self.grid.view_evidence(), self.visibility)
        return self._evidence

    def policy_field(self, policy: GreedyFieldPolicy) -> np.ndarray:
        """(N,) utility field of `policy` (memoised until the next invalidation, read only), with
        the frustum decay of the views committed by earlier requests applied."""
        field = self._field(policy)
        if self.committed_decay is None:
            return field
        return field * self.committed_decay

    def _field(self, policy: GreedyFieldPolicy) -> np.ndarray:
        """The policy's field without the committed decay, memoised."""
        if policy.name not in self._fields:
            self._fields[policy.name] = policy.field(self)
        return self._fields[policy.name]

    def masks(self) -> tuple[tuple | None, dict]:
        """(candidates, caches) as installed, for `snapshot` to select from later."""
        return self._candidates, dict(self._caches)

    def snapshot(self, policy: Policy, masks: tuple | None = None) -> PlanningContext:
        """A copy from which `policy` (a `Policy.map_free` one) selects views while the map goes
        on changing: the candidates, the policy's visibility cache and its field are made now
        (under the caller's lock) and shared read only; the camera poses and the committed decay
        are copied. The copy reads of the grid only its spec and region, which never change.
        `adopt` takes the decay of the views it committed back. With `masks` (of `masks()`,
        from an earlier map) it selects from those candidates and caches instead."""
        caches = {}
        fields = {}
        candidates = self.candidates() if masks is None else masks[0]
        if policy.relevant is not None:
            cache = None if masks is None else masks[1].get(policy.relevant)
            caches[policy.relevant] = cache or self._cache(policy.relevant)
            fields[policy.name] = self._field(policy)
        return replace(
            self,
            camera_positions=list(self.camera_positions),
            camera_poses=list(self.camera_poses),
            committed_decay=None if self.committed_decay is None else self.committed_decay.copy(),
            _candidates=candidates,
            _caches=caches,
            _fields=fields,
            _evidence=self.evidence() if policy.relevant is not None else None,
            _previous={},
        )

    def adopt(self, snapshot: PlanningContext) -> None:
        """Keep the committed decay of views selected on `snapshot` (taken from this context)
        and the first planned view's gain."""
        self.committed_decay = snapshot.committed_decay
        self.first_gain = snapshot.first_gain

    def commit(self, cache: VisibilityCache, views: list[int], poses: list[np.ndarray]) -> None:
        """Remember the decay u <- (1 - eta) u of committed views (at the poses really taken) for
        the requests that follow.

        The paper decays the field inside the frustum after every committed view; in closed loop
        each request starts a new selection, so without this the planner would send the camera
        back to a view already taken whenever the new frame leaves that view's uncertainty high
        (voxels the visibility expects to see but the camera cannot).
        """
        if self.committed_decay is None:
            self.committed_decay = np.ones(self.grid.spec.num_voxels)
        for view, pose in zip(views, poses, strict=True):
            decay_committed(
                cache, self.committed_decay, view, self.greedy.eta, self.greedy.decay, pose
            )

    def region_centre(self) -> np.ndarray:
        return 0.5 * (self.grid.roi_lo + self.grid.roi_hi)

    def region_half_diagonal(self) -> float:
        return 0.5 * float(np.linalg.norm(self.grid.roi_hi - self.grid.roi_lo))

    def default_distance(self) -> float:
        """Shell radius before any frame is captured: the region's half diagonal plus 0.3 m."""
        return self.region_half_diagonal() + 0.3

    def valid_positions(self, points: np.ndarray, occupancy: np.ndarray) -> np.ndarray:
        """(P,) bool: camera centres `points` (P, 3) the map allows (`valid_seeds`); at object
        level unknown space outside the region (grown by clearance and a voxel) counts as usable."""
        g = self.grid
        outside = None
        if self.visibility.level == "object":
            margin = self.clearance + g.spec.voxel_size
            outside = (g.roi_lo - margin, g.roi_hi + margin)
        return valid_seeds(
            points,
            g.spec,
            occupancy,
            self.workspace_lo,
            self.workspace_hi,
            self.clearance,
            unknown_ok_outside=outside,
        )

    def candidate_views(self, occupancy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(positions (S, 3), rotations (S, B, 3, 3)) of the candidate views for an occupancy
        snapshot (N,) int8: shells around the region at object level, a known-free lattice
        inside it at room level (see `candidates.py`)."""
        p = self.visibility
        if p.level == "object":
            centre = self.region_centre()
            radius = self.working_distance() or self.default_distance()
            points = shell_positions(centre, radius, p)
            usable = self.valid_positions(points, occupancy)
            if not usable.any() and p.near > VisibilityParams.near:
                points, usable = self._shells_beyond_min_range(occupancy, centre, radius)
            points = points[usable]
            return points, shell_rotations(points, centre, p.fan_deg)
        points = lattice_positions(self.workspace_lo, self.workspace_hi, p.seed_spacing)
        points = points[self.valid_positions(points, occupancy)]
        _, rotations = orientation_bins(p)
        return points, np.broadcast_to(rotations, (points.shape[0], *rotations.shape)).copy()

    def _shells_beyond_min_range(
        self, occupancy: np.ndarray, centre: np.ndarray, radius: float
    ) -> tuple[np.ndarray, np.ndarray]:
        """(positions (S, 3), usable (S,) bool) of the candidate shells moved out until the whole
        region lies beyond a camera's minimum range (`min_range`): the inner shell that range
        beyond the region's half diagonal, around the region's `centre`.

        Only when the minimum range leaves no usable position at the working distance `radius`
        (the clearance, at least that range, keeps positions away from what the map holds and,
        inside the region, from what it does not know yet). Moving them out whenever a minimum
        range was set took them to 1.3-1.8x the working distance with the stereo pair's 0.2 m,
        and cost `area3d` its lead over `uniform` (docs/results.md); stopping at the first
        radius with a usable position left a Kinect-class camera (0.5 m) views that saw almost
        none of the region."""
        p = self.visibility
        radius = max(radius, (p.near + self.region_half_diagonal()) / min(p.shell_scales))
        points = shell_positions(centre, radius, p)
        return points, self.valid_positions(points, occupancy)

    def build(self, occupancy: np.ndarray, kinds: tuple = ()) -> tuple[tuple, dict]:
        """Candidate views and the visibility caches named in `kinds` (see `cache`) for an
        occupancy snapshot (N,) int8, without touching the context: ((seeds, rotations),
        caches). The masks depend on the occupancy alone (the evidence weighs them when views
        are scored, `evidence`)."""
        candidates = self.candidate_views(occupancy)
        caches = {kind: self._build_cache(kind, occupancy, *candidates) for kind in kinds}
        return candidates, caches

    def _build_cache(
        self, kind: str, occupancy: np.ndarray, seeds: np.ndarray, rotations: np.ndarray
    ) -> VisibilityCache:
        relevant = self._relevant(kind, occupancy)
        occluders, seen_into = self._unknown_in_view(occupancy)
        if occluders is not None:
            relevant &= occluders if seen_into is None else occluders | seen_into
        base = self._caches.get(kind) or self._previous.pop(kind, None)
        if base is not None:  # what the map changed since, re-examined only where it shows
            return base.update(occupancy, seeds, rotations, relevant, occluders=occluders)
        return VisibilityCache.build(
            self.grid.spec,
            occupancy,
            seeds,
            rotations,
            self.visibility,
            relevant=relevant,
            occluders=occluders,
            incremental=True,
        )

    def occluders(self, occupancy: np.ndarray) -> np.ndarray | None:
        """(N,) bool: the voxels that hide what lies behind them, or None where only occupied
        voxels do (`unknown_occludes: false`). Everything not carved hides what is behind it,
        so only its boundary with carved space can be seen; with `unknown_see_through`, unknown
        space hides what lies deeper than that behind the boundary (its layer at that depth
        occludes; `seen_into` is what a view sees in front of it). At object level, unknown space
        over the region (above its top, within its footprint) does not (`unknown_above_occludes:
        false`): a view from above sees the region through it, and a surface there occludes
        once a frame maps it."""
        return self._unknown_in_view(occupancy)[0]

    def seen_into(self, occupancy: np.ndarray) -> np.ndarray | None:
        """(N,) bool: the unknown voxels within `unknown_see_through` of carved space, which a
        view sees in front of the layer that occludes (`occluders`); None without see-through."""
        return self._unknown_in_view(occupancy)[1]

    def _unknown_in_view(self, occupancy: np.ndarray) -> tuple:
        """(`occluders`, `seen_into`) of one occupancy, each dilation of carved space done once."""
        if not self.visibility.unknown_occludes:
            return None, None
        occluders = self.grid.boundary(occupancy)
        if not (layers := self._see_through_layers()):
            return self._over_region_hides_nothing(occluders, occupancy), None
        unknown = occupancy == UNKNOWN
        seen = unknown & self.grid.near_free(occupancy, layers)
        deeper = unknown & self.grid.near_free(occupancy, layers + 1) & ~seen
        occluders = (occluders & ~unknown) | deeper
        return tuple(self._over_region_hides_nothing(m, occupancy) for m in (occluders, seen))

    def _see_through_layers(self) -> int:
        return int(round(self.visibility.unknown_see_through / self.grid.spec.voxel_size))

    def _over_region_hides_nothing(self, mask: np.ndarray, occupancy: np.ndarray) -> np.ndarray:
        """`mask` without the unknown voxels over the region, at object level unless
        `unknown_above_occludes`: neither occluders nor counted."""
        if self.visibility.level == "object" and not self.visibility.unknown_above_occludes:
            mask &= ~self.grid.over_region | (occupancy != UNKNOWN)
        return mask

    def install(self, candidates: tuple, caches: dict) -> None:
        """Use candidates and caches made by `build` (replaces the current ones and the fields)."""
        self._candidates = candidates
        self._caches = dict(caches)
        self._fields.clear()

    def _relevant(self, kind: str, occupancy: np.ndarray) -> np.ndarray:
        if kind != "roi_not_free":
            raise InputError("visibility cache", kind, "'roi_not_free'")
        return self.grid.roi_mask & (occupancy != FREE)

    def working_distance(self) -> float | None:
        """Median distance of the initial views' cameras to the ROI centre (of every captured
        frame before the first plan; None before any). Planned views do not move it: with every
        captured view counted, views taken on the outer shell pushed the shells outwards
        (0.44 -> 0.70 m over an object episode)."""
        positions = self.camera_positions[: self.initial_views or None]
        if not positions:
            return None
        c = self.region_centre()
        return float(np.median(np.linalg.norm(np.asarray(positions) - c, axis=1)))

    def range_gain(self, seeds: np.ndarray) -> np.ndarray | None:
        """(S,) range prior of `seeds` around the working distance (None: no prior)."""
        return range_gain(
            seeds, self.region_centre(), self.working_distance(), self.greedy.range_sigma
        )

    @property
    def start_position(self) -> np.ndarray | None:
        if self.start is None:
            return None
        s = np.asarray(self.start, np.float64)
        return s[:3, 3] if s.shape == (4, 4) else s.reshape(3)

    def candidates(self) -> tuple[np.ndarray, np.ndarray]:
        """(positions (S, 3), rotations (S, B, 3, 3)) of the current candidate views."""
        if self._candidates is None:
            self._candidates = self.candidate_views(self.grid.occupancy())
        return self._candidates

    def seeds(self) -> np.ndarray:
        return self.candidates()[0]

    def cache(self, relevant: str = "roi_not_free") -> VisibilityCache:
        """Visibility cache recording the ROI voxels that are not known free, scored under the
        current evidence (`evidence`)."""
        return self._cache(relevant).bind(self.evidence())

    def _cache(self, relevant: str) -> VisibilityCache:
        if relevant not in self._caches:
            occ = self.grid.occupancy()
            self._caches[relevant] = self._build_cache(relevant, occ, *self.candidates())
        return self._caches[relevant]
