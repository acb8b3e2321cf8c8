"""Budgeted next-best-view selection: plain greedy and lazy greedy (the paper's Algorithm 1).

Objective of a view v under field U:
    utility(v) = gain(seed(v)) * sum_{i in mask(v)} p_i U_i + prior(seed(v)),
prior = -w_dist * ||seed - start|| and gain (a range prior, see `range_gain`) are constants per seed. After each committed view the field is
decayed on the view's mask, U_i <- (1 - eta) U_i, and views near the committed one are suppressed
(light NMS). Decay and suppression only lower utilities, so a seed's last computed best utility
is an upper bound of its current one: lazy greedy re-evaluates only the seeds whose stale bound
reaches the top of the queue and still returns exactly the plain greedy choices.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from area3d_msgs_py.errors import InputError
from area3d_msgs_py.grid import GridSpec
from area3d_planner.candidates import VisibilityParams, orientation_bins
from area3d_planner.lazy import lazy_select
from area3d_planner.masks import decay_view
from area3d_planner.visibility import VisibilityCache

DECAY_REGIONS = ("frustum", "visible")


@dataclass(frozen=True)
class GreedyParams:
    """Tunables of the selection loop."""

    eta: float = 0.3  # paper, supplement Table "frustum-based decay": decay factor 0.3
    w_dist: float = 0.0  # distance prior weight per metre from the start (paper: "with distance prior", value not published)
    nms_radius: float = 0.1  # metres: light NMS, views at seeds this close to a committed one ...
    nms_angle_deg: float = 30.0  # ... and looking within this angle of it are suppressed
    # Object level: a view already taken also rules out the candidates in the same direction from
    # the region centre (within this angle, looking within nms_angle_deg of it) at any range: a
    # shell nearer or farther along the same ray sees nearly the same surface. 0 = off.
    nms_centre_angle_deg: float = 0.0
    # Range prior (paper: "with distance prior", form not published): seeds far nearer or farther
    # from the region than the working distance of the captured views see it at another
    # resolution and noise level; gain = exp(-((d - d0) / (range_sigma * d0))^2 / 2). 0 = off.
    range_sigma: float = 0.0
    # Where a committed view decays the field: "frustum" (the paper: every voxel inside the view's
    # frustum, occluded or not) or "visible" (only its visibility mask).
    decay: str = "frustum"
    # Object level, one view per request: once the best view's gain falls below this share of the
    # first planned view's, the gains no longer tell the views apart (a few voxels each, many of
    # them a depth estimator's false hits): of the views with half the best gain or more, the one
    # farthest in direction from every captured view is taken (`policies.coverage_view`). 0 = off.
    coverage_below: float = 0.0

    def validate(self) -> None:
        if self.decay not in DECAY_REGIONS:
            raise InputError("decay", self.decay, f"one of {', '.join(DECAY_REGIONS)}")
        if not (0.0 <= self.eta <= 1.0):
            raise InputError("eta", self.eta, "a decay factor in [0, 1]")
        if not (np.isfinite(self.w_dist) and self.w_dist >= 0):
            raise InputError("w_dist", self.w_dist, "a finite value >= 0")
        if not (np.isfinite(self.nms_radius) and self.nms_radius >= 0):
            raise InputError("nms_radius", self.nms_radius, "a finite value >= 0 metres")
        if not (np.isfinite(self.range_sigma) and self.range_sigma >= 0):
            raise InputError(
                "range_sigma", self.range_sigma, "a finite value >= 0 (0 = no range prior)"
            )
        if not (0 <= self.nms_angle_deg <= 180):
            raise InputError("nms_angle_deg", self.nms_angle_deg, "a value in [0, 180] degrees")
        if not (0.0 <= self.coverage_below <= 1.0):
            raise InputError("coverage_below", self.coverage_below, "a share in [0, 1]")
        if not (0 <= self.nms_centre_angle_deg <= 180):
            raise InputError(
                "nms_centre_angle_deg", self.nms_centre_angle_deg, "a value in [0, 180] degrees"
            )


@dataclass
class Selection:
    """Result of a greedy run: committed view indices (in order), their utilities at commit time,
    the decayed field, and how many single-view utilities were evaluated."""

    views: list[int] = field(default_factory=list)
    utilities: list[float] = field(default_factory=list)
    field: np.ndarray | None = None
    evaluations: int = 0


def seed_prior(cache: VisibilityCache, start: np.ndarray | None, w_dist: float) -> np.ndarray:
    """(S,) float64 distance prior -w_dist * ||seed - start|| (zeros without a start)."""
    if start is None or w_dist == 0.0:
        return np.zeros(cache.num_seeds)
    return -w_dist * np.linalg.norm(cache.seeds - np.asarray(start, np.float64)[None, :3], axis=1)


def range_gain(
    seeds: np.ndarray, target: np.ndarray, working_distance: float | None, range_sigma: float
) -> np.ndarray | None:
    """(S,) multiplicative range prior of each seed, or None (no prior) when it is switched off or
    there is no working distance yet. target: (3,) region centre; working_distance: metres."""
    if range_sigma <= 0 or working_distance is None or not working_distance > 0:
        return None
    d = np.linalg.norm(np.asarray(seeds, np.float64) - np.asarray(target, np.float64), axis=1)
    return np.exp(-0.5 * ((d - working_distance) / (range_sigma * working_distance)) ** 2)


def decay_committed(
    cache: VisibilityCache,
    U: np.ndarray,
    view: int,
    eta: float,
    region: str = "frustum",
    pose: np.ndarray | None = None,
) -> None:
    """U <- (1 - eta) U, in place, on the frustum of a committed view (the paper) or on its mask.

    pose: the (4, 4) pose the camera really takes (e.g. aimed), default the view's own."""
    if region == "visible":
        decay_view(cache.indptr, cache.voxel_ids, U, view, 1.0 - eta)
        return
    ids = cache.frustum(cache.view_pose(view) if pose is None else pose)
    U[ids] *= 1.0 - eta


def _within_angle(cos_angle: np.ndarray, angle_deg: float) -> np.ndarray:
    """Where two viewing directions, given by the cosine of the angle between them, lie within
    `angle_deg` of each other."""
    return np.degrees(np.arccos(np.clip(cos_angle, -1.0, 1.0))) <= angle_deg + 1e-9


def _facing_alike(cos_angle: np.ndarray, params: GreedyParams) -> np.ndarray:
    """The NMS test of orientation: within nms_angle_deg."""
    return _within_angle(cos_angle, params.nms_angle_deg)


def poses_alike(poses, pose: np.ndarray, radius: float, angle_deg: float) -> np.ndarray:
    """For each (4, 4) camera pose of `poses`: whether it lies within `radius` metres of `pose`
    and looks within `angle_deg` of it (optical z axes)."""
    T = np.asarray(poses, np.float64).reshape(-1, 4, 4)
    pose = np.asarray(pose, np.float64)
    near = np.linalg.norm(T[:, :3, 3] - pose[:3, 3], axis=1) <= radius
    return near & _within_angle(T[:, :3, 2] @ pose[:3, 2], angle_deg)


def _nms_suppress(
    cache: VisibilityCache, excluded: np.ndarray, view: int, params: GreedyParams
) -> None:
    """Mark views (S, B) within nms_radius and nms_angle_deg of `view` as excluded (itself included)."""
    s, b = divmod(view, cache.num_bins)
    near_seeds = np.flatnonzero(
        np.linalg.norm(cache.seeds - cache.seeds[s], axis=1) <= params.nms_radius
    )
    excluded[near_seeds] |= _facing_alike(cache.forward[near_seeds] @ cache.forward[s, b], params)
    excluded[s, b] = True


def near_taken(pose: np.ndarray, poses: list[np.ndarray], params: GreedyParams) -> bool:
    """Whether the (4, 4) `pose` lies within nms_radius and nms_angle_deg of a view already
    captured (`poses`): the test `taken_views` applies to candidates, applied to a pose as it
    will be sent (a committed view turned to its uncertainty, `aim_at_uncertainty`, can face
    where a taken view faced although its orientation bin did not)."""
    if not poses:
        return False
    return bool(np.any(poses_alike(poses, pose, params.nms_radius, params.nms_angle_deg)))


def unit_rows(v: np.ndarray) -> np.ndarray:
    """(N, 3) rows of `v` scaled to unit length (a zero row stays zero)."""
    return v / np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-12)


def taken_views(
    cache: VisibilityCache,
    poses: list[np.ndarray],
    params: GreedyParams,
    centre: np.ndarray | None = None,
) -> np.ndarray:
    """(S, B) bool: candidate views within nms_radius and nms_angle_deg of a view already captured
    ((4, 4) poses). Looking again from where the camera already looked adds little but noise.
    With a region `centre` (3,) and params.nms_centre_angle_deg > 0, also the views whose seed
    lies within that angle of a taken view's direction from the centre, at any range."""
    excluded = np.zeros((cache.num_seeds, cache.num_bins), bool)
    if not poses or cache.num_views == 0:
        return excluded
    T = np.asarray(poses, np.float64).reshape(-1, 4, 4)
    # A camera streaming from one place repeats its pose: each (position, direction) counts once,
    # told apart to 0.1 mm and 1e-4 of the unit direction (far below the NMS radius and angle),
    # so a plan's cost grows with the places the camera has been, not with the frames it sent.
    key = np.round(np.concatenate([T[:, :3, 3], T[:, :3, 2]], axis=1) * 1e4).astype(np.int64)
    rows = np.ascontiguousarray(key).view(np.dtype((np.void, key.itemsize * 6))).ravel()
    _, first = np.unique(rows, return_index=True)  # (a row as one opaque value: 6x faster)
    positions, forwards = T[first, :3, 3], T[first, :3, 2]
    # (seed, pose) pairs within nms_radius, all at once and without Python lists
    pairs = cKDTree(cache.seeds).sparse_distance_matrix(
        cKDTree(positions), params.nms_radius, output_type="ndarray"
    )
    seed_idx, pose_idx = pairs["i"].astype(np.int64), pairs["j"].astype(np.int64)
    if centre is not None and params.nms_centre_angle_deg > 0:
        rays = unit_rows(cache.seeds - np.asarray(centre, np.float64))
        taken = unit_rows(positions - np.asarray(centre, np.float64))
        s_dir, p_dir = np.nonzero(rays @ taken.T >= np.cos(np.radians(params.nms_centre_angle_deg)))
        pairs = np.unique(
            np.stack([np.append(seed_idx, s_dir), np.append(pose_idx, p_dir)]), axis=1
        )
        seed_idx, pose_idx = pairs
    if seed_idx.size:
        cos_angle = np.einsum("pbk,pk->pb", cache.forward[seed_idx], forwards[pose_idx])
        np.logical_or.at(excluded, seed_idx, _facing_alike(cos_angle, params))
    return excluded


def _check(cache: VisibilityCache, U: np.ndarray, budget: int, params: GreedyParams) -> np.ndarray:
    params.validate()
    U = np.array(U, dtype=np.float64)
    if U.shape != (cache.spec.num_voxels,):
        raise InputError("field", U.shape, f"({cache.spec.num_voxels},) flat voxel field")
    # min is NaN if any value is; a sum of values >= 0 is finite iff every value is
    if U.size and not (U.min() >= 0 and np.isfinite(U.sum())):
        raise InputError("field", "non-finite or negative values", "finite uncertainties >= 0")
    if int(budget) < 0:
        raise InputError("budget", budget, "an integer >= 0")
    return U


def _seed_terms(
    cache: VisibilityCache, params: GreedyParams, start: np.ndarray | None, gain: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray]:
    """(gain (S,), prior (S,)): the per-seed factor and offset of the objective, shared by both
    greedy variants so that they optimise exactly the same utility."""
    gain = np.ones(cache.num_seeds) if gain is None else np.asarray(gain, np.float64)
    return gain, seed_prior(cache, start, params.w_dist)


def _excluded(cache: VisibilityCache, excluded: np.ndarray | None) -> np.ndarray:
    """A fresh (S, B) bool of views out of the race (a copy of `excluded`, or none)."""
    if excluded is None:
        return np.zeros((cache.num_seeds, cache.num_bins), bool)
    excluded = np.array(excluded, dtype=bool)
    if excluded.shape != (cache.num_seeds, cache.num_bins):
        raise InputError("excluded", excluded.shape, f"({cache.num_seeds}, {cache.num_bins}) bool")
    return excluded


def plain_greedy(
    cache: VisibilityCache,
    U: np.ndarray,
    budget: int,
    params: GreedyParams | None = None,
    start: np.ndarray | None = None,
    gain: np.ndarray | None = None,
    excluded: np.ndarray | None = None,
) -> Selection:
    """Re-score every unsuppressed view each iteration and commit the best (ties: lowest view index).

    U: (N,) field, copied (the caller's array is not decayed). gain: (S,) range prior per seed
    (None = 1). Returns at most `budget` views.
    """
    params = params or GreedyParams()
    U = _check(cache, U, budget, params)
    gain_s, prior_s = _seed_terms(cache, params, start, gain)
    gain_v, prior = np.repeat(gain_s, cache.num_bins), np.repeat(prior_s, cache.num_bins)
    excluded = _excluded(cache, excluded)
    out = Selection(field=U)
    for _ in range(int(budget)):
        alive = ~excluded.ravel()
        if not alive.any():
            break
        scores = cache.score(U) * gain_v + prior
        out.evaluations += int(alive.sum())
        scores[~alive] = -np.inf
        v = int(np.argmax(scores))
        out.views.append(v)
        out.utilities.append(float(scores[v]))
        decay_committed(cache, U, v, params.eta, params.decay)
        _nms_suppress(cache, excluded, v, params)
    return out


def lazy_greedy(
    cache: VisibilityCache,
    U: np.ndarray,
    budget: int,
    params: GreedyParams | None = None,
    start: np.ndarray | None = None,
    gain: np.ndarray | None = None,
    excluded: np.ndarray | None = None,
) -> Selection:
    """Algorithm 1: a max-priority queue over seeds keyed by an upper bound of their best view.

    Every view keeps an upper bound of its utility (its last score: decay and suppression only
    lower utilities). Pop the top seed and re-score only those of its views whose bound reaches
    the next seed's key (the others cannot win this round); commit its best view if that view's
    score is fresh and still beats the next key (ties: lower seed, then lower bin, as plain
    greedy), otherwise reinsert the seed keyed by its best bound. Same result as `plain_greedy`, with
    far fewer single-view evaluations than re-scoring whole seeds (a frustum decay touches most
    seeds of a room, but only a few of each seed's orientations). The loop runs compiled
    (`lazy.lazy_select`).
    """
    params = params or GreedyParams()
    U = _check(cache, U, budget, params)
    nb = cache.num_bins
    gain, prior = _seed_terms(cache, params, start, gain)
    excluded = _excluded(cache, excluded)
    out = Selection(field=U)
    if cache.num_views == 0 or int(budget) == 0:
        return out
    bound = cache.score(U).reshape(cache.num_seeds, nb) * gain[:, None] + prior[:, None]
    bound[excluded] = -np.inf
    out.evaluations += cache.num_views
    p = cache.params
    views, utilities, evaluations = lazy_select(
        cache.masks,
        cache.evidence.kernel_args(),
        U,
        bound,
        excluded,
        gain,
        prior,
        int(budget),
        cache.seeds,
        np.ascontiguousarray(cache.rotations, np.float64),
        cache.record_centres,
        cache.record_ids,
        p.near,
        p.max_range,
        p.tan_x,
        p.tan_y,
        1.0 - params.eta,
        params.decay == "frustum",
        params.nms_radius,
        params.nms_angle_deg,
    )
    out.views = [int(v) for v in views]
    out.utilities = [float(u) for u in utilities]
    out.evaluations += int(evaluations)
    return out


def warm_up_kernels() -> None:
    """Load the compiled kernels of a visibility build and update, the scoring and the lazy
    greedy loop (from numba's cache: 0.1-0.3 s each the first time in a process) on a tiny
    map, so that the first request does not wait for them."""
    spec = GridSpec.from_bounds(np.zeros(3), np.ones(3), 0.25)
    occupancy = np.zeros(spec.num_voxels, np.int8)
    occupancy[: spec.num_voxels // 2] = 1
    params = VisibilityParams(level="room", face_res=16, yaw_bins=2, pitch_bins=1)
    seeds = np.array([[0.5, 0.5, 0.9]])
    rotations = orientation_bins(params)[1]
    cache = VisibilityCache.build(spec, occupancy, seeds, rotations, params, incremental=True)
    occupancy[:4] = 0
    cache = cache.update(occupancy, seeds, rotations)
    cache.score(np.ones(spec.num_voxels))
    cache.score_views(np.ones(spec.num_voxels), np.arange(cache.num_views))
    lazy_greedy(cache, np.ones(spec.num_voxels), 1)
