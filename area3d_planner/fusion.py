"""The fused voxel uncertainty grid: geometric + semantic evidence + the global weight gamma.

Per voxel the grid keeps plain evidence counters; the uncertainty fields are derived from them on
demand, so the planner can copy `fused()` and decay the copy while it selects views.
"""

from __future__ import annotations

import functools

import numpy as np
from scipy import ndimage

from area3d_msgs_py.backproject import backproject
from area3d_msgs_py.errors import InputError
from area3d_msgs_py.grid import GridSpec
from area3d_planner.fusion_kernels import FREE, OCCUPIED, UNKNOWN, fused_field, occupancy_states
from area3d_planner.observation import (
    DIRECTION_BINS,
    DepthObservation,
    FrameObserver,
    check_K,
    check_pose,
)

# Log-odds of one occupied / one free observation (OctoMap defaults p_hit = 0.7, p_miss = 0.4).
LOG_ODDS_HIT = float(np.log(0.7 / 0.3))
LOG_ODDS_MISS = float(np.log(0.4 / 0.6))
# Clamping of the accumulated log-odds (OctoMap defaults p_min = 0.12, p_max = 0.97), so a voxel
# can change its mind after many observations.
LOG_ODDS_MIN = float(np.log(0.12 / 0.88))
LOG_ODDS_MAX = float(np.log(0.97 / 0.03))

GEOMETRIC_RULES = ("product", "mean")
# What a hit adds to a voxel's occupancy log-odds: one observation of LOG_ODDS_HIT ("hits", as
# OctoMap), or that times the frame's confidence in the voxel ("confidence": a stereo match at
# 0.04 in the empty air is undone by the next ray through it, one at 0.9 takes three).
OCCUPANCY_RULES = ("hits", "confidence")
# What a view is worth: the uncertainty an observation is predicted to remove ("removable": what
# the voxel holds times how much of it a new direction can still resolve), or the uncertainty the
# voxel holds ("held", the paper's mask-weighted utility).
GAIN_RULES = ("removable", "held")


# The depth backend's confidence by range, tallied in bins of this width (metres) from every hit;
# a bin needs this many hits before it counts (else its nearest counted neighbour's value).
RANGE_BIN = 0.1
RANGE_BIN_MIN_HITS = 50


class FusedGrid:
    """Voxel evidence and the fused uncertainty field U of the paper.

    spec: the voxel grid. roi_lo, roi_hi: (3,) world metres, the region to reconstruct (U = 0
    outside). gamma: global weight added to every voxel that is not known free (paper: 0.01
    object level, 0.005 scene level). unobserved_uncertainty: geometric uncertainty of a voxel
    never observed (DESIGN: unobserved space means high uncertainty). semantic_weight: weight of
    the semantic field in U (0 = the "without VLM" ablation). geometric_rule: "product" (each
    observation lowers the uncertainty, see `geometric`) or "mean" (1 - mean confidence).
    max_confidence: cap of one observation's confidence in the product rule.
    gain_rule: "removable" (a voxel is worth what an observation can still remove, see
    `achievability`) or "held" (what it holds). retry_gain: after each distinct direction a voxel
    was observed from without being pinned down, the share of its remaining uncertainty a new
    direction is expected to resolve is multiplied by this. hard_min_directions /
    hard_max_confidence: a region voxel observed from at least that many directions whose best
    confidence stayed below that is a hard voxel (`hard`): no view is expected to resolve it.
    carve_min_confidence: a depth below this confidence is a hit that carves no free space.
    """

    def __init__(
        self,
        spec: GridSpec,
        roi_lo: np.ndarray,
        roi_hi: np.ndarray,
        gamma: float,
        unobserved_uncertainty: float = 1.0,  # DESIGN.md: unobserved space = high uncertainty
        semantic_weight: float = 1.0,  # equal weight of both fields (paper fuses them unweighted)
        geometric_rule: str = "product",
        max_confidence: float = 0.9,  # one view lowers a voxel's uncertainty at most 10-fold
        gain_rule: str = "removable",
        retry_gain: float = 0.25,  # measured: each failed direction quarters the hope in the next
        hard_min_directions: int = 3,  # our choice: "several distinct directions"
        hard_max_confidence: float = 0.3,  # our choice: the rgbd model's edge confidence is 0.2
        occupancy_rule: str = "hits",
        carve_min_confidence: float = 0.0,
        unobserved_reach: float = 0.0,
        unobserved_far_weight: float = 1.0,
        unobserved_reach_confidence: float = 0.0,
    ) -> None:
        if occupancy_rule not in OCCUPANCY_RULES:
            raise InputError(
                "occupancy_rule", occupancy_rule, f"one of {', '.join(OCCUPANCY_RULES)}"
            )
        if geometric_rule not in GEOMETRIC_RULES:
            raise InputError(
                "geometric_rule", geometric_rule, f"one of {', '.join(GEOMETRIC_RULES)}"
            )
        if not (0.0 < max_confidence < 1.0):
            raise InputError("max_confidence", max_confidence, "a value in (0, 1)")
        if gain_rule not in GAIN_RULES:
            raise InputError("gain_rule", gain_rule, f"one of {', '.join(GAIN_RULES)}")
        if not (0.0 <= retry_gain <= 1.0):
            raise InputError("retry_gain", retry_gain, "a value in [0, 1]")
        if not (1 <= int(hard_min_directions) <= len(DIRECTION_BINS)):
            raise InputError(
                "hard_min_directions",
                hard_min_directions,
                f"an integer in [1, {len(DIRECTION_BINS)}] directions",
            )
        if not (0.0 <= carve_min_confidence <= 1.0):
            raise InputError("carve_min_confidence", carve_min_confidence, "a value in [0, 1]")
        if not (0.0 <= hard_max_confidence <= 1.0):
            raise InputError("hard_max_confidence", hard_max_confidence, "a value in [0, 1]")
        if not (np.isfinite(unobserved_reach) and unobserved_reach >= 0):
            raise InputError("unobserved_reach", unobserved_reach, "a finite value >= 0 metres")
        if not (0.0 <= unobserved_far_weight <= 1.0):
            raise InputError("unobserved_far_weight", unobserved_far_weight, "a value in [0, 1]")
        if not (0.0 <= unobserved_reach_confidence <= 1.0):
            raise InputError(
                "unobserved_reach_confidence", unobserved_reach_confidence, "a value in [0, 1]"
            )
        roi_lo = np.asarray(roi_lo, dtype=np.float64)
        roi_hi = np.asarray(roi_hi, dtype=np.float64)
        if roi_lo.shape != (3,) or roi_hi.shape != (3,) or not np.all(roi_hi > roi_lo):
            raise InputError(
                "roi", [roi_lo.tolist(), roi_hi.tolist()], "roi_min < roi_max on every axis"
            )
        for name, value in (
            ("gamma", gamma),
            ("unobserved_uncertainty", unobserved_uncertainty),
            ("semantic_weight", semantic_weight),
        ):
            if not (np.isfinite(value) and value >= 0):
                raise InputError(name, value, "a finite value >= 0")
        self.spec = spec
        self.roi_lo = roi_lo
        self.roi_hi = roi_hi
        self.gamma = float(gamma)
        self.unobserved_uncertainty = float(unobserved_uncertainty)
        self.semantic_weight = float(semantic_weight)
        self.geometric_rule = geometric_rule
        self.max_confidence = float(max_confidence)
        self.gain_rule = gain_rule
        self.retry_gain = float(retry_gain)
        self.hard_min_directions = int(hard_min_directions)
        self.hard_max_confidence = float(hard_max_confidence)
        self.occupancy_rule = occupancy_rule
        self.carve_min_confidence = float(carve_min_confidence)
        self.unobserved_reach = float(unobserved_reach)
        self.unobserved_far_weight = float(unobserved_far_weight)
        self.unobserved_reach_confidence = float(unobserved_reach_confidence)
        n = spec.num_voxels
        self.conf_sum = np.zeros(n, np.float32)
        self.hit_count = np.zeros(n, np.float32)
        self.log_residual = np.zeros(n, np.float32)  # sum over hits of log(1 - confidence)
        self.free_count = np.zeros(n, np.float32)
        self.sem_sum = np.zeros(n, np.float32)
        self.sem_count = np.zeros(n, np.float32)
        self.best_confidence = np.zeros(n, np.float32)  # best frame confidence of each voxel
        self.directions = np.zeros(n, np.uint32)  # DIRECTION_BINS it was observed from (bits)
        # confidence of every hit, summed per RANGE_BIN of its optical depth, and the hit counts
        self.range_confidence = np.zeros(int(np.ceil(100.0 / RANGE_BIN)), np.float64)
        self.range_hits = np.zeros_like(self.range_confidence)
        centers = spec.centers()
        self.roi_mask = np.all((centers >= roi_lo) & (centers <= roi_hi), axis=1)
        self.roi_ids = np.flatnonzero(self.roi_mask)
        self.roi_centres = np.ascontiguousarray(centers[self.roi_ids])
        self.frames = 0
        self.semantic_frames = 0
        # what a frame tells the grid, from its layout alone (scratch tallies allocated once)
        self._observer = FrameObserver(
            self.spec,
            self.roi_ids,
            self.roi_centres,
            self.max_confidence,
            self.carve_min_confidence,
        )

    @functools.cached_property
    def over_region(self) -> np.ndarray:
        """(N,) bool: the column over the region, above its top and within its footprint (made
        on first use: only object-level planning reads it)."""
        centers = self.spec.centers()
        inside = np.all(
            (centers[:, :2] >= self.roi_lo[:2]) & (centers[:, :2] <= self.roi_hi[:2]), axis=1
        )
        return inside & (centers[:, 2] > self.roi_hi[2])

    # ------------------------------------------------------------------ integration
    def integrate_depth(
        self,
        depth: np.ndarray,
        conf: np.ndarray,
        K: np.ndarray,
        T_world_cam: np.ndarray,
        max_range: float = 5.0,  # paper, supplement: max depth 5 m
        stride: int = 2,  # carve every 2nd pixel row/column; surface hits use every pixel
    ) -> None:
        """Fuse one frame: `apply_depth(observe_depth(...))` (see `observe_depth`)."""
        self.apply_depth(self.observe_depth(depth, conf, K, T_world_cam, max_range, stride))

    def observe_depth(
        self,
        depth: np.ndarray,
        conf: np.ndarray,
        K: np.ndarray,
        T_world_cam: np.ndarray,
        max_range: float = 5.0,  # paper, supplement: max depth 5 m
        stride: int = 2,  # carve every 2nd pixel row/column; surface hits use every pixel
    ) -> DepthObservation:
        """What one frame tells the grid: surface evidence of hit voxels, free space along every
        ray. Reads only the grid's layout, never its evidence, so it runs while the grid is in
        use elsewhere (a plan); `apply_depth` then adds it in a few milliseconds.

        depth: (H, W) float32 metres along optical z (REP 117): +Inf = no return within range,
        NaN = no estimate. conf: (H, W) float32 in [0, 1] (NaN = no confidence, pixel skipped).
        Each voxel counts at most one hit and one free observation per frame (hits win); its
        confidence sample is the frame's mean over the pixels that land in it. A +Inf pixel
        carves free space out to max_range; a NaN pixel carves nothing: a dropout of a depth
        camera, a failed stereo match or a feed-forward model's gap says nothing of the space
        behind it (which of a depth camera's missing pixels are +Inf: perception's `no_return`).
        Nor does a finite depth at confidence 0 (a stereo match the left-right check refused),
        or below `carve_min_confidence`: it counts as a hit at its confidence and carves nothing.
        """
        return self._observer.observe(depth, conf, K, T_world_cam, max_range, stride)

    def apply_depth(self, observation: DepthObservation) -> None:
        """Add one frame's observation (from `observe_depth` on this grid) to the evidence."""
        hit = observation.hit
        self.conf_sum[hit] += observation.confidence
        self.log_residual[hit] += observation.log_residual
        self.hit_count[hit] += 1.0
        self.free_count[observation.free] += 1.0
        self.best_confidence[hit] = np.maximum(self.best_confidence[hit], observation.confidence)
        if observation.hit_bits is not None:
            self.directions[hit] |= observation.hit_bits
        if observation.hit_range is not None:
            bins = np.minimum(
                (np.maximum(observation.hit_range, 0.0) / RANGE_BIN).astype(np.int64),
                self.range_hits.size - 1,
            )
            n = self.range_hits.size
            self.range_confidence += np.bincount(bins, observation.confidence, minlength=n)
            self.range_hits += np.bincount(bins, minlength=n)
        if observation.missed is not None:
            self.directions[observation.missed] |= observation.missed_bits
        self.frames += 1

    def integrate_semantic(
        self, u_sem: np.ndarray, depth: np.ndarray, K: np.ndarray, T_world_cam: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Splat a per-pixel semantic uncertainty map U_sem (H, W) float32 in [0, 1] as a per-voxel mean.

        depth: (H, W) metres of the same frame (NaN = no return; those pixels carry nothing).
        Returns the contribution (voxel ids, values) so that `retract_semantic` can take it back.
        """
        u_sem = np.asarray(u_sem)
        depth = np.asarray(depth)
        if u_sem.ndim != 2 or u_sem.shape != depth.shape:
            raise InputError(
                "semantic_uncertainty", u_sem.shape, f"the depth image shape {depth.shape}"
            )
        K = check_K(K)
        T = check_pose(T_world_cam, "T_world_cam")
        n = self.spec.num_voxels
        points, pixel = backproject(depth.astype(np.float32, copy=False), K, T)
        u = u_sem.reshape(-1)[pixel].astype(np.float64)
        vox, inside = self.spec.flat_index(points)
        keep = inside & np.isfinite(u)
        vox, u = vox[keep], np.clip(u[keep], 0.0, 1.0)
        pix_count = np.bincount(vox, minlength=n)
        hit = np.flatnonzero(pix_count > 0)
        values = (np.bincount(vox, weights=u, minlength=n)[hit] / pix_count[hit]).astype(np.float32)
        self.sem_sum[hit] += values
        self.sem_count[hit] += 1.0
        self.semantic_frames += 1
        return hit, values

    def retract_semantic(self, ids: np.ndarray, values: np.ndarray) -> None:
        """Take back one `integrate_semantic` contribution (a map replaced by a newer analysis)."""
        self.sem_sum[ids] -= values
        self.sem_count[ids] -= 1.0
        np.maximum(self.sem_sum, 0.0, out=self.sem_sum)
        self.semantic_frames -= 1

    # ------------------------------------------------------------------ fields
    def _hit_evidence(self) -> np.ndarray:
        """(N,) float32 the hits as the occupancy counts them (`occupancy_rule`): their number,
        or the sum of their confidences."""
        return self.conf_sum if self.occupancy_rule == "confidence" else self.hit_count

    def log_odds(self) -> np.ndarray:
        """(N,) float32 clamped occupancy log-odds (0 for never observed voxels)."""
        lo = self._hit_evidence() * np.float32(LOG_ODDS_HIT) + self.free_count * np.float32(
            LOG_ODDS_MISS
        )
        return np.clip(lo, LOG_ODDS_MIN, LOG_ODDS_MAX).astype(np.float32)

    def occupancy(self) -> np.ndarray:
        """(N,) int8: -1 unknown (never observed), 0 free, 1 occupied (log-odds > 0), in one
        compiled pass (`fusion_kernels.occupancy_states`; each request reads it, a room's grid
        has ~10^6 voxels)."""
        return occupancy_states(
            self.hit_count,
            self._hit_evidence(),
            self.free_count,
            np.float32(LOG_ODDS_HIT),
            np.float32(LOG_ODDS_MISS),
        )

    def occupancy_probability(self) -> np.ndarray:
        """(N,) float32 p(occupied) = sigmoid(log-odds); 0.5 where never observed."""
        return (1.0 / (1.0 + np.exp(-self.log_odds()))).astype(np.float32)

    def geometric(self, occ: np.ndarray | None = None) -> np.ndarray:
        """(N,) float32 geometric uncertainty of occupied voxels, `unobserved_uncertainty` on
        unknown voxels, 0 on known free voxels.

        "product" rule: G = prod_k (1 - min(c_k, max_confidence)) over the frames k that hit the
        voxel with mean confidence c_k: the chance that no observation so far pinned the surface
        down. One view gives the paper's 1 - C; every further view lowers G, by a lot when it is
        confident and a little when it is not, so a surface never stays attractive forever.
        "mean" rule: G = 1 - mean_k c_k (does not fall with repeated views).

        An unknown voxel farther than `unobserved_reach` (Chebyshev, whole voxels) from every
        occupied voxel holds `unobserved_far_weight` times `unobserved_uncertainty`: it is most
        likely air (the upper part of a region box drawn around one tall object), and the views
        that would carve it see little surface.
        """
        occ = self.occupancy() if occ is None else occ
        g = np.full(self.spec.num_voxels, self.unobserved_uncertainty, np.float32)
        if self.unobserved_far_weight < 1.0:
            g[(occ == UNKNOWN) & ~self.near_surface(occ)] *= np.float32(self.unobserved_far_weight)
        g[occ == FREE] = 0.0
        surf = occ == OCCUPIED
        if self.geometric_rule == "product":
            g[surf] = np.exp(self.log_residual[surf])
        else:
            g[surf] = 1.0 - self.conf_sum[surf] / self.hit_count[surf]
        return g

    def near_surface(self, occ: np.ndarray | None = None) -> np.ndarray:
        """(N,) bool: voxels within `unobserved_reach` (whole voxels on every axis) of an occupied
        voxel (a separable maximum filter: tens of milliseconds at the 4 M-voxel cap) that two
        frames hit, or one at `unobserved_reach_confidence` or more: a surface where it is seen
        again is one, while a lone uncertain match in the air (stereo's, on a periodic texture
        matched at the wrong disparity, lands elsewhere from every view) would draw views to the
        empty space around it."""
        occ = self.occupancy() if occ is None else occ
        surface = occ == OCCUPIED
        if self.unobserved_reach_confidence > 0.0:
            surface &= (self.hit_count >= 2.0) | (
                self.best_confidence >= np.float32(self.unobserved_reach_confidence)
            )
        return self._within(surface, int(round(self.unobserved_reach / self.spec.voxel_size)))

    def near_free(self, occ: np.ndarray, layers: int) -> np.ndarray:
        """(N,) bool: voxels within `layers` whole voxels (on every axis) of a known-free one,
        the free ones included."""
        return self._within(occ == FREE, int(layers))

    def _within(self, mask: np.ndarray, layers: int) -> np.ndarray:
        """(N,) bool: voxels within `layers` whole voxels on every axis of one in `mask` (N,)."""
        if layers == 0:
            return np.asarray(mask, bool).copy()
        grid = mask.reshape(self.spec.shape).view(np.uint8)
        near = ndimage.maximum_filter(grid, size=2 * layers + 1, mode="constant")
        return near.reshape(-1).astype(bool)

    def boundary(self, occ: np.ndarray | None = None) -> np.ndarray:
        """(N,) bool: voxels that are not known free but have a known-free face neighbour: the
        surface of everything the camera has not carved away (occupied or unknown)."""
        occ = (self.occupancy() if occ is None else occ).reshape(self.spec.shape)
        free = occ == FREE
        near = np.zeros_like(free)
        for axis in range(3):
            a = [slice(None)] * 3
            b = [slice(None)] * 3
            a[axis], b[axis] = slice(1, None), slice(None, -1)
            near[tuple(a)] |= free[tuple(b)]
            near[tuple(b)] |= free[tuple(a)]
        return ((occ != FREE) & near).reshape(-1)

    def semantic(self) -> np.ndarray:
        """(N,) float32 mean splatted U_sem per voxel (0 where no semantic frame landed)."""
        s = np.zeros(self.spec.num_voxels, np.float32)
        seen = self.sem_count > 0
        s[seen] = self.sem_sum[seen] / self.sem_count[seen]
        return s

    def direction_count(self) -> np.ndarray:
        """(N,) uint8: how many distinct directions (`DIRECTION_BINS`) each voxel was observed
        from, with a return (a hit) or without one (in view, no depth at its pixel)."""
        return np.bitwise_count(self.directions).astype(np.uint8)

    def achievability(self) -> np.ndarray:
        """(N,) float32 in [0, 1]: the share of a voxel's uncertainty a view from a new direction
        is expected to resolve, from what the depth backend achieved on it so far:

            a = c* + (1 - c*) retry_gain^n

        c* the best confidence any frame reached on the voxel (0 if none hit it), n the distinct
        directions it was observed from. Never observed: 1. Seen once with confidence 0.2 (a
        depth edge, a blank surface for stereo): 0.6, as another direction may do better; after
        three directions that all stayed at 0.2: 0.3, and no view is expected to do better than
        the best so far. A voxel in view three times without any return (glossy, dark, blank):
        0.125.
        """
        c = self.best_confidence
        return (c + (1.0 - c) * self._retry_powers()[self.direction_count()]).astype(np.float32)

    def _retry_powers(self) -> np.ndarray:
        """(33,) float32 retry_gain ** n for every count of directions n (0-32), raised by
        numpy's float32 power as a whole array of counts would be, so a lookup gives the same
        values (the power of 10^6 voxels took 8 ms of a room's request)."""
        return np.float32(self.retry_gain) ** np.arange(33, dtype=np.float32)

    def view_evidence(self) -> tuple[np.ndarray, tuple[np.ndarray, float]]:
        """What the visibility masks weigh views by, copied (a rebuild runs while fusion goes on):
        (the `directions` each voxel was observed from, the `range_profile`)."""
        return self.directions.copy(), self.range_profile()

    def range_profile(self) -> tuple[np.ndarray, float]:
        """(profile (R,) float64, RANGE_BIN): the mean confidence of the hits in each range bin,
        relative to the best bin, from every frame fused so far; a bin with fewer than
        RANGE_BIN_MIN_HITS hits takes the value of the nearest bin with enough (all ones before
        any). What a view's range lets the depth backend achieve: with stereo, confidence falls
        with the distance; with a depth camera it hardly changes within a few metres."""
        counted = np.flatnonzero(self.range_hits >= RANGE_BIN_MIN_HITS)
        if counted.size == 0:
            return np.ones(self.range_hits.size), RANGE_BIN
        mean = self.range_confidence[counted] / self.range_hits[counted]
        best = float(mean.max())
        if not best > 0:
            return np.ones(self.range_hits.size), RANGE_BIN
        profile = np.interp(np.arange(self.range_hits.size), counted, mean / best)
        return profile, RANGE_BIN

    def hard(self, occ: np.ndarray | None = None) -> np.ndarray:
        """(N,) bool: region voxels that are not known free, were observed from at least
        `hard_min_directions` distinct directions and never reached `hard_max_confidence`: what
        the camera cannot resolve (reported, not chased)."""
        occ = self.occupancy() if occ is None else occ
        return (
            self.roi_mask
            & (occ != FREE)
            & (self.direction_count() >= self.hard_min_directions)
            & (self.best_confidence < self.hard_max_confidence)
        )

    def fused(self, occ: np.ndarray | None = None, geo: np.ndarray | None = None) -> np.ndarray:
        """(N,) float32 utility field on every voxel that is not known free (0 on known free
        voxels and outside the ROI), from the `occupancy` and `geometric` field given (made here
        when None: a caller that needs them too passes its own):

            held:       U = max(0, G + semantic_weight * S * sqrt(G)) + gamma
            removable:  U = a * max(0, G + semantic_weight * S * sqrt(G)) + gamma

        with a the voxel's `achievability`: a view is worth the uncertainty it is predicted to
        remove, not the uncertainty the voxel holds (the mask weights add the view's own share:
        resolution, and incidence where enabled). gamma, the paper's global weight, stays on
        every voxel as it is.

        The semantic term falls with the observations too, at half the rate of G on a log scale:
        a region the VLM flags as hard stays attractive for about twice as many views as one it
        does not flag (with the "mean" rule the semantic term is the plain mean, as before).
        """
        occ = self.occupancy() if occ is None else occ
        return fused_field(
            self.geometric(occ) if geo is None else geo,
            occ,
            self.roi_mask,
            self.sem_sum,
            self.sem_count,
            self.geometric_rule == "product",
            np.float32(self.semantic_weight),
            self.gain_rule == "removable",
            self.best_confidence,
            self.direction_count(),
            self._retry_powers(),
            np.float32(self.gamma),
        )

    def entropy(self) -> np.ndarray:
        """(N,) float32 binary entropy (bits) of the occupancy probability, 0 outside the ROI
        (classic volumetric information gain, the `volumetric_ig` baseline)."""
        p = np.clip(self.occupancy_probability().astype(np.float64), 1e-9, 1 - 1e-9)
        h = -(p * np.log2(p) + (1 - p) * np.log2(1 - p))
        h[~self.roi_mask] = 0.0
        return h.astype(np.float32)
