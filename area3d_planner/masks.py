"""Kernels on visibility masks stored as CSR rows (`indptr`, voxel `ids`, `weights`): scoring views
against a utility field and decaying the field on one view's mask."""

from __future__ import annotations

import numpy as np
from numba import njit, prange


@njit(cache=True, nogil=True)
def score_views(indptr, ids, weights, field, first, last):
    """Mask-weighted utility sum_i w_i U[id_i] of views first..last-1 (float64, sequential sums)."""
    out = np.empty(last - first)
    for v in range(first, last):
        acc = 0.0
        for k in range(indptr[v], indptr[v + 1]):
            acc += weights[k] * field[ids[k]]
        out[v - first] = acc
    return out


@njit(cache=True, nogil=True)
def score_view_list(indptr, ids, weights, field, views):
    """Same sums as `score_views` for the views listed (int64 array, any order)."""
    out = np.empty(views.shape[0])
    for q in range(views.shape[0]):
        v = views[q]
        acc = 0.0
        for k in range(indptr[v], indptr[v + 1]):
            acc += weights[k] * field[ids[k]]
        out[q] = acc
    return out


@njit(cache=True, parallel=True)
def score_all_views(indptr, ids, weights, field):
    """Same sums as `score_views` over every view, in parallel (bit-identical per view)."""
    n = indptr.shape[0] - 1
    out = np.empty(n)
    for v in prange(n):
        acc = 0.0
        for k in range(indptr[v], indptr[v + 1]):
            acc += weights[k] * field[ids[k]]
        out[v] = acc
    return out


@njit(cache=True)
def decay_view(indptr, ids, field, view, factor):
    """field[mask(view)] *= factor, in place."""
    for k in range(indptr[view], indptr[view + 1]):
        field[ids[k]] *= factor
