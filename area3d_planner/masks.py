"""Kernels on visibility masks stored as CSR rows: scoring views against a utility field and
decaying the field on one view's mask.

A mask set is the tuple `masks = (indptr, ids, weights, range_bins, direction_bins)`: the entries of
view v are k in indptr[v]:indptr[v+1], voxel ids[k] (int32) with its geometric weight weights[k]
(float64, the share of a full observation the view's resolution gives it), the range bin of its
optical depth (`fusion.RANGE_BIN` metres each) and the `observation.DIRECTION_BINS` row of the direction
from the voxel to the camera (uint8). The evidence the fused frames give, `evidence = (directions,
profile, repeat_gain)`, weighs each entry when a view is scored, so the masks depend on the map's
geometry alone: directions (N,) uint32 the bins each voxel was already observed from
(`FusedGrid.directions`; empty: none), profile (R,) float64 the depth backend's confidence by
range relative to its best (`FusedGrid.range_profile`; bins beyond its end take its last value),
repeat_gain the share a voxel seen again from a direction it was observed from counts.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange


@njit(cache=True, nogil=True, inline="always")
def entry_weight(masks, evidence, k):
    """Weight of mask entry k under the evidence: float32(weights[k] * (repeat_gain where the voxel
    was already observed from the entry's direction bin) * profile[range bin]), multiplied in
    float64 in this order and rounded once to float32: bit for bit the weight a mask built with
    the evidence held (the product of the same factors, stored as float32), so views score and
    are aimed exactly as they were then."""
    ids, weights, range_bins, direction_bins = masks[1], masks[2], masks[3], masks[4]
    directions, profile, repeat_gain = evidence
    w = weights[k]
    if directions.shape[0] > 0:
        if (directions[ids[k]] >> np.uint32(direction_bins[k])) & np.uint32(1):
            w *= repeat_gain
    return np.float32(w * profile[min(np.int64(range_bins[k]), profile.shape[0] - 1)])


@njit(cache=True, nogil=True, inline="always")
def score_view(masks, evidence, field, view):
    """Mask-weighted utility sum_k w_k U[id_k] of one view (float64, sequential sum, w_k the
    `entry_weight`): the one sum every scoring kernel and the lazy greedy loop use, so their
    scores are bit-identical."""
    indptr, ids = masks[0], masks[1]
    acc = 0.0
    for k in range(indptr[view], indptr[view + 1]):
        acc += np.float64(entry_weight(masks, evidence, k)) * field[ids[k]]
    return acc


@njit(cache=True, nogil=True)
def score_views(masks, evidence, field, first, last):
    """`score_view` of views first..last-1."""
    out = np.empty(last - first)
    for v in range(first, last):
        out[v - first] = score_view(masks, evidence, field, v)
    return out


@njit(cache=True, nogil=True)
def score_view_list(masks, evidence, field, views):
    """`score_view` of the views listed (int64 array, any order)."""
    out = np.empty(views.shape[0])
    for q in range(views.shape[0]):
        out[q] = score_view(masks, evidence, field, views[q])
    return out


@njit(cache=True, parallel=True)
def score_all_views(masks, evidence, field):
    """`score_view` of every view, in parallel (bit-identical per view)."""
    n = masks[0].shape[0] - 1
    out = np.empty(n)
    for v in prange(n):
        out[v] = score_view(masks, evidence, field, v)
    return out


@njit(cache=True, nogil=True)
def view_weights(masks, evidence, view):
    """(entries,) float32 `entry_weight` of one view's entries."""
    lo, hi = masks[0][view], masks[0][view + 1]
    out = np.empty(hi - lo, np.float32)
    for k in range(lo, hi):
        out[k - lo] = entry_weight(masks, evidence, k)
    return out


@njit(cache=True)
def decay_view(indptr, ids, field, view, factor):
    """field[mask(view)] *= factor, in place."""
    for k in range(indptr[view], indptr[view + 1]):
        field[ids[k]] *= factor
