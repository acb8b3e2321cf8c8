"""Voxel ray traversal (Amanatides & Woo 3D DDA) for free-space carving and visibility masks.

All kernels take the grid as (lower (3,) float64 metres, voxel_size metres, shape (3,) int64) and
address voxels by their flat C-order index (x slowest, z fastest), matching
`area3d_perception.grid.GridSpec`.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

_EPS = 1e-9


@njit(cache=True, inline="always")
def _box_interval(o, d, lower, upper, t_end):
    """Parametric interval [t0, t1] of the ray o + t d, t in [0, t_end], inside the box."""
    t0 = 0.0
    t1 = t_end
    for a in range(3):
        if abs(d[a]) < 1e-12:
            if o[a] < lower[a] or o[a] >= upper[a]:
                return 1.0, 0.0
        else:
            ta = (lower[a] - o[a]) / d[a]
            tb = (upper[a] - o[a]) / d[a]
            if ta > tb:
                ta, tb = tb, ta
            t0 = max(t0, ta)
            t1 = min(t1, tb)
    return t0, t1


@njit(cache=True)
def traverse(
    o, d, t_end, lower, voxel_size, shape, occupancy, stop_on_occupied, out_ids, out_texit
):
    """Voxels crossed by the ray o + t d for t in [0, t_end], in order.

    o, d: (3,) float64 origin and unit direction (world). occupancy: flat int8 (-1/0/1), read only
    when stop_on_occupied is True: traversal then ends after the first occupied voxel (first hit).
    Writes flat ids and each voxel's exit parameter t into out_ids / out_texit; returns the count.
    A ray that starts outside the grid box starts at its box entry.
    """
    ny, nz = shape[1], shape[2]
    upper = np.empty(3)
    for a in range(3):
        upper[a] = lower[a] + shape[a] * voxel_size
    t0, t1 = _box_interval(o, d, lower, upper, t_end)
    if t0 >= t1:
        return 0
    idx = np.empty(3, np.int64)
    step = np.empty(3, np.int64)
    t_next = np.empty(3)
    t_delta = np.empty(3)
    ts = t0 + _EPS
    for a in range(3):
        p = o[a] + d[a] * ts
        i = int(np.floor((p - lower[a]) / voxel_size))
        i = min(max(i, 0), shape[a] - 1)
        idx[a] = i
        if d[a] > 1e-12:
            step[a] = 1
            t_next[a] = (lower[a] + (i + 1) * voxel_size - o[a]) / d[a]
            t_delta[a] = voxel_size / d[a]
        elif d[a] < -1e-12:
            step[a] = -1
            t_next[a] = (lower[a] + i * voxel_size - o[a]) / d[a]
            t_delta[a] = -voxel_size / d[a]
        else:
            step[a] = 0
            t_next[a] = np.inf
            t_delta[a] = np.inf
    stride_x = ny * nz
    flat = (idx[0] * ny + idx[1]) * nz + idx[2]
    n = 0
    cap = out_ids.shape[0]
    while n < cap:
        axis = 0
        if t_next[1] < t_next[axis]:
            axis = 1
        if t_next[2] < t_next[axis]:
            axis = 2
        t_exit = min(t_next[axis], t1)
        out_ids[n] = flat
        out_texit[n] = t_exit
        n += 1
        if stop_on_occupied and occupancy[flat] == 1:
            break
        if t_next[axis] >= t1:
            break
        idx[axis] += step[axis]
        if idx[axis] < 0 or idx[axis] >= shape[axis]:
            break
        t_next[axis] += t_delta[axis]
        if axis == 0:
            flat += step[0] * stride_x
        elif axis == 1:
            flat += step[1] * nz
        else:
            flat += step[2]
    return n


@njit(cache=True, inline="always")
def _axis_step(d, o, lower, i, voxel_size):
    """DDA set-up along one axis: (step sign, ray t of the next voxel boundary, t per voxel)."""
    if d > 1e-12:
        return 1, (lower + (i + 1) * voxel_size - o) / d, voxel_size / d
    if d < -1e-12:
        return -1, (lower + i * voxel_size - o) / d, -voxel_size / d
    return 0, np.inf, np.inf


VOXEL_OCCUPIED = np.uint8(1)  # bit flags of the `voxel_flags` array of `visibility_masks`
VOXEL_RELEVANT = np.uint8(2)


@njit(cache=True, nogil=True)
def visibility_masks(
    seeds,
    rotations,
    dirs_cam,
    t_far,
    lower,
    voxel_size,
    shape,
    voxel_flags,
    box_lo,
    box_hi,
    cos_half_diag,
    ray_weight,
    scale_by_range,
    counts,
    touched,
):
    """Monte Carlo visibility of every (seed, orientation) view, as CSR rows.

    seeds: (S, 3) camera centres; rotations: (B, 3, 3) R_world_cam per orientation bin;
    dirs_cam: (R, 3) unit ray directions in the optical frame; t_far: (R,) ray length to the far
    plane; voxel_flags: flat uint8, VOXEL_OCCUPIED | VOXEL_RELEVANT bits: relevant voxels are
    recorded (the others are traversed but left out of the masks); box_lo, box_hi: (3,)
    a box holding every relevant voxel: rays that miss it are not cast, rays that cross it stop
    at its exit, and views whose frustum cone (half-angle acos(cos_half_diag)) misses its
    bounding sphere get an empty mask without casting.
    Rays stop after the first occupied voxel; unknown voxels are traversed (optimistic).
    counts: (N,) float64 zeros, touched: (N,) int32 scratch (returned zeroed, reusable).
    Returns (nnz (S*B,) int64, ids (sum nnz,) int32, weights (sum nnz,) float32).
    A voxel's weight is sum over the rays reaching it of ray_weight[r], times r^2 when
    scale_by_range (r = range of the voxel centre). With ray_weight = the solid angle each ray
    stands for / voxel_size^2 and scale_by_range, the weight is the Monte Carlo estimate of how
    much of the voxel the view sees (a voxel face at range r subtends voxel_size^2 cos / r^2), so a
    view's utility estimates the uncertainty-weighted number of voxels it sees, near or far. With
    ray_weight = 1/R and no scaling, it is the fraction of the view's rays that reach the voxel.
    The traversal is `traverse` (first hit) unrolled on scalars: the same voxels, in the same order.
    """
    nx, ny, nz = shape[0], shape[1], shape[2]
    stride_x = ny * nz
    upper = np.empty(3)
    for a in range(3):
        upper[a] = lower[a] + shape[a] * voxel_size
    n_seeds = seeds.shape[0]
    n_bins = rotations.shape[0]
    n_rays = dirs_cam.shape[0]
    nnz = np.zeros(n_seeds * n_bins, np.int64)
    cap = 1 << 16
    out_ids = np.empty(cap, np.int32)
    out_w = np.empty(cap, np.float32)
    total = 0
    d = np.empty(3)
    centre = 0.5 * (box_lo + box_hi)
    radius = 0.5 * np.sqrt(np.sum((box_hi - box_lo) ** 2))
    half_diag = np.arccos(cos_half_diag)
    for s in range(n_seeds):
        o = seeds[s]
        ox, oy, oz = o[0], o[1], o[2]
        to_c = centre - o
        dist_c = np.sqrt(np.sum(to_c**2))
        for b in range(n_bins):
            rot = rotations[b]
            n_touched = 0
            if dist_c > radius:
                cos_c = (rot[0, 2] * to_c[0] + rot[1, 2] * to_c[1] + rot[2, 2] * to_c[2]) / dist_c
                angle = np.arccos(min(1.0, max(-1.0, cos_c)))
                if angle - np.arcsin(radius / dist_c) > half_diag:
                    nnz[s * n_bins + b] = 0
                    continue
            for r in range(n_rays):
                for a in range(3):
                    d[a] = (
                        rot[a, 0] * dirs_cam[r, 0]
                        + rot[a, 1] * dirs_cam[r, 1]
                        + rot[a, 2] * dirs_cam[r, 2]
                    )
                b0, b1 = _box_interval(o, d, box_lo, box_hi, t_far[r])
                if b0 >= b1:
                    continue
                t0, t1 = _box_interval(o, d, lower, upper, b1)
                if t0 >= t1:
                    continue
                w = ray_weight[r]
                ts = t0 + _EPS
                dx, dy, dz = d[0], d[1], d[2]
                ix = min(max(int(np.floor((ox + dx * ts - lower[0]) / voxel_size)), 0), nx - 1)
                iy = min(max(int(np.floor((oy + dy * ts - lower[1]) / voxel_size)), 0), ny - 1)
                iz = min(max(int(np.floor((oz + dz * ts - lower[2]) / voxel_size)), 0), nz - 1)
                sx, tnx, tdx = _axis_step(dx, ox, lower[0], ix, voxel_size)
                sy, tny, tdy = _axis_step(dy, oy, lower[1], iy, voxel_size)
                sz, tnz, tdz = _axis_step(dz, oz, lower[2], iz, voxel_size)
                flat = (ix * ny + iy) * nz + iz
                while True:
                    f = voxel_flags[flat]
                    if f & VOXEL_RELEVANT:
                        if counts[flat] == 0.0:
                            touched[n_touched] = flat
                            n_touched += 1
                        counts[flat] += w
                    if f & VOXEL_OCCUPIED:
                        break
                    # next axis: the smallest t_next, ties to the lower axis (as `traverse`)
                    if tny < tnx:
                        if tnz < tny:
                            if tnz >= t1:
                                break
                            iz += sz
                            if iz < 0 or iz >= nz:
                                break
                            tnz += tdz
                            flat += sz
                        else:
                            if tny >= t1:
                                break
                            iy += sy
                            if iy < 0 or iy >= ny:
                                break
                            tny += tdy
                            flat += sy * nz
                    elif tnz < tnx:
                        if tnz >= t1:
                            break
                        iz += sz
                        if iz < 0 or iz >= nz:
                            break
                        tnz += tdz
                        flat += sz
                    else:
                        if tnx >= t1:
                            break
                        ix += sx
                        if ix < 0 or ix >= nx:
                            break
                        tnx += tdx
                        flat += sx * stride_x
            if total + n_touched > cap:
                while total + n_touched > cap:
                    cap *= 2
                grown_ids = np.empty(cap, np.int32)
                grown_w = np.empty(cap, np.float32)
                grown_ids[:total] = out_ids[:total]
                grown_w[:total] = out_w[:total]
                out_ids = grown_ids
                out_w = grown_w
            sorted_touched = np.sort(touched[:n_touched])
            for k in range(n_touched):
                v = sorted_touched[k]
                out_ids[total + k] = v
                if scale_by_range:
                    vz = v % nz
                    vy = (v // nz) % ny
                    vx = v // stride_x
                    ex = lower[0] + (vx + 0.5) * voxel_size - ox
                    ey = lower[1] + (vy + 0.5) * voxel_size - oy
                    ez = lower[2] + (vz + 0.5) * voxel_size - oz
                    out_w[total + k] = counts[v] * (ex * ex + ey * ey + ez * ez)
                else:
                    out_w[total + k] = counts[v]
                counts[v] = 0.0
            total += n_touched
            nnz[s * n_bins + b] = n_touched
    return nnz, out_ids[:total].copy(), out_w[:total].copy()


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
