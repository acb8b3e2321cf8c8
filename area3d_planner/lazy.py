"""The lazy greedy loop (`greedy.lazy_greedy`) compiled: its queue, re-scoring, decay and light NMS
in one numba function, so that the thousands of queue operations a room-level batch needs cost
microseconds each instead of a Python round trip."""

from __future__ import annotations

import numpy as np
from numba import njit

from area3d_planner.masks import score_view
from area3d_planner.zbuffer import in_frustum


@njit(cache=True, inline="always")
def _before(key_a, seed_a, key_b, seed_b):
    """Queue order: the larger key first, ties to the lower seed (plain greedy's view order)."""
    return key_a > key_b or (key_a == key_b and seed_a < seed_b)


@njit(cache=True)
def _push(keys, seeds, size, key, seed):
    i = size
    keys[i] = key
    seeds[i] = seed
    while i > 0:
        parent = (i - 1) // 2
        if not _before(keys[i], seeds[i], keys[parent], seeds[parent]):
            break
        keys[i], keys[parent] = keys[parent], keys[i]
        seeds[i], seeds[parent] = seeds[parent], seeds[i]
        i = parent
    return size + 1


@njit(cache=True)
def _pop(keys, seeds, size):
    """Remove the top; returns (key, seed, new size)."""
    key, seed = keys[0], seeds[0]
    size -= 1
    keys[0], seeds[0] = keys[size], seeds[size]
    i = 0
    while True:
        left, right, top = 2 * i + 1, 2 * i + 2, i
        if left < size and _before(keys[left], seeds[left], keys[top], seeds[top]):
            top = left
        if right < size and _before(keys[right], seeds[right], keys[top], seeds[top]):
            top = right
        if top == i:
            break
        keys[i], keys[top] = keys[top], keys[i]
        seeds[i], seeds[top] = seeds[top], seeds[i]
        i = top
    return key, seed, size


@njit(cache=True)
def lazy_select(
    masks,
    evidence,
    field,
    bound,
    excluded,
    gain,
    prior,
    budget,
    seeds,
    rotations,
    record_centres,
    record_ids,
    near,
    max_range,
    tan_x,
    tan_y,
    keep,
    decay_frustum,
    nms_radius,
    nms_angle_deg,
):
    """Lazy greedy over views s * B + b of the mask set `masks` scored under `evidence` (see
    `masks.py`; fixed during the selection, so scores only fall). field (N,) is decayed in place; bound (S, B) holds each
    view's initial utility (-inf where excluded) and is updated in place; excluded (S, B) bool
    likewise. keep = 1 - eta; decay_frustum: decay every recorded voxel in the committed view's
    frustum (else its mask). Returns (views, utilities, single-view evaluations)."""
    n_seeds, n_bins = bound.shape
    fresh = np.ones((n_seeds, n_bins), np.bool_)
    keys = np.empty(n_seeds + budget + 1)
    heap_seeds = np.empty(n_seeds + budget + 1, np.int64)
    size = 0
    for s in range(n_seeds):
        size = _push(keys, heap_seeds, size, bound[s].max(), s)
    views = np.empty(budget, np.int64)
    utilities = np.empty(budget)
    count = 0
    evaluations = 0
    while size > 0 and count < budget:
        _, s, size = _pop(keys, heap_seeds, size)
        best = -np.inf
        for b in range(n_bins):
            if excluded[s, b]:
                bound[s, b] = -np.inf
            best = max(best, bound[s, b])
        if best == -np.inf:
            continue  # every view of the seed is suppressed
        # re-score the stale views that could still win now: those whose bound reaches the next
        # seed's key (the others lose to that seed either way)
        next_key = keys[0] if size > 0 else -np.inf
        best = -np.inf
        stale_on_top = False
        for b in range(n_bins):
            if not fresh[s, b] and bound[s, b] >= next_key and bound[s, b] > -np.inf:
                bound[s, b] = score_view(masks, evidence, field, s * n_bins + b) * gain[s]
                bound[s, b] += prior[s]
                fresh[s, b] = True
                evaluations += 1
        for b in range(n_bins):
            best = max(best, bound[s, b])
        for b in range(n_bins):
            if bound[s, b] == best and not fresh[s, b]:
                stale_on_top = True
        if stale_on_top or (size > 0 and _before(keys[0], heap_seeds[0], best, s)):
            size = _push(keys, heap_seeds, size, best, s)
            continue
        b_best = 0
        for b in range(n_bins):
            if fresh[s, b] and bound[s, b] == best:
                b_best = b
                break
        v = s * n_bins + b_best
        views[count] = v
        utilities[count] = best
        count += 1
        # decay u <- (1 - eta) u on the committed view's frustum (the paper) or its mask
        if decay_frustum:
            T = np.eye(4)
            T[:3, :3] = rotations[s, b_best]
            T[:3, 3] = seeds[s]
            inside = in_frustum(record_centres, T, near, max_range, tan_x, tan_y)
            for k in range(record_centres.shape[0]):
                if inside[k]:
                    field[record_ids[k]] *= keep
        else:
            indptr, ids = masks[0], masks[1]
            for k in range(indptr[v], indptr[v + 1]):
                field[ids[k]] *= keep
        # light NMS: views at seeds within nms_radius looking within nms_angle_deg of it
        for s2 in range(n_seeds):
            d0 = seeds[s2, 0] - seeds[s, 0]
            d1 = seeds[s2, 1] - seeds[s, 1]
            d2 = seeds[s2, 2] - seeds[s, 2]
            if np.sqrt(d0 * d0 + d1 * d1 + d2 * d2) > nms_radius:
                continue
            for b2 in range(n_bins):
                c = 0.0
                for a in range(3):
                    c += rotations[s2, b2, a, 2] * rotations[s, b_best, a, 2]
                c = min(max(c, -1.0), 1.0)
                if np.degrees(np.arccos(c)) <= nms_angle_deg + 1e-9:
                    excluded[s2, b2] = True
        excluded[s, b_best] = True
        fresh[:, :] = False
        size = _push(keys, heap_seeds, size, best, s)
    return views[:count], utilities[:count], evaluations
