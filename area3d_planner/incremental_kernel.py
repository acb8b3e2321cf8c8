"""The kernel of the incremental visibility update (`incremental.py`, which describes it):
`update_seeds` brings the buffers and masks of the positions that stay candidates up to date
after the map changed. Its helpers and constants: `incremental_geometry.py`.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from area3d_planner.incremental_geometry import (
    ADDED,
    CHANGED,
    GROW,
    STATS,
    TILE,
    UNCHANGED,
    _at,
    _brick_meets,
    _in_window,
    _one_tile_max,
    _pixel_of,
    _push,
)
from area3d_planner.zbuffer import (
    direction_bin,
    grown,
    splat_alpha,
    splat_rect,
    view_entry,
)


@njit(cache=True, nogil=True)
def update_seeds(
    seeds,
    rotations,
    pool,
    zrect,
    zoff,
    theirs,
    cells,
    maxima,
    old_start,
    old_counts,
    old_masks,
    added,
    removed,
    occluders,
    record,
    changed_record,
    removed_record,
    geometry,
    direction_bins,
    bin_template,
    scratch,
    out,
):
    """Update the buffers and masks of positions that stay candidates after the map changed.

    seeds (S, 3), rotations (S, B, 3, 3): the positions and their views; their buffers: in
    pool (float32), crops zrect[s] (6, 4), offsets zoff[s] (6,) into it (see
    `zbuffer.seed_view_masks`), updated in place. Position s was theirs[s] in the cache
    updated, whose arrays by position are: the largest value of each tile, maxima (S', 6, nt,
    nt) float32 (`tile_maxima`, updated in place); the views a direction in each tile may be in,
    cells (S', 6, nt, nt) uint64 (`view_cells`); its masks, old_masks = (ids, weights, range
    bins, direction bins), view b of position t at old_start[t] + sum(old_counts[t, :b]),
    old_counts[t, b] entries.

    Voxel sets come brick by brick (`brick_index`: centres in brick order, ptr, lo, hi, ...):
    added / removed: the occluders that joined / left the map; occluders: those of the map now;
    record = (centres (K, 3), ids (K,) int32 ascending, normals (K, 3), status (K,) uint8
    ADDED / REWEIGHED bits, order, ptr, lo, hi): the voxels recorded now; changed_record =
    (positions in record, ptr, lo, hi): those with a status; removed_record = (centres, ids,
    ptr, lo, hi): those recorded before and not now. geometry = (voxel_size, max_range, near,
    tan_x, tan_y, fs2, pixels_per_voxel, tol, range_bin). scratch (`incremental.new_scratch`):
    left as found. out: (ids, weights, range bins, direction bins) arrays to write the new masks
    into (grown when they are too small).

    Returns (outcome (S,) int8 UNCHANGED / CHANGED / GROW, grow (S, 6, 4) int64 the crops a GROW
    position needs (its buffer untouched: grow it with `grow_buffer`, then run it again), stats
    (STAT_NAMES), counts (S, B) int64 and the entries (ids, weights, range bins, direction bins)
    of the CHANGED positions' new masks, position after position)."""
    voxel_size, max_range, near, tan_x, tan_y, fs2, ppv, tol, range_bin = geometry
    add_c, add_ptr, add_lo, add_hi = added
    rm_c, rm_ptr, rm_lo, rm_hi = removed
    occ_c, occ_ptr, occ_lo, occ_hi = occluders
    rec_c, rec_ids, rec_n, rec_status, rec_order, rec_ptr, rec_lo, rec_hi = record
    chg_q, chg_ptr, chg_lo, chg_hi = changed_record
    gone_c, gone_ids, gone_ptr, gone_lo, gone_hi = removed_record
    old_ids, old_w, old_r, old_d = old_masks
    mark, touched, old_z, reset_lo, reset_hi, changed_lo, changed_hi = scratch[:7]
    tile_before, tile_max, tile_now, no_floor, dirty_flag = scratch[7:]
    out_ids, out_w, out_r, out_d = out
    cap = out_ids.shape[0]
    n = mark.shape[1]
    nt = reset_lo.shape[1]
    n_seeds, n_views = rotations.shape[0], rotations.shape[1]
    max_bin = np.iinfo(bin_template.dtype).max
    outcome = np.zeros(n_seeds, np.int8)
    stats = np.zeros(STATS, np.int64)
    grow = np.zeros((n_seeds, 6, 4), np.int64)
    counts = np.zeros((n_seeds, n_views), np.int64)
    total = 0
    ins_e = np.empty((n_views, 1024), np.int64)  # per view, the dirty voxels it gets ...
    ins_w = np.empty((n_views, 1024), np.float64)  # ... their weights ...
    ins_r = np.empty((n_views, 1024), np.int64)  # ... and range bins
    ins_count = np.zeros(n_views, np.int64)
    d_q = np.empty(16, np.int64)  # dirty voxels: record position (-1: left the record) ...
    d_id = np.empty(16, np.int64)  # ... voxel id ...
    d_vis = np.empty(16, np.bool_)  # ... visible now
    for s in range(n_seeds):
        o = seeds[s]
        data = pool
        rect = zrect[s]
        offset = zoff[s]
        # 0. the crops must hold every pixel a new occluder covers (full faces always do)
        need = False
        full = True
        for f in range(6):
            full = full and rect[f, 0] == 0 and rect[f, 1] == n - 1
            full = full and rect[f, 2] == 0 and rect[f, 3] == n - 1
            for q in range(4):
                grow[s, f, q] = rect[f, q]
        for k in range(0 if full else add_c.shape[0]):
            dx, dy, dz = add_c[k, 0] - o[0], add_c[k, 1] - o[1], add_c[k, 2] - o[2]
            r = np.sqrt(dx * dx + dy * dy + dz * dz)
            if r < 1e-9 or r > max_range:
                continue
            alpha = splat_alpha(r, voxel_size)
            for a in range(3):
                f, i0, i1, j0, j1 = splat_rect(dx, dy, dz, r, alpha, a, n)
                if f < 0:
                    continue
                if rect[f, 1] >= rect[f, 0]:
                    if i0 >= rect[f, 0] and i1 <= rect[f, 1]:
                        if j0 >= rect[f, 2] and j1 <= rect[f, 3]:
                            continue
                need = True
                g = grow[s, f]
                if g[1] < g[0]:
                    g[0], g[1], g[2], g[3] = i0, i1, j0, j1
                else:
                    g[0], g[1] = min(g[0], i0), max(g[1], i1)
                    g[2], g[3] = min(g[2], j0), max(g[3], j1)
        if need:
            outcome[s] = GROW
            continue
        # the farthest value of each tile: a voxel farther than that cannot change it
        tile_before[:] = maxima[theirs[s]]
        tile_max[:] = tile_before
        # A. an occluder that left resets the pixels where it was the nearest
        n_touched = 0
        for bi in range(rm_ptr.shape[0] - 1):
            if not _brick_meets(
                o, rm_lo[bi], rm_hi[bi], True, voxel_size, max_range, no_floor, tile_max, 0.0, n
            ):
                continue
            for k in range(rm_ptr[bi], rm_ptr[bi + 1]):
                dx, dy, dz = rm_c[k, 0] - o[0], rm_c[k, 1] - o[1], rm_c[k, 2] - o[2]
                r = np.sqrt(dx * dx + dy * dy + dz * dz)
                if r < 1e-9 or r > max_range:
                    continue
                rf = np.float32(r)
                alpha = splat_alpha(r, voxel_size)
                for a in range(3):
                    f, i0, i1, j0, j1 = splat_rect(dx, dy, dz, r, alpha, a, n)
                    if f < 0:
                        continue
                    for i in range(i0, i1 + 1):
                        for j in range(j0, j1 + 1):
                            idx = _at(rect, offset, f, i, j)
                            if idx < 0 or data[idx] < rf or mark[f, i, j] >= 0:
                                continue
                            mark[f, i, j] = n_touched
                            touched[n_touched] = (f * n + i) * n + j
                            old_z[n_touched] = data[idx]
                            n_touched += 1
                            data[idx] = np.inf
                            tile_max[f, i // TILE, j // TILE] = np.inf
        n_reset = n_touched  # the pixels touched first are the reset ones
        stats[1] += n_reset
        # C. an occluder that joined is splatted (nearest wins)
        for bi in range(add_ptr.shape[0] - 1):
            if not _brick_meets(
                o, add_lo[bi], add_hi[bi], True, voxel_size, max_range, no_floor, tile_max, 0.0, n
            ):
                continue
            for k in range(add_ptr[bi], add_ptr[bi + 1]):
                dx, dy, dz = add_c[k, 0] - o[0], add_c[k, 1] - o[1], add_c[k, 2] - o[2]
                r = np.sqrt(dx * dx + dy * dy + dz * dz)
                if r < 1e-9 or r > max_range:
                    continue
                alpha = splat_alpha(r, voxel_size)
                for a in range(3):
                    f, i0, i1, j0, j1 = splat_rect(dx, dy, dz, r, alpha, a, n)
                    if f < 0:
                        continue
                    for i in range(i0, i1 + 1):
                        for j in range(j0, j1 + 1):
                            idx = _at(rect, offset, f, i, j)
                            if r < data[idx]:
                                if mark[f, i, j] < 0:
                                    mark[f, i, j] = n_touched
                                    touched[n_touched] = (f * n + i) * n + j
                                    old_z[n_touched] = data[idx]
                                    n_touched += 1
                                data[idx] = np.float32(r)
        # B. a reset pixel gets the nearest occluder (now) that covers it: one that stayed is at
        # least as far as the one that left (that was the nearest), and counts only if nearer
        # than what the new ones gave it, so each tile of reset pixels has a window of ranges
        for t in range(n_reset):
            f, i, j = touched[t] // (n * n), (touched[t] // n) % n, touched[t] % n
            ti, tj = i // TILE, j // TILE
            reset_lo[f, ti, tj] = min(reset_lo[f, ti, tj], old_z[t])
            reset_hi[f, ti, tj] = max(reset_hi[f, ti, tj], data[_at(rect, offset, f, i, j)])
        for bi in range(occ_ptr.shape[0] - 1 if n_reset > 0 else 0):
            if not _brick_meets(
                o, occ_lo[bi], occ_hi[bi], True, voxel_size, max_range, reset_lo, reset_hi, 0.0, n
            ):
                continue
            stats[2] += occ_ptr[bi + 1] - occ_ptr[bi]
            for k in range(occ_ptr[bi], occ_ptr[bi + 1]):
                dx, dy, dz = occ_c[k, 0] - o[0], occ_c[k, 1] - o[1], occ_c[k, 2] - o[2]
                r = np.sqrt(dx * dx + dy * dy + dz * dz)
                if r < 1e-9 or r > max_range:
                    continue
                alpha = splat_alpha(r, voxel_size)
                for a in range(3):
                    f, i0, i1, j0, j1 = splat_rect(dx, dy, dz, r, alpha, a, n)
                    if f < 0 or not _in_window(reset_lo, reset_hi, f, i0, i1, j0, j1, r):
                        continue
                    for i in range(i0, i1 + 1):
                        for j in range(j0, j1 + 1):
                            m = mark[f, i, j]
                            if m < 0 or m >= n_reset:  # not reset: its value stands
                                continue
                            idx = _at(rect, offset, f, i, j)
                            if r < data[idx]:
                                data[idx] = np.float32(r)
        # D. the pixels whose value changed: each tile's window of ranges whose visibility did
        any_changed = False
        for t in range(n_touched):
            f, i, j = touched[t] // (n * n), (touched[t] // n) % n, touched[t] % n
            z_now = data[_at(rect, offset, f, i, j)]
            if z_now != old_z[t]:
                ti, tj = i // TILE, j // TILE
                changed_lo[f, ti, tj] = min(changed_lo[f, ti, tj], min(z_now, old_z[t]))
                changed_hi[f, ti, tj] = max(changed_hi[f, ti, tj], max(z_now, old_z[t]))
                any_changed = True
        for f in range(6):  # the farthest value of each tile before or now
            for ti in range(nt):
                for tj in range(nt):
                    tile_now[f, ti, tj] = max(tile_before[f, ti, tj], changed_hi[f, ti, tj])
        # E. the recorded voxels whose visibility or entries change
        nd = 0
        for bi in range(chg_ptr.shape[0] - 1):  # joined the record, or a new normal
            if not _brick_meets(
                o, chg_lo[bi], chg_hi[bi], False, voxel_size, max_range, no_floor, tile_now, tol, n
            ):
                continue
            for e in range(chg_ptr[bi], chg_ptr[bi + 1]):
                q = chg_q[e]
                c = rec_c[q]
                dx, dy, dz = c[0] - o[0], c[1] - o[1], c[2] - o[2]
                r = np.sqrt(dx * dx + dy * dy + dz * dz)
                if r < 1e-9 or r > max_range:
                    continue
                f, i, j = _pixel_of(o, c, n)
                idx = _at(rect, offset, f, i, j)
                z_now = data[idx] if idx >= 0 else np.inf
                vis = r <= z_now + tol
                if rec_status[q] & ADDED:
                    if not vis:
                        continue
                else:
                    z_before = old_z[mark[f, i, j]] if mark[f, i, j] >= 0 else z_now
                    if not (vis or r <= z_before + tol):
                        continue
                d_q, d_id, d_vis, nd = _push(d_q, d_id, d_vis, nd, q, rec_ids[q], vis)
        for bi in range(rec_ptr.shape[0] - 1 if any_changed else 0):
            # the voxels behind a changed pixel, at a range whose visibility changed
            if not _brick_meets(
                o,
                rec_lo[bi],
                rec_hi[bi],
                False,
                voxel_size,
                max_range,
                changed_lo,
                changed_hi,
                tol,
                n,
            ):
                continue
            stats[3] += rec_ptr[bi + 1] - rec_ptr[bi]
            for e in range(rec_ptr[bi], rec_ptr[bi + 1]):
                q = rec_order[e]
                if rec_status[q] != 0:
                    continue
                c = rec_c[q]
                dx, dy, dz = c[0] - o[0], c[1] - o[1], c[2] - o[2]
                r = np.sqrt(dx * dx + dy * dy + dz * dz)
                if r < 1e-9 or r > max_range:
                    continue
                f, i, j = _pixel_of(o, c, n)
                m = mark[f, i, j]
                if m < 0:
                    continue
                vis = r <= data[_at(rect, offset, f, i, j)] + tol
                if vis != (r <= old_z[m] + tol):
                    d_q, d_id, d_vis, nd = _push(d_q, d_id, d_vis, nd, q, rec_ids[q], vis)
        for bi in range(gone_ptr.shape[0] - 1):  # left the record: out of the masks it was in
            if not _brick_meets(
                o,
                gone_lo[bi],
                gone_hi[bi],
                False,
                voxel_size,
                max_range,
                no_floor,
                tile_before,
                tol,
                n,
            ):
                continue
            for e in range(gone_ptr[bi], gone_ptr[bi + 1]):
                c = gone_c[e]
                dx, dy, dz = c[0] - o[0], c[1] - o[1], c[2] - o[2]
                r = np.sqrt(dx * dx + dy * dy + dz * dz)
                if r < 1e-9 or r > max_range:
                    continue
                f, i, j = _pixel_of(o, c, n)
                if mark[f, i, j] >= 0:
                    z_before = old_z[mark[f, i, j]]
                else:
                    idx = _at(rect, offset, f, i, j)
                    z_before = data[idx] if idx >= 0 else np.inf
                if r <= z_before + tol:
                    d_q, d_id, d_vis, nd = _push(d_q, d_id, d_vis, nd, -1, gone_ids[e], False)
        # the scratch back to clean
        for t in range(n_touched):
            p = touched[t]
            mark[p // (n * n), (p // n) % n, p % n] = -1
        if n_reset > 0:
            reset_lo[:] = np.inf
            reset_hi[:] = -np.inf
        if any_changed:
            for f in range(6):
                for ti in range(nt):
                    for tj in range(nt):
                        if changed_lo[f, ti, tj] <= changed_hi[f, ti, tj]:
                            maxima[theirs[s], f, ti, tj] = _one_tile_max(
                                data, rect, offset, f, ti, tj, n
                            )
            changed_lo[:] = np.inf
            changed_hi[:] = -np.inf
        if nd == 0:
            outcome[s] = UNCHANGED
            continue
        # F. each view's mask: its entries of the dirty voxels out, theirs now in, in voxel order
        outcome[s] = CHANGED
        stats[0] += 1
        stats[4] += nd
        by_id = np.argsort(d_id[:nd])
        dq, did, dvis = d_q[:nd][by_id], d_id[:nd][by_id], d_vis[:nd][by_id]
        if nd > ins_e.shape[1]:
            size = 2 * nd
            ins_e = np.empty((n_views, size), np.int64)
            ins_w = np.empty((n_views, size), np.float64)
            ins_r = np.empty((n_views, size), np.int64)
        ins_count[:] = 0
        to_seed = np.zeros(nd, np.uint8)
        for e in range(nd):
            dirty_flag[did[e]] = 1
            if not dvis[e]:
                continue
            c = rec_c[dq[e]]
            dx, dy, dz = c[0] - o[0], c[1] - o[1], c[2] - o[2]
            to_seed[e] = direction_bin(direction_bins, -dx, -dy, -dz)
            f, i, j = _pixel_of(o, c, n)
            bits = cells[theirs[s], f, i // TILE, j // TILE]
            for b in range(n_views):
                if b < 64 and not (bits >> np.uint64(b)) & np.uint64(1):
                    continue
                w, rb = view_entry(
                    rotations[s, b], dx, dy, dz, rec_n[dq[e]],
                    near, max_range, tan_x, tan_y, fs2, ppv, range_bin, max_bin,
                )  # fmt: skip
                if w >= 0.0:
                    m = ins_count[b]
                    ins_e[b, m], ins_w[b, m], ins_r[b, m] = e, w, rb
                    ins_count[b] = m + 1
        start = old_start[theirs[s]]
        for b in range(n_views):
            n_old, n_in = old_counts[theirs[s], b], ins_count[b]
            if total + n_old + n_in > cap:
                while total + n_old + n_in > cap:
                    cap *= 2
                out_ids = grown(out_ids, total, cap)
                out_w = grown(out_w, total, cap)
                out_r = grown(out_r, total, cap)
                out_d = grown(out_d, total, cap)
            at = total
            m = 0
            for k in range(start, start + n_old):
                voxel = old_ids[k]
                while m < n_in and did[ins_e[b, m]] < voxel:  # the voxels that come first
                    e = ins_e[b, m]
                    out_ids[at], out_w[at], out_r[at], out_d[at] = (
                        did[e],
                        ins_w[b, m],
                        ins_r[b, m],
                        to_seed[e],
                    )
                    at += 1
                    m += 1
                if dirty_flag[voxel]:
                    continue
                out_ids[at], out_w[at], out_r[at], out_d[at] = voxel, old_w[k], old_r[k], old_d[k]
                at += 1
            while m < n_in:
                e = ins_e[b, m]
                out_ids[at], out_w[at], out_r[at], out_d[at] = (
                    did[e],
                    ins_w[b, m],
                    ins_r[b, m],
                    to_seed[e],
                )
                at += 1
                m += 1
            counts[s, b] = at - total
            total = at
            start += n_old
        for e in range(nd):
            dirty_flag[did[e]] = 0
    return (
        outcome,
        grow,
        stats,
        counts,
        out_ids[:total],
        out_w[:total],
        out_r[:total],
        out_d[:total],
    )
