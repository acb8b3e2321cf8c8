"""View selection policies: AREA3D and the baselines, behind one interface.

A policy maps a planning context to at most `budget` camera poses (4x4 T_world_cam, optical
frame). Ablations are configuration of the `area3d` policy, not policies: without VLM =
semantic_weight 0, gamma = 0 = gamma 0 in the FusedGrid, without feed-forward = uniform
confidence upstream (perception).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from area3d_msgs_py.camera_pose import look_at
from area3d_msgs_py.errors import InputError
from area3d_planner.context import PlanningContext, SelectedViews
from area3d_planner.fusion import FREE
from area3d_planner.greedy import (
    Selection,
    lazy_greedy,
    near_taken,
    taken_views,
    unit_rows,
)
from area3d_planner.visibility import (
    VisibilityCache,
)

GOLDEN_ANGLE = np.pi * (3.0 - np.sqrt(5.0))


class Policy:
    """Interface: `select_views(context, budget) -> SelectedViews` (at most `budget` poses, each a
    (4, 4) T_world_cam, with their predicted gains).

    A `sequential` policy does not look at the fused field: it plans its whole view sequence once
    and the server hands the views out in order, so closed-loop requests continue the sequence
    instead of starting it again.
    """

    name = ""
    sequential = False
    relevant: str | None = None  # the visibility cache it plans with (None: seeds only)
    # selects from a `PlanningContext.snapshot` alone, without reading the map: the planner then
    # selects outside its lock, so frames go on being fused meanwhile
    map_free = False

    def select_views(self, context: PlanningContext, budget: int) -> SelectedViews:
        raise NotImplementedError


# selections run again when an aimed view repeats a taken one (each run leaves those views out)
AIM_RETRIES = 4
# Once the gains collapse (`coverage_below`), the views within this share of the best gain are
# taken as equals and the one in the direction least seen is chosen among them (our choice: a
# gain of a few voxels, many of them a depth estimator's false hits, tells views apart no better).
COVERAGE_KEEP = 0.5
# ... ordered by direction (a cosine) first: a gain counts as a cosine this many times smaller
DIRECTION_FIRST = 1e6
DIRECTION_BLOCK = 4096  # captured cameras compared with every candidate at once, at most


class GreedyFieldPolicy(Policy):
    """Lazy greedy (Algorithm 1) on a utility field provided by `field(context)`."""

    relevant = "roi_not_free"
    map_free = True

    def field(self, context: PlanningContext) -> np.ndarray:
        raise NotImplementedError

    def selection(
        self,
        context: PlanningContext,
        budget: int,
        U: np.ndarray | None = None,
        also_excluded: Sequence[int] = (),
    ) -> Selection:
        """Lazy greedy on the policy's field `U` (default: `context.policy_field`), without the
        candidates near views already taken and the views `also_excluded`."""
        U = context.policy_field(self) if U is None else U
        if not np.all(np.isfinite(U)):
            raise InputError("uncertainty field", "NaN or inf voxels", "finite uncertainties")
        cache = context.cache(self.relevant)
        gain = context.range_gain(cache.seeds)
        taken = excluded_views(context, cache)
        taken.reshape(-1)[list(also_excluded)] = True
        return lazy_greedy(
            cache, U, budget, context.greedy, context.start_position, gain, excluded=taken
        )

    def select_views(self, context: PlanningContext, budget: int) -> SelectedViews:
        cache = context.cache(self.relevant)
        U = context.policy_field(self)  # one decayed copy per request (10^6 voxels in a room)
        selection = self.selection(context, budget, U)
        if len(selection.views) == 1 and gains_collapsed(context, selection.utilities[0]):
            view, utility = coverage_view(context, cache, U, selection.utilities[0])
            T = aim_at_uncertainty(cache, view, U) if context.aim_views else cache.view_pose(view)
            context.commit(cache, [view], [T])
            note = (
                f"coverage view: the best gain ({selection.utilities[0]:.3g}) is below "
                f"coverage_below={context.greedy.coverage_below} of the first plan's "
                f"({context.first_gain:.3g}); of the views with half of it, the direction least "
                "seen"
            )
            return SelectedViews([T], [utility], note)
        if context.aim_views:
            poses = [aim_at_uncertainty(cache, v, U) for v in selection.views]
            # a view turned to its uncertainty may face where a taken view faced (its bin did
            # not): it is left out and the selection run again, at most AIM_RETRIES times
            repeats: list[int] = []
            for _ in range(AIM_RETRIES):
                again = [
                    v
                    for v, T in zip(selection.views, poses, strict=True)
                    if near_taken(T, context.camera_poses, context.greedy)
                ]
                if not again:
                    break
                repeats += again
                retry = self.selection(context, budget, U, repeats)
                if len(retry.views) < len(selection.views):
                    break  # nothing else left to look at: the repeat stands
                selection = retry
                poses = [aim_at_uncertainty(cache, v, U) for v in selection.views]
        else:
            poses = [cache.view_pose(v) for v in selection.views]
        views = selection.views
        context.commit(cache, views, poses)
        return SelectedViews(poses, [float(u) for u in selection.utilities])


def excluded_views(context: PlanningContext, cache: VisibilityCache) -> np.ndarray:
    """(S, B) bool: the candidate views a selection leaves out: those near a view already taken
    (`taken_views`; all of them allowed again once every one is) and the seeds the newest frames
    block (`context.blocked_seeds`)."""
    centre = context.region_centre() if context.visibility.level == "object" else None
    taken = taken_views(cache, context.camera_poses, context.greedy, centre)
    if taken.all():  # every candidate was taken already: allow them again
        taken[:] = False
    if context.blocked_seeds is not None:
        taken[context.blocked_seeds] = True
    return taken


def gains_collapsed(context: PlanningContext, best: float) -> bool:
    """Whether the best view's gain `best` is below `coverage_below` times the first planned
    view's (`context.first_gain`, set here by the first plan, which it never is); object level
    only, never with `coverage_below` 0."""
    share = context.greedy.coverage_below
    if share <= 0 or context.visibility.level != "object":
        return False
    if context.first_gain is None:
        context.first_gain = float(best)
        return False
    return best < share * context.first_gain


def coverage_view(
    context: PlanningContext, cache: VisibilityCache, U: np.ndarray, best: float
) -> tuple[int, float]:
    """(view, its gain): of the candidate views the selection allows (`excluded_views`) whose
    gain under `U` reaches COVERAGE_KEEP of the best one's (`best`), the one whose direction from
    the region centre is farthest from every captured camera's (the largest least angle; within
    a rounding error of it: the higher gain). The best view itself qualifies, so there always is
    one."""
    scores = cache.score(U).reshape(cache.num_seeds, cache.num_bins)
    gain = context.range_gain(cache.seeds)
    if gain is not None:
        scores = scores * gain[:, None]
    allowed = (scores >= COVERAGE_KEEP * best) & ~excluded_views(context, cache)
    centre = context.region_centre()
    rays = unit_rows(cache.seeds - centre)
    seen = np.asarray(context.camera_positions, np.float64).reshape(-1, 3)
    closest = np.zeros(len(rays))
    # in blocks of captured cameras: a streaming camera fuses thousands of frames
    for start in range(0, len(seen), DIRECTION_BLOCK):
        block = (rays @ unit_rows(seen[start : start + DIRECTION_BLOCK] - centre).T).max(axis=1)
        closest = block if start == 0 else np.maximum(closest, block)
    # the least cosine first (the farthest direction); directions a rounding error apart (mirror
    # images on the shells) are told apart by the gain, not by that error
    key = np.where(allowed, scores - DIRECTION_FIRST * closest[:, None], -np.inf)
    view = int(np.argmax(key))
    return view, float(scores.reshape(-1)[view])


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
    centres = cache.spec.centers_of(ids)
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

    def select_views(self, context: PlanningContext, budget: int) -> SelectedViews:
        n = int(budget)
        if n <= 0:
            return SelectedViews()
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
        valid = context.valid_positions(pts, context.grid.occupancy())
        poses = []
        for p, ok in zip(pts, valid, strict=True):
            if not ok:
                if seeds.size == 0:
                    continue
                p = seeds[int(np.argmin(np.linalg.norm(seeds - p, axis=1)))]
            poses.append(look_at(p, c))
        return SelectedViews.unscored(poses)


class VLMNaivePolicy(GreedyFieldPolicy):
    """Views towards VLM-flagged regions only: field = semantic in the ROI (no geometry, no gamma).

    Falls back to `uniform` while no semantic evidence has been fused.
    """

    name = "vlm_naive"
    map_free = False  # its fallback (uniform) checks camera positions against the map

    def field(self, context: PlanningContext) -> np.ndarray:
        s = context.grid.semantic()
        s[~context.grid.roi_mask] = 0.0
        s[context.grid.occupancy() == FREE] = 0.0
        return s

    def select_views(self, context: PlanningContext, budget: int) -> SelectedViews:
        if not np.any(context.policy_field(self) > 0):
            return UniformPolicy().select_views(context, budget)
        return super().select_views(context, budget)


class RandomPolicy(Policy):
    """Uniformly random candidate views (seed x orientation bin) whose optical axis hits the ROI box
    within max_range, drawn without replacement from a generator seeded with context.rng_seed."""

    name = "random"
    sequential = True

    def select_views(self, context: PlanningContext, budget: int) -> SelectedViews:
        seeds, rotations = context.candidates()
        if seeds.size == 0:
            return SelectedViews()
        g = context.grid
        nb = rotations.shape[1]
        o = np.repeat(seeds, nb, axis=0)
        d = rotations[:, :, :, 2].reshape(-1, 3)
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
            s, b = divmod(int(v), nb)
            T = np.eye(4)
            T[:3, :3] = rotations[s, b]
            T[:3, 3] = seeds[s]
            poses.append(T)
        return SelectedViews.unscored(poses)


POLICIES: dict[str, type[Policy]] = {
    p.name: p
    for p in (Area3DPolicy, VolumetricIGPolicy, VLMNaivePolicy, RandomPolicy, UniformPolicy)
}


def make_policy(name: str) -> Policy:
    """Policy by name: one of POLICIES."""
    if name not in POLICIES:
        raise InputError("policy", name, f"one of {', '.join(sorted(POLICIES))}")
    return POLICIES[name]()
