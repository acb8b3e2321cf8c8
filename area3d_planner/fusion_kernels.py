"""The compiled per-voxel kernels of the fused grid (`fusion.FusedGrid`): the occupancy of the
evidence counters and the fused field, each in one pass. Kept apart from the grid's Python so that
numba's on-disk cache, keyed by this file, is not invalidated by changes to the rest."""

from __future__ import annotations

import numpy as np
from numba import njit

UNKNOWN, FREE, OCCUPIED = -1, 0, 1


@njit(cache=True, nogil=True)
def fused_field(
    g, occ, roi, sem_sum, sem_count, sqrt_rule, weight, removable, best, counts, powers, gamma
):  # pragma: no cover - compiled
    """`FusedGrid.fused` from the geometric uncertainty `g` in one pass, in float32 and in the
    order numpy's passes over whole arrays took (the semantic mean, its product with sqrt(g), the
    weighted sum, max(., 0) keeping a NaN as np.maximum does, the achievability with the power
    looked up by each voxel's count of directions, `counts`, gamma): the same field bit for bit
    (test)."""
    out = np.empty(g.shape[0], np.float32)
    zero = np.float32(0.0)
    one = np.float32(1.0)
    for i in range(g.shape[0]):
        if occ[i] == FREE or not roi[i]:
            out[i] = zero
            continue
        gi = g[i]
        s = sem_sum[i] / sem_count[i] if sem_count[i] > 0 else zero
        if sqrt_rule:
            s = s * np.sqrt(gi)
        x = gi + weight * s
        u = x if (x >= zero or np.isnan(x)) else zero
        if removable:
            c = best[i]
            u = u * (c + (one - c) * powers[counts[i]])
        out[i] = u + gamma
    return out


@njit(cache=True, nogil=True)
def occupancy_states(hit_count, hit_evidence, free_count, hit, miss):  # pragma: no cover - compiled
    """`FusedGrid.occupancy` of the counts (float32): observed where hits + misses > 0, occupied
    where the log-odds evidence * hit + misses * miss (float32, as `log_odds` computes them
    before clamping, which keeps the sign) is > 0."""
    out = np.empty(hit_count.shape[0], np.int8)
    for i in range(hit_count.shape[0]):
        h, f = hit_count[i], free_count[i]
        if h + f > 0:
            out[i] = OCCUPIED if hit_evidence[i] * hit + f * miss > 0 else FREE
        else:
            out[i] = UNKNOWN
    return out
