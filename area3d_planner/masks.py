"""Kernels on visibility masks stored as CSR rows (`indptr`, voxel `ids`, `weights`): scoring views
against a utility field and decaying the field on one view's mask."""

from __future__ import annotations

import numpy as np
from numba import njit, prange


@njit(cache=True, nogil=True, inline="always")
def score_view(indptr, ids, weights, field, view):
    """Mask-weighted utility sum_i w_i U[id_i] of one view (float64, sequential sum): the one sum
    every scoring kernel and the lazy greedy loop use, so their scores are bit-identical."""
    acc = 0.0
    for k in range(indptr[view], indptr[view + 1]):
        acc += weights[k] * field[ids[k]]
    return acc


@njit(cache=True, nogil=True)
def score_views(indptr, ids, weights, field, first, last):
    """`score_view` of views first..last-1."""
    out = np.empty(last - first)
    for v in range(first, last):
        out[v - first] = score_view(indptr, ids, weights, field, v)
    return out


@njit(cache=True, nogil=True)
def score_view_list(indptr, ids, weights, field, views):
    """`score_view` of the views listed (int64 array, any order)."""
    out = np.empty(views.shape[0])
    for q in range(views.shape[0]):
        out[q] = score_view(indptr, ids, weights, field, views[q])
    return out


@njit(cache=True, parallel=True)
def score_all_views(indptr, ids, weights, field):
    """`score_view` of every view, in parallel (bit-identical per view)."""
    n = indptr.shape[0] - 1
    out = np.empty(n)
    for v in prange(n):
        out[v] = score_view(indptr, ids, weights, field, v)
    return out


@njit(cache=True)
def decay_view(indptr, ids, field, view, factor):
    """field[mask(view)] *= factor, in place."""
    for k in range(indptr[view], indptr[view + 1]):
        field[ids[k]] *= factor
