"""Dense visibility of voxels from a camera centre: a cube-map z-buffer of the occupied voxels.

Every candidate camera position gets one panoramic depth buffer (six square faces of `face_res`
pixels) into which the occupied voxels are splatted; a voxel is visible from that position when
its centre is no farther than the nearest occupied voxel in its direction (plus a tolerance of
`tol` metres, so the surface layer itself counts). Every voxel is tested, none is sampled: the
only approximation is the buffer's angular resolution (90 / face_res degrees at a face's centre).

All kernels address voxels by the caller's ids and work on (N, 3) float64 voxel centres.
"""

from __future__ import annotations

import numpy as np
from numba import njit

# Half the angular size of a voxel splatted into the buffer, in voxel edges over range: 0.5 is the
# inscribed sphere, so the splats of neighbouring surface voxels touch without covering each
# other's centres (a surface seen obliquely does not hide itself).
SPLAT_HALF_EXTENT = 0.87
# Cap of a splat's angular half extent, radians (a voxel right at the camera would cover the whole
# face): an angle, not a pixel count, so the same voxels occlude the same directions at any face_res.
MAX_SPLAT_HALF_ANGLE = 0.25


@njit(cache=True, inline="always")
def _cube_coords(dx, dy, dz):
    """(face 0..5, u, v) of a direction: u, v in [-1, 1] on the face of the major axis."""
    ax, ay, az = abs(dx), abs(dy), abs(dz)
    if ax >= ay and ax >= az:
        return (0 if dx > 0 else 1), dy / ax, dz / ax
    if ay >= az:
        return (2 if dy > 0 else 3), dx / ay, dz / ay
    return (4 if dz > 0 else 5), dx / az, dy / az


@njit(cache=True, inline="always")
def _pixel(c, n):
    i = int((c + 1.0) * 0.5 * n)
    return min(max(i, 0), n - 1)


@njit(cache=True, nogil=True)
def _clear(zbuf, dirty):
    """Set the pixels of zbuf inside each face's dirty rectangle (6, 4: i0, i1, j0, j1) to inf
    and mark every face clean; pixels outside the rectangles are inf already."""
    for f in range(6):
        if dirty[f, 0] <= dirty[f, 1]:
            zbuf[f, dirty[f, 0] : dirty[f, 1] + 1, dirty[f, 2] : dirty[f, 3] + 1] = np.inf
        dirty[f, 0] = zbuf.shape[1]
        dirty[f, 1] = -1
        dirty[f, 2] = zbuf.shape[2]
        dirty[f, 3] = -1


@njit(cache=True, inline="always")
def splat_alpha(r, voxel_size):
    """Angular half extent (radians) of the splat of a voxel at range r."""
    return min(SPLAT_HALF_EXTENT * voxel_size / r, MAX_SPLAT_HALF_ANGLE)


@njit(cache=True, inline="always")
def splat_rect(dx, dy, dz, r, alpha, a, n):
    """(face, i0, i1, j0, j1): the pixels of the face of axis a (0..2, on the side of the voxel)
    that the splat of a voxel at offset (dx, dy, dz) from the camera, range r, half angle alpha
    covers, in a buffer of n x n pixels per face; face -1 where it covers none. The one
    definition of a splat's footprint (`fill_zbuffer` and the incremental update use it)."""
    da = dx if a == 0 else (dy if a == 1 else dz)
    db = dy if a == 0 else dx
    dc = dy if a == 2 else dz
    if da == 0.0:
        return -1, 0, -1, 0, -1
    m = abs(da)
    if m < alpha * r:  # this face's axis is (nearly) perpendicular to the voxel
        return -1, 0, -1, 0, -1
    face = 2 * a + (0 if da > 0 else 1)
    half = 0.5 * n
    u = db / m
    v = dc / m
    eu = alpha * (1.0 + u * u) * half
    ev = alpha * (1.0 + v * v) * half
    pu = (u + 1.0) * half
    pv = (v + 1.0) * half
    if pu + eu < 0 or pu - eu >= n or pv + ev < 0 or pv - ev >= n:
        return -1, 0, -1, 0, -1
    # the pixels whose centres (i + 0.5) lie inside the splat; at least the one holding the
    # voxel's own centre. Covering every pixel the splat touches instead would grow each
    # occluder by up to a pixel, hiding more the coarser the buffer.
    i0 = int(np.ceil(pu - eu - 0.5))
    i1 = int(np.floor(pu + eu - 0.5))
    if i1 < i0:
        i0 = i1 = int(np.floor(pu))
    j0 = int(np.ceil(pv - ev - 0.5))
    j1 = int(np.floor(pv + ev - 0.5))
    if j1 < j0:
        j0 = j1 = int(np.floor(pv))
    i0 = max(i0, 0)
    i1 = min(i1, n - 1)
    j0 = max(j0, 0)
    j1 = min(j1, n - 1)
    if i1 < i0 or j1 < j0:
        return -1, 0, -1, 0, -1
    return face, i0, i1, j0, j1


@njit(cache=True, nogil=True)
def fill_zbuffer(origin, occ_centres, voxel_size, max_range, zbuf, dirty):
    """Splat occupied voxel centres (M, 3) into zbuf (6, n, n) float32 as their range from
    `origin` (3,), keeping the nearest per pixel. Voxels beyond max_range are skipped. A splat
    that crosses a face edge is drawn on the neighbouring face too (no gaps at cube edges).
    dirty: (6, 4) int64 rectangles written by the previous fill (all inf before the first one:
    np.full(..., inf) and `_clear` semantics); only they are cleared, which for a small scene
    seen from afar is a small part of the panorama."""
    n = zbuf.shape[1]
    _clear(zbuf, dirty)
    for k in range(occ_centres.shape[0]):
        dx = occ_centres[k, 0] - origin[0]
        dy = occ_centres[k, 1] - origin[1]
        dz = occ_centres[k, 2] - origin[2]
        r = np.sqrt(dx * dx + dy * dy + dz * dz)
        if r < 1e-9 or r > max_range:
            continue
        alpha = splat_alpha(r, voxel_size)
        for a in range(3):
            face, i0, i1, j0, j1 = splat_rect(dx, dy, dz, r, alpha, a, n)
            if face < 0:
                continue
            dirty[face, 0] = min(dirty[face, 0], i0)
            dirty[face, 1] = max(dirty[face, 1], i1)
            dirty[face, 2] = min(dirty[face, 2], j0)
            dirty[face, 3] = max(dirty[face, 3], j1)
            for i in range(i0, i1 + 1):
                for j in range(j0, j1 + 1):
                    if r < zbuf[face, i, j]:
                        zbuf[face, i, j] = np.float32(r)


@njit(cache=True, nogil=True)
def visible_from(origin, centres, zbuf, voxel_size, tol, max_range, out):
    """Indices k of centres (N, 3) visible from origin given its filled zbuf; writes them to
    out (N,) int64 and returns their count. Visible: range <= max_range and no farther than the
    buffer at the pixel of its centre plus tol metres (voxel_size: unused, the footprint is the
    centre pixel)."""
    n = zbuf.shape[1]
    count = 0
    for k in range(centres.shape[0]):
        dx = centres[k, 0] - origin[0]
        dy = centres[k, 1] - origin[1]
        dz = centres[k, 2] - origin[2]
        r = np.sqrt(dx * dx + dy * dy + dz * dz)
        if r < 1e-9 or r > max_range:
            continue
        face, u, v = _cube_coords(dx, dy, dz)
        if r <= zbuf[face, _pixel(u, n), _pixel(v, n)] + tol:
            out[count] = k
            count += 1
    return count


@njit(cache=True, nogil=True, inline="always")
def direction_bin(direction_bins, dx, dy, dz):
    """Index of the row of direction_bins (D, 3) nearest the direction (dx, dy, dz) (the first of
    equals): the bin `observation.direction_bits` gives the same direction."""
    best, bin_of = -2.0, 0
    for d in range(direction_bins.shape[0]):
        dot = direction_bins[d, 0] * dx + direction_bins[d, 1] * dy + direction_bins[d, 2] * dz
        if dot > best:
            best, bin_of = dot, d
    return bin_of


@njit(cache=True, inline="always")
def view_entry(R, dx, dy, dz, normal, near, max_range, tan_x, tan_y, fs2, ppv, range_bin, max_bin):
    """(weight, range bin) of a voxel at offset (dx, dy, dz) from the camera in the view of
    rotation R (3, 3) R_world_cam, weight -1 where it is outside the view (see
    `seed_view_masks`); normal (3,) the voxel's (zero: unknown); fs2 = (focal * voxel_size)^2."""
    z = R[0, 2] * dx + R[1, 2] * dy + R[2, 2] * dz
    if z < near or z > max_range:
        return -1.0, 0
    x = R[0, 0] * dx + R[1, 0] * dy + R[2, 0] * dz
    if abs(x) > tan_x * z:
        return -1.0, 0
    y = R[0, 1] * dx + R[1, 1] * dy + R[2, 1] * dz
    if abs(y) > tan_y * z:
        return -1.0, 0
    cos = 1.0
    nn = normal[0] * normal[0] + normal[1] * normal[1]
    nn += normal[2] * normal[2]
    if nn > 0.0:
        r = np.sqrt(dx * dx + dy * dy + dz * dz)
        cos = -(normal[0] * dx + normal[1] * dy + normal[2] * dz) / r
        if cos <= 0.0:
            return -1.0, 0
    return min(1.0, fs2 * cos / (z * z) / ppv), min(int(z / range_bin), max_bin)


@njit(cache=True, nogil=True)
def seed_view_masks(
    seeds,
    rotations,
    occ_centres,
    centres,
    ids,
    normals,
    voxel_size,
    max_range,
    near,
    tan_x,
    tan_y,
    focal,
    pixels_per_voxel,
    tol,
    zbuf,
    dirty,
    range_bin,
    direction_bins,
    bin_template,
    keep_buffers,
):
    """Visibility masks of every view at every seed, as CSR rows, from geometry alone.

    seeds: (S, 3) camera centres; rotations: (S, B, 3, 3) R_world_cam of each seed's B views;
    occ_centres: (M, 3) occupied voxel centres (the occluders); centres: (N, 3) centres of the
    voxels to record, ids: (N,) int32 their flat ids. A voxel is in view b when it is visible from
    the seed (see `visible_from`) and inside the view's frustum (optical z in [near, max_range],
    |x| <= tan_x z, |y| <= tan_y z). Its weight is the share of a full observation the view's
    resolution allows: min(1, (focal * voxel_size / z)^2 * cos / pixels_per_voxel), i.e. the
    pixels its surface covers over the pixels a voxel needs; cos is the cosine between the
    voxel's normal (N, 3) (unit, towards free space; zero = unknown, cos taken as 1) and the
    direction to the camera, so a surface seen at a grazing angle counts little. Each entry also
    keeps what the evidence weighs it by when views are scored (`masks.score_view`): its range
    bin z // range_bin (capped at the largest value of bin_template's dtype, whose dtype the bins
    take) and the row of direction_bins (D, 3) nearest the direction from the voxel to the seed.
    zbuf: (6, n, n) float32 scratch, all inf, with its dirty (6, 4) int64 rectangles (see
    `fill_zbuffer`; left as the last fill wrote them). Returns (nnz (S*B,) int64, ids int32,
    weights float64, range bins, direction bins uint8, buffers): with keep_buffers, buffers =
    (data float32, rects (S, 6, 4) int64, offsets (S, 6) int64), each seed's z-buffer cropped
    to the rectangles its splats wrote (face f: rows i0..i1, columns j0..j1 of rects[s, f], row
    by row from data[offsets[s, f]]; none where i1 < i0), what an incremental update starts from.
    """
    n_seeds = seeds.shape[0]
    n_views = rotations.shape[1]
    nnz = np.zeros(n_seeds * n_views, np.int64)
    cap = 1 << 16
    out_ids = np.empty(cap, np.int32)
    out_w = np.empty(cap, np.float64)
    out_r = np.empty(cap, bin_template.dtype)
    out_d = np.empty(cap, np.uint8)
    total = 0
    visible = np.empty(centres.shape[0], np.int64)
    to_seed = np.empty(centres.shape[0], np.uint8)
    fs2 = (focal * voxel_size) ** 2
    max_bin = np.iinfo(bin_template.dtype).max
    rects = np.zeros((n_seeds if keep_buffers else 0, 6, 4), np.int64)
    offsets = np.zeros((n_seeds if keep_buffers else 0, 6), np.int64)
    data = np.empty(1 << 16 if keep_buffers else 0, np.float32)
    used = 0
    for s in range(n_seeds):
        o = seeds[s]
        fill_zbuffer(o, occ_centres, voxel_size, max_range, zbuf, dirty)
        if keep_buffers:
            data, used = _keep_crop(zbuf, dirty, data, used, rects[s], offsets[s])
        n_vis = visible_from(o, centres, zbuf, voxel_size, tol, max_range, visible)
        for q in range(n_vis):
            k = visible[q]
            to_seed[q] = direction_bin(
                direction_bins, o[0] - centres[k, 0], o[1] - centres[k, 1], o[2] - centres[k, 2]
            )
        for b in range(n_views):
            R = rotations[s, b]
            if total + n_vis > cap:
                while total + n_vis > cap:
                    cap *= 2
                out_ids = grown(out_ids, total, cap)
                out_w = grown(out_w, total, cap)
                out_r = grown(out_r, total, cap)
                out_d = grown(out_d, total, cap)
            count = 0
            for q in range(n_vis):
                k = visible[q]
                w, rb = view_entry(
                    R,
                    centres[k, 0] - o[0],
                    centres[k, 1] - o[1],
                    centres[k, 2] - o[2],
                    normals[k],
                    near,
                    max_range,
                    tan_x,
                    tan_y,
                    fs2,
                    pixels_per_voxel,
                    range_bin,
                    max_bin,
                )
                if w < 0.0:
                    continue
                out_ids[total + count] = ids[k]
                out_w[total + count] = w
                out_r[total + count] = rb
                out_d[total + count] = to_seed[q]
                count += 1
            nnz[s * n_views + b] = count
            total += count
    return (
        nnz,
        out_ids[:total],
        out_w[:total],
        out_r[:total],
        out_d[:total],
        (data[:used], rects, offsets),
    )


@njit(cache=True, nogil=True)
def _keep_crop(zbuf, dirty, data, used, rect, offset):
    """Append the dirty rectangles of zbuf to data (grown when full); rect (6, 4), offset (6,)
    get where they went. Returns (data, used)."""
    for f in range(6):
        i0, i1, j0, j1 = dirty[f, 0], dirty[f, 1], dirty[f, 2], dirty[f, 3]
        rect[f, 0], rect[f, 1], rect[f, 2], rect[f, 3] = i0, i1, j0, j1
        offset[f] = used
        if i1 < i0 or j1 < j0:
            rect[f, 1] = i0 - 1  # none
            continue
        size = (i1 - i0 + 1) * (j1 - j0 + 1)
        if used + size > data.shape[0]:
            cap = data.shape[0]
            while used + size > cap:
                cap *= 2
            data = grown(data, used, cap)
        q = used
        for i in range(i0, i1 + 1):
            for j in range(j0, j1 + 1):
                data[q] = zbuf[f, i, j]
                q += 1
        used = q
    return data, used


@njit(cache=True, nogil=True)
def grown(a, used, cap):
    """A copy of a[:used] in a new array of cap elements."""
    out = np.empty(cap, a.dtype)
    out[:used] = a[:used]
    return out


@njit(cache=True)
def in_frustum(centres, T, near, max_range, tan_x, tan_y):
    """(N,) bool: voxel centres (N, 3) inside the frustum of the optical-frame pose T (4, 4)."""
    out = np.zeros(centres.shape[0], np.bool_)
    for k in range(centres.shape[0]):
        dx = centres[k, 0] - T[0, 3]
        dy = centres[k, 1] - T[1, 3]
        dz = centres[k, 2] - T[2, 3]
        z = T[0, 2] * dx + T[1, 2] * dy + T[2, 2] * dz
        if z < near or z > max_range:
            continue
        x = T[0, 0] * dx + T[1, 0] * dy + T[2, 0] * dz
        y = T[0, 1] * dx + T[1, 1] * dy + T[2, 1] * dz
        out[k] = abs(x) <= tan_x * z and abs(y) <= tan_y * z
    return out


def new_zbuffer(face_res: int) -> tuple[np.ndarray, np.ndarray]:
    """A clean cube-map z-buffer (6, n, n) float32 of inf and its (6, 4) dirty rectangles (none)."""
    dirty = np.empty((6, 4), np.int64)
    dirty[:, 0::2] = face_res
    dirty[:, 1::2] = -1
    return np.full((6, face_res, face_res), np.inf, np.float32), dirty
