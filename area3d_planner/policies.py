"""View selection policies: AREA3D and the baselines, behind one interface.

A policy maps a planning context to at most `budget` camera poses (4x4 T_world_cam, optical
frame). Ablations are configuration of the `area3d` policy, not policies: without VLM =
semantic_weight 0, gamma = 0 = gamma 0 in the FusedGrid, without feed-forward = uniform
confidence upstream (perception).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from area3d_msgs_py.errors import InputError
from area3d_planner.fusion import FREE, FusedGrid
from area3d_planner.greedy import GreedyParams, Selection, lazy_greedy, range_gain
from area3d_planner.raycast import decay_view
from area3d_planner.visibility import (
    VisibilityCache,
    VisibilityParams,
    candidate_seeds,
    look_at,
    orientation_bins,
)

GOLDEN_ANGLE = np.pi * (3.0 - np.sqrt(5.0))


@dataclass
class PlanningContext:
    """Everything a policy needs. Caches are built on first use and reused until `invalidate()`."""

    grid: FusedGrid
    workspace_lo: np.ndarray
    workspace_hi: np.ndarray
    seed_spacing: float = 0.1  # metres; object level 0.1, room level 0.5 (our choice)
    clearance: float = 0.05  # metres, same as sim_bridge.validity.check_pose
    visibility: VisibilityParams = field(default_factory=VisibilityParams)
    greedy: GreedyParams = field(default_factory=GreedyParams)
    start: np.ndarray | None = None  # (4, 4) current camera pose or (3,) position
    rng_seed: int = 0
    scene: object | None = None  # sim_bridge Scene: adds its validity check to the seeds
    allow_unknown_seeds: bool | None = None  # default: True with a scene, False without
    committed_decay: np.ndarray | None = None  # (N,) decay of views committed so far
    aim_views: bool = True  # turn each committed view to the centroid of the utility it sees
    camera_positions: list = field(default_factory=list)  # (3,) centres of the fused frames
    _seeds: np.ndarray | None = None
    _caches: dict = field(default_factory=dict)
    _fields: dict = field(default_factory=dict)

    def invalidate(self) -> None:
        """Forget seeds, visibility masks and fields (the occupancy changed)."""
        self._seeds = None
        self._caches.clear()
        self._fields.clear()

    def invalidate_fields(self) -> None:
        """Forget the memoised utility fields only (new evidence, masks still current)."""
        self._fields.clear()

    def policy_field(self, policy: GreedyFieldPolicy) -> np.ndarray:
        """(N,) utility field of `policy` (memoised until the next invalidation, read only), with
        the frustum decay of the views committed by earlier requests applied."""
        if policy.name not in self._fields:
            self._fields[policy.name] = policy.field(self)
        if self.committed_decay is None:
            return self._fields[policy.name]
        return self._fields[policy.name] * self.committed_decay

    def commit(self, cache: VisibilityCache, views: list[int]) -> None:
        """Remember the decay u <- (1 - eta) u of committed views for the requests that follow.

        The paper decays the field inside its frustum after every committed view; in closed loop
        each request starts a new selection, so without this the planner would send the camera
        back to a view already taken whenever the new frame leaves that view's uncertainty high
        (voxels the optimistic visibility expects to see but the camera cannot).
        """
        if self.committed_decay is None:
            self.committed_decay = np.ones(self.grid.spec.num_voxels)
        for view in views:
            decay_view(
                cache.indptr, cache.voxel_ids, self.committed_decay, view, 1.0 - self.greedy.eta
            )

    def build(self, occupancy: np.ndarray, kinds: tuple = ()) -> tuple[np.ndarray, dict]:
        """Seeds and the visibility caches named in `kinds` (see `cache`) for an occupancy
        snapshot (N,) int8, without touching the context: (seeds (S, 3), {kind: cache})."""
        allow = self.allow_unknown_seeds
        if allow is None:
            allow = self.scene is not None
        seeds = candidate_seeds(
            self.workspace_lo,
            self.workspace_hi,
            self.seed_spacing,
            self.grid.spec,
            occupancy,
            self.clearance,
            allow_unknown=allow,
            scene=self.scene,
        )
        caches = {
            kind: VisibilityCache.build(
                self.grid.spec,
                occupancy,
                seeds,
                self.visibility,
                relevant=self._relevant(kind, occupancy),
            )
            for kind in kinds
        }
        return seeds, caches

    def install(self, seeds: np.ndarray, caches: dict) -> None:
        """Use seeds and caches made by `build` (replaces the current ones and the fields)."""
        self._seeds = seeds
        self._caches = dict(caches)
        self._fields.clear()

    def _relevant(self, kind: str, occupancy: np.ndarray) -> np.ndarray:
        if kind == "roi_not_free":
            return self.grid.roi_mask & (occupancy != FREE)
        return self.grid.roi_mask

    def working_distance(self) -> float | None:
        """Median distance of the captured frames' cameras to the ROI centre (None before any)."""
        if not self.camera_positions:
            return None
        c = 0.5 * (self.grid.roi_lo + self.grid.roi_hi)
        return float(np.median(np.linalg.norm(np.asarray(self.camera_positions) - c, axis=1)))

    def range_gain(self, seeds: np.ndarray) -> np.ndarray | None:
        """(S,) range prior of `seeds` around the working distance (None: no prior)."""
        c = 0.5 * (self.grid.roi_lo + self.grid.roi_hi)
        return range_gain(seeds, c, self.working_distance(), self.greedy.range_sigma)

    @property
    def start_position(self) -> np.ndarray | None:
        if self.start is None:
            return None
        s = np.asarray(self.start, np.float64)
        return s[:3, 3] if s.shape == (4, 4) else s.reshape(3)

    def seeds(self) -> np.ndarray:
        if self._seeds is None:
            self._seeds, _ = self.build(self.grid.occupancy())
        return self._seeds

    def cache(self, relevant: str = "roi_not_free") -> VisibilityCache:
        """Visibility cache recording the ROI voxels that are not known free ("roi_not_free") or
        every ROI voxel ("roi", for fields that are non-zero on free space)."""
        if relevant not in self._caches:
            occ = self.grid.occupancy()
            self._caches[relevant] = VisibilityCache.build(
                self.grid.spec,
                occ,
                self.seeds(),
                self.visibility,
                relevant=self._relevant(relevant, occ),
            )
        return self._caches[relevant]


class Policy:
    """Interface: `select_views(context, budget) -> list of (4, 4) T_world_cam`.

    A `sequential` policy does not look at the fused field: it plans its whole view sequence once
    and the server hands the views out in order, so closed-loop requests continue the sequence
    instead of starting it again.
    """

    name = ""
    sequential = False
    relevant: str | None = None  # the visibility cache it plans with (None: seeds only)

    def select_views(self, context: PlanningContext, budget: int) -> list[np.ndarray]:
        raise NotImplementedError


class GreedyFieldPolicy(Policy):
    """Lazy greedy (Algorithm 1) on a utility field provided by `field(context)`."""

    relevant = "roi_not_free"

    def field(self, context: PlanningContext) -> np.ndarray:
        raise NotImplementedError

    def selection(self, context: PlanningContext, budget: int) -> Selection:
        U = context.policy_field(self)
        if not np.all(np.isfinite(U)):
            raise InputError("uncertainty field", "NaN or inf voxels", "finite uncertainties")
        cache = context.cache(self.relevant)
        gain = context.range_gain(cache.seeds)
        return lazy_greedy(cache, U, budget, context.greedy, context.start_position, gain)

    def select_views(self, context: PlanningContext, budget: int) -> list[np.ndarray]:
        cache = context.cache(self.relevant)
        U = context.policy_field(self) if context.aim_views else None
        views = self.selection(context, budget).views
        context.commit(cache, views)
        if U is None:
            return [cache.view_pose(v) for v in views]
        return [aim_at_uncertainty(cache, v, U) for v in views]


def aim_at_uncertainty(cache: VisibilityCache, view: int, U: np.ndarray) -> np.ndarray:
    """The committed view turned to look at the utility-weighted centroid of what it sees.

    Orientation bins are coarse (30 degree yaw steps); once the seed and bin are chosen, the
    camera keeps its position and centres the uncertainty its mask covers (the paper's "fan of
    orientations" at the chosen seed, resolved in closed form). A view that sees no utility keeps
    its bin orientation.
    """
    ids, weights = cache.mask(view)
    mass = weights * U[ids]
    T = cache.view_pose(view)
    total = float(mass.sum())
    if ids.size == 0 or not total > 0:
        return T
    ijk = np.stack(np.unravel_index(ids, cache.spec.shape), axis=1)
    centres = cache.spec.lower + (ijk + 0.5) * cache.spec.voxel_size
    target = (mass[:, None] * centres).sum(axis=0) / total
    if np.linalg.norm(target - T[:3, 3]) < 1e-6:
        return T
    return look_at(T[:3, 3], target)


class Area3DPolicy(GreedyFieldPolicy):
    """The paper: fused field U = geometric + semantic_weight * semantic + gamma."""

    name = "area3d"

    def field(self, context: PlanningContext) -> np.ndarray:
        return context.grid.fused()


class VolumetricIGPolicy(GreedyFieldPolicy):
    """Classic volumetric information gain: binary entropy of occupancy, no confidence, no VLM."""

    name = "volumetric_ig"
    relevant = "roi"

    def field(self, context: PlanningContext) -> np.ndarray:
        return context.grid.entropy()


class UniformPolicy(Policy):
    """Evenly spread views on the upper half of a Fibonacci sphere around the ROI centre.

    Radius: the median distance of the captured frames (the initial views) to the ROI centre,
    i.e. the working distance the operator chose, capped at 95 % of the largest radius that keeps
    the hemisphere inside the workspace and at the max range; every view looks at the ROI centre.
    A view that is not a valid camera position is replaced by the nearest valid candidate seed,
    still looking at the centre.
    """

    name = "uniform"
    sequential = True

    def select_views(self, context: PlanningContext, budget: int) -> list[np.ndarray]:
        n = int(budget)
        if n <= 0:
            return []
        g = context.grid
        c = 0.5 * (g.roi_lo + g.roi_hi)
        lo, hi = np.asarray(context.workspace_lo, float), np.asarray(context.workspace_hi, float)
        r_fit = min(c[0] - lo[0], hi[0] - c[0], c[1] - lo[1], hi[1] - c[1], hi[2] - c[2])
        radius = 0.95 * min(r_fit, context.visibility.max_range)
        working = context.working_distance()
        if working is not None:
            radius = min(radius, working)
        if radius <= 0:
            radius = 0.5 * float(np.min(hi - lo))
        i = np.arange(n)
        z = (i + 0.5) / n
        rxy = np.sqrt(1 - z**2)
        phi = i * GOLDEN_ANGLE
        pts = c + radius * np.stack([rxy * np.cos(phi), rxy * np.sin(phi), z], axis=1)
        seeds = context.seeds()
        valid = _valid_points(context, pts)
        poses = []
        for p, ok in zip(pts, valid, strict=True):
            if not ok:
                if seeds.size == 0:
                    continue
                p = seeds[int(np.argmin(np.linalg.norm(seeds - p, axis=1)))]
            poses.append(look_at(p, c))
        return poses


def _valid_points(context: PlanningContext, pts: np.ndarray) -> np.ndarray:
    """(N,) bool: the candidate-seed validity rules applied to arbitrary points."""
    g = context.grid
    ok = np.all((pts >= context.workspace_lo) & (pts <= context.workspace_hi), axis=1)
    occ = g.occupancy()
    occupied = np.flatnonzero(occ == 1)
    if occupied.size:
        from scipy.spatial import cKDTree

        d, _ = cKDTree(g.spec.centers()[occupied]).query(pts, k=1)
        ok &= d > context.clearance + 0.5 * g.spec.voxel_size
    if context.scene is not None and ok.any():
        ok &= np.asarray(context.scene.valid_positions(pts, context.clearance), dtype=bool)
    return ok


class VLMNaivePolicy(GreedyFieldPolicy):
    """Views towards VLM-flagged regions only: field = semantic in the ROI (no geometry, no gamma).

    Falls back to `uniform` while no semantic evidence has been fused.
    """

    name = "vlm_naive"

    def field(self, context: PlanningContext) -> np.ndarray:
        s = context.grid.semantic()
        s[~context.grid.roi_mask] = 0.0
        s[context.grid.occupancy() == FREE] = 0.0
        return s

    def select_views(self, context: PlanningContext, budget: int) -> list[np.ndarray]:
        if not np.any(context.policy_field(self) > 0):
            return UniformPolicy().select_views(context, budget)
        return super().select_views(context, budget)


class RandomPolicy(Policy):
    """Uniformly random candidate views (seed x orientation bin) whose optical axis hits the ROI box
    within max_range, drawn without replacement from a generator seeded with context.rng_seed."""

    name = "random"
    sequential = True

    def select_views(self, context: PlanningContext, budget: int) -> list[np.ndarray]:
        seeds = context.seeds()
        forward, rotations = orientation_bins(context.visibility)
        if seeds.size == 0:
            return []
        g = context.grid
        o = np.repeat(seeds, len(forward), axis=0)
        d = np.tile(forward, (len(seeds), 1))
        with np.errstate(divide="ignore", invalid="ignore"):
            t_a = (g.roi_lo - o) / d
            t_b = (g.roi_hi - o) / d
        t_near = np.nanmax(np.minimum(t_a, t_b), axis=1)
        t_far = np.nanmin(np.maximum(t_a, t_b), axis=1)
        hits = (t_far >= np.maximum(t_near, 0)) & (
            np.maximum(t_near, 0) <= context.visibility.max_range
        )
        views = np.flatnonzero(hits)
        rng = np.random.default_rng(context.rng_seed)
        chosen = rng.choice(views, size=min(int(budget), views.size), replace=False)
        poses = []
        for v in chosen:
            s, b = divmod(int(v), len(forward))
            T = np.eye(4)
            T[:3, :3] = rotations[b]
            T[:3, 3] = seeds[s]
            poses.append(T)
        return poses


POLICIES: dict[str, type[Policy]] = {
    p.name: p
    for p in (Area3DPolicy, VolumetricIGPolicy, VLMNaivePolicy, RandomPolicy, UniformPolicy)
}


def make_policy(name: str) -> Policy:
    """Policy by name: one of POLICIES."""
    if name not in POLICIES:
        raise InputError("policy", name, f"one of {', '.join(sorted(POLICIES))}")
    return POLICIES[name]()
