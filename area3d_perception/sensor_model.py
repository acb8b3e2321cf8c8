"""The `rgbd` backend: per-pixel confidence and realistic noise of a structured-light / ToF camera.

Axial noise follows Nguyen, Izadi and Lovell, "Modeling Kinect Sensor Noise for Improved 3D
Reconstruction and Tracking" (3DIMPVT 2012):

    sigma_z(z, theta) = a + b (z - z0)^2 + c / sqrt(z) * theta^2 / (pi/2 - theta)^2   [metres]
    sigma_L(theta)    = l0 + l1 * theta / (pi/2 - theta)                              [pixels]

with a = 0.0012, b = 0.0019, z0 = 0.4 m, c = 0.0001, l0 = 0.8 px, l1 = 0.035 px; theta is the angle
between the surface normal and the viewing ray. Confidence is the product of three factors in [0, 1]:

    range:      exp(-(sigma_z(z, 0) / sigma_ref)^2)
    incidence:  max(cos theta, 0)^p
    edges:      ramps from `edge_confidence` on a depth discontinuity to 1 at `edge_radius_px` + 1 px

and 0 where depth is missing.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np
from numba import njit

from area3d_msgs_py.camera import PAPER_MAX_RANGE
from area3d_msgs_py.errors import InputError
from area3d_msgs_py.param_fields import described


@dataclass(frozen=True)
class RgbdSensorParams:
    """Noise and confidence model of a depth camera; defaults are a Kinect-class sensor."""

    # Axial noise sigma_z = a + b (z - z0)^2 (Nguyen et al. 2012, fit for 10-60 deg incidence).
    sigma_a: float = described(
        0.0012, "axial noise sigma_z = a + b (z - z0)^2: a (Nguyen et al. 2012)", "metres",
        (0.0, 1.0),
    )  # fmt: skip
    sigma_b: float = described(
        0.0019, "axial noise: b (Nguyen et al. 2012)", "per metre", (0.0, 1.0)
    )
    sigma_z0: float = described(0.4, "axial noise: z0 (Nguyen et al. 2012)", "metres", (0.0, 100.0))
    # Angular growth of axial noise, c / sqrt(z) * theta^2 / (pi/2 - theta)^2 (Nguyen et al. 2012).
    sigma_angle: float = described(
        0.0001,
        "growth of axial noise with incidence theta, c / sqrt(z) theta^2 / (pi/2 - theta)^2: c "
        "(Nguyen et al. 2012)",
        "metres^1.5",
        (0.0, 1.0),
    )
    # Lateral noise in pixels, l0 + l1 * theta / (pi/2 - theta) (Nguyen et al. 2012).
    lateral_l0_px: float = described(
        0.8, "lateral noise l0 + l1 theta / (pi/2 - theta): l0 (Nguyen et al. 2012)", "pixels",
        (0.0, 100.0),
    )  # fmt: skip
    lateral_l1_px: float = described(
        0.035, "lateral noise: l1 (Nguyen et al. 2012)", "pixels", (0.0, 100.0)
    )
    # Axial sigma at which range confidence falls to 1/e; 2.5 cm is reached near 3.9 m on the curve
    # above, where Kinect-class depth stops being useful for centimetre reconstruction (our choice).
    sigma_ref: float = described(
        0.025, "axial sigma at which the range confidence falls to 1/e", "metres", (1e-6, 10.0)
    )
    # Normals: edge-preserving box mean of this radius, then tangents over this many pixels; at
    # 1 m a Kinect pixel is ~3 mm wide and the axial noise ~2 mm, so 1-pixel tangents would be
    # dominated by noise (our choice; KinectFusion smooths depth before normals for the same reason).
    normal_smoothing_px: int = described(
        1, "radius of the edge-preserving mean before normals", "pixels", (0, 32)
    )
    normal_step_px: int = described(2, "normals: tangents over this many pixels", "pixels", (1, 32))
    # Exponent p of the incidence factor max(cos theta, 0)^p (Lambertian return: p = 1).
    incidence_power: float = described(
        1.0, "exponent p of the incidence confidence max(cos theta, 0)^p (Lambertian: 1)", "",
        (0.0, 10.0),
    )  # fmt: skip
    # A neighbour differing by more than this fraction of the nearer depth is a discontinuity.
    edge_jump_rel: float = described(
        0.05,
        "a neighbour this much farther, as a fraction of the nearer depth, makes a discontinuity",
        "fraction",
        (1e-6, 10.0),
    )
    # Pixels within this many pixels of a discontinuity get reduced confidence (mixed pixels).
    edge_radius_px: int = described(
        2, "pixels this close to a discontinuity get reduced confidence", "pixels", (0, 64)
    )
    # Confidence factor on the discontinuity itself; ramps linearly to 1 outside the radius.
    edge_confidence: float = described(
        0.2, "confidence factor on a discontinuity, ramping to 1 at edge_radius_px", "", (0.0, 1.0)
    )
    # Noise only: probability that a pixel on a discontinuity becomes a dropout (flying pixel).
    edge_dropout: float = described(
        0.5, "noise: probability that a pixel on a discontinuity drops out", "", (0.0, 1.0)
    )
    # Noise only: dropout probability ramps from 0 at this incidence angle ...
    grazing_start_deg: float = described(
        70.0, "noise: dropouts start at this incidence angle", "degrees", (0.0, 90.0)
    )
    # ... to 1 at this one (structured light loses the pattern at grazing angles).
    grazing_full_deg: float = described(
        85.0, "noise: every pixel drops out from this incidence angle", "degrees", (0.0, 90.0)
    )
    # Returns beyond this range are NaN (the paper's camera: max range 5 m).
    max_range: float = described(
        PAPER_MAX_RANGE, "returns beyond this range are no return (the paper's camera: 5)",
        "metres", (0.01, 1000.0),
    )  # fmt: skip

    def __post_init__(self) -> None:
        positive = {
            "sigma_ref": self.sigma_ref,
            "max_range": self.max_range,
            "edge_jump_rel": self.edge_jump_rel,
        }
        for name, value in positive.items():
            if not (np.isfinite(value) and value > 0):
                raise InputError(name, value, "a finite value > 0")
        nonneg = {
            "sigma_a": self.sigma_a,
            "sigma_b": self.sigma_b,
            "sigma_angle": self.sigma_angle,
            "lateral_l0_px": self.lateral_l0_px,
            "lateral_l1_px": self.lateral_l1_px,
            "incidence_power": self.incidence_power,
        }
        for name, value in nonneg.items():
            if not (np.isfinite(value) and value >= 0):
                raise InputError(name, value, "a finite value >= 0")
        for name, value in (
            ("edge_confidence", self.edge_confidence),
            ("edge_dropout", self.edge_dropout),
        ):
            if not (0.0 <= value <= 1.0):
                raise InputError(name, value, "a value in [0, 1]")
        for name, value, low in (
            ("edge_radius_px", self.edge_radius_px, 0),
            ("normal_smoothing_px", self.normal_smoothing_px, 0),
            ("normal_step_px", self.normal_step_px, 1),
        ):
            if int(value) != value or value < low:
                raise InputError(name, value, f"an integer >= {low}")
        if not (0.0 <= self.grazing_start_deg < self.grazing_full_deg <= 90.0):
            raise InputError(
                "grazing_start_deg/grazing_full_deg",
                (self.grazing_start_deg, self.grazing_full_deg),
                "0 <= start < full <= 90 degrees",
            )


# theta^2 / (pi/2 - theta)^2 diverges at 90 deg; such pixels are dropped as grazing anyway.
_MAX_THETA = np.deg2rad(89.0)
_UNIT_K = np.eye(3)


def check_depth_and_intrinsics(depth: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Validate a depth image and intrinsics at the boundary; returns (depth float32, K float64)."""
    depth = np.asarray(depth)
    if depth.ndim != 2 or depth.size == 0 or not np.issubdtype(depth.dtype, np.floating):
        raise InputError(
            "depth",
            f"array {depth.dtype} {depth.shape}",
            "a non-empty (H, W) float array in metres",
        )
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise InputError(
            "K", K.tolist() if K.size <= 9 else K.shape, "finite 3x3 intrinsics with fx, fy > 0"
        )
    return depth.astype(np.float32, copy=False), K


def valid_depth_mask(depth: np.ndarray, max_range: float = np.inf) -> np.ndarray:
    """(H, W) bool: finite, > 0 and within `max_range` metres."""
    with np.errstate(invalid="ignore"):
        return np.isfinite(depth) & (depth > 0) & (depth <= max_range)


@njit(cache=True, inline="always")
def _axial_sigma_at(z, theta, a, b, z0, c, max_theta):  # pragma: no cover - compiled
    t = min(abs(theta), max_theta)
    r = t / (np.pi / 2 - t)
    return a + b * (z - z0) ** 2 + c / np.sqrt(max(z, 1e-6)) * r * r


@njit(cache=True, error_model="numpy")
def _axial_sigma(z, theta, a, b, z0, c, max_theta):  # pragma: no cover - compiled
    out = np.empty(z.shape, dtype=np.float32)
    for n in range(z.size):
        out[n] = _axial_sigma_at(z[n], theta[n], a, b, z0, c, max_theta)
    return out


def axial_sigma(z: np.ndarray, theta: np.ndarray | float, params: RgbdSensorParams) -> np.ndarray:
    """Axial noise standard deviation sigma_z(z, theta) in metres (Nguyen et al. 2012).

    z: depth in metres, theta: incidence angle in radians (an array of z's shape, or a scalar).
    Returns float32 of z's shape.
    """
    z = np.asarray(z, dtype=np.float32)
    if np.isscalar(theta) and theta == 0.0:
        return (params.sigma_a + params.sigma_b * (z - np.float32(params.sigma_z0)) ** 2).astype(
            np.float32
        )
    theta = np.broadcast_to(np.asarray(theta, dtype=np.float32), z.shape)
    sigma = _axial_sigma(
        np.ascontiguousarray(z).reshape(-1),
        np.ascontiguousarray(theta).reshape(-1),
        params.sigma_a,
        params.sigma_b,
        params.sigma_z0,
        params.sigma_angle,
        _MAX_THETA,
    )
    return sigma.reshape(z.shape)


# The kernels below run on one thread: the graph already runs its nodes as processes on a few
# cores, and numba's thread pool on a busy 2-core machine waits on descheduled workers (measured:
# noise + confidence per 640x480 frame 41-44 ms on one thread, 81-106 ms on two, same load).
# They walk the image a row at a time with branch-free inner loops over the columns, which LLVM
# turns into SIMD code; error_model="numpy" lets it (a float division by zero gives inf or NaN,
# never a Python exception, so the division needs no branch). The per-pixel arithmetic is that
# of the straightforward per-pixel loops (test_perception_sensor_model checks them against one).
@njit(cache=True, error_model="numpy")
def _accumulate_same_surface(row, near, total, count, jump_rel, max_range):  # pragma: no cover
    for u in range(row.size):
        d = row[u]
        dn = near[u]
        same = (dn > 0) & (dn <= max_range) & (abs(dn - d) <= jump_rel * d)
        total[u] += dn if same else 0.0
        count[u] += 1.0 if same else 0.0


@njit(cache=True, error_model="numpy")
def _smooth_depth(depth, radius, jump_rel, max_range):  # pragma: no cover - compiled
    """Edge-preserving box mean: each valid pixel averages the valid pixels of its
    (2 radius + 1)^2 window that lie within `jump_rel` of its own depth (same surface), summed in
    row-major window order. NaN where the pixel itself is missing."""
    h, w = depth.shape
    out = np.empty((h, w), dtype=np.float32)
    total = np.empty(w, dtype=np.float64)
    count = np.empty(w, dtype=np.float64)
    for v in range(h):
        row = depth[v]
        total[:] = 0.0
        count[:] = 0.0
        for vv in range(max(v - radius, 0), min(v + radius + 1, h)):
            for du in range(-radius, radius + 1):
                lo = max(-du, 0)
                hi = min(w - du, w)
                _accumulate_same_surface(
                    row[lo:hi],
                    depth[vv, lo + du : hi + du],
                    total[lo:hi],
                    count[lo:hi],
                    jump_rel,
                    max_range,
                )
        for u in range(w):
            d = row[u]
            out[v, u] = total[u] / count[u] if (d > 0) & (d <= max_range) else np.nan
    return out


@njit(cache=True, inline="always")
def _is_jump(d, dn, jump_rel, max_range):  # pragma: no cover - compiled
    """A neighbour depth `dn` that is missing or off the surface of `d` (see `_surface_terms`)."""
    present = (dn > 0) & (dn <= max_range)
    return (not present) | (abs(dn - d) > jump_rel * min(d, dn))


@njit(cache=True, inline="always")
def _pick_tangent(back, fwd, ds):  # pragma: no cover - compiled
    """(forward, any): the tangent of a pixel at smoothed depth `ds` comes from the backward
    neighbour unless the forward one has a strictly smaller depth step; a neighbour that is NaN,
    <= 0 or infinitely far is never picked (a missing or out-of-image one is NaN here)."""
    use_back = (back > 0) & (abs(back - ds) < np.inf)
    best = abs(back - ds) if use_back else np.inf
    use_fwd = (fwd > 0) & (abs(fwd - ds) < best)
    return use_fwd, use_back | use_fwd


@njit(cache=True, error_model="numpy")
def _surface_row(
    d_row,
    d_left,
    d_right,
    d_up,
    d_down,
    s_row,
    s_back,
    s_fwd,
    s_up,
    s_down,
    xs,
    xs_back,
    xs_fwd,
    y,
    y_up,
    y_down,
    jump_rel,
    max_range,
    cos,
    edge,
):  # pragma: no cover - compiled
    """One image row of `_surface_terms`: d_* the depth row and its 4-neighbour rows (an
    out-of-image neighbour is the pixel itself), s_* the smoothed row and its neighbours `step`
    pixels away (NaN out of the image), xs/xs_* and y/y_* their normalised image coordinates."""
    for u in range(d_row.size):
        d = d_row[u]
        valid = (d > 0) & (d <= max_range)
        jump = (
            _is_jump(d, d_left[u], jump_rel, max_range)
            | _is_jump(d, d_right[u], jump_rel, max_range)
            | _is_jump(d, d_up[u], jump_rel, max_range)
            | _is_jump(d, d_down[u], jump_rel, max_range)
        )
        edge[u] = valid & jump
        ds = np.float64(s_row[u])
        x = xs[u]
        back = np.float64(s_back[u])
        fwd = np.float64(s_fwd[u])
        fwd_u, any_u = _pick_tangent(back, fwd, ds)
        dn = fwd if fwd_u else back
        xn = xs_fwd[u] if fwd_u else xs_back[u]
        sign = 1.0 if fwd_u else -1.0
        tux = sign * (xn * dn - x * ds)
        tuy = sign * (y * dn - y * ds)
        tuz = sign * (dn - ds)
        back = np.float64(s_up[u])
        fwd = np.float64(s_down[u])
        fwd_v, any_v = _pick_tangent(back, fwd, ds)
        dn = fwd if fwd_v else back
        yn = y_down if fwd_v else y_up
        sign = 1.0 if fwd_v else -1.0
        tvx = sign * (x * dn - x * ds)
        tvy = sign * (yn * dn - y * ds)
        tvz = sign * (dn - ds)
        nx = tuy * tvz - tuz * tvy
        ny = tuz * tvx - tux * tvz
        nz = tux * tvy - tuy * tvx
        px = x * ds
        py = y * ds
        nn = np.sqrt((nx * nx + ny * ny + nz * nz) * (px * px + py * py + ds * ds))
        c = min(abs(nx * px + ny * py + nz * ds) / nn, 1.0)
        cos[u] = c if valid & any_u & any_v & (nn > 0) else 0.0


@njit(cache=True)
def _surface_terms(depth, smooth, fx, fy, cx, cy, jump_rel, max_range, step):  # pragma: no cover
    """Per pixel |cos| of the incidence angle and a depth-discontinuity flag.

    The normal is the cross product of the two image-axis tangents of the back-projected smoothed
    depth, taken `step` pixels apart; each tangent comes from the forward or backward neighbour,
    whichever has the smaller depth step, so a pixel next to a discontinuity takes its tangent from
    its own surface. A valid pixel whose 4-neighbour is missing or differs by more than `jump_rel`
    x the nearer depth is a discontinuity.
    """
    h, w = depth.shape
    cos = np.empty((h, w), dtype=np.float32)
    edge = np.empty((h, w), dtype=np.bool_)
    xs = np.empty(w + 2 * step)  # columns -step .. w + step - 1
    for i in range(w + 2 * step):
        xs[i] = (i - step + 0.5 - cx) / fx
    depth_padded = np.empty(w + 2, dtype=np.float32)  # the row with its end pixels repeated
    smooth_padded = np.full(w + 2 * step, np.nan, dtype=np.float32)
    missing = np.full(w, np.nan, dtype=np.float32)
    for v in range(h):
        depth_padded[1 : w + 1] = depth[v]
        depth_padded[0] = depth[v, 0]
        depth_padded[w + 1] = depth[v, w - 1]
        smooth_padded[step : step + w] = smooth[v]
        _surface_row(
            depth[v],
            depth_padded[0:w],
            depth_padded[2 : w + 2],
            depth[v - 1] if v > 0 else depth[v],
            depth[v + 1] if v < h - 1 else depth[v],
            smooth[v],
            smooth_padded[0:w],
            smooth_padded[2 * step : 2 * step + w],
            smooth[v - step] if v >= step else missing,
            smooth[v + step] if v + step < h else missing,
            xs[step : step + w],
            xs[0:w],
            xs[2 * step : 2 * step + w],
            (v + 0.5 - cy) / fy,
            (v - step + 0.5 - cy) / fy,
            (v + step + 0.5 - cy) / fy,
            jump_rel,
            max_range,
            cos[v],
            edge[v],
        )
    return cos, edge


def surface_terms(
    depth: np.ndarray,
    K: np.ndarray,
    jump_rel: float,
    max_range: float = np.inf,
    smoothing_px: int = 1,
    normal_step_px: int = 2,
) -> tuple[np.ndarray, np.ndarray]:
    """Incidence cosine and discontinuity mask of a depth image.

    depth: (H, W) float metres (NaN, <= 0 or beyond `max_range` = missing). K: (3, 3).
    Normals are estimated on the depth smoothed by an edge-preserving box mean of radius
    `smoothing_px`, from neighbours `normal_step_px` apart, so sensor noise does not tilt them.
    Returns (cos (H, W) float32 |cos| of the angle between normal and viewing ray, 0 where missing
    or without neighbours; edges (H, W) bool, valid pixels on either side of a depth jump larger
    than `jump_rel` x the nearer depth, or next to a missing pixel).
    """
    depth = np.ascontiguousarray(depth, dtype=np.float32)
    max_range = float(min(max_range, np.finfo(np.float32).max))
    smooth = (
        _smooth_depth(depth, int(smoothing_px), float(jump_rel), max_range)
        if smoothing_px > 0
        else depth
    )
    cos, edge = _surface_terms(
        depth,
        smooth,
        K[0, 0],
        K[1, 1],
        K[0, 2],
        K[1, 2],
        float(jump_rel),
        max_range,
        int(normal_step_px),
    )
    return cos, edge


def incidence_cosine(depth: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(H, W) float32 |cos| of the angle between the surface normal and the viewing ray."""
    return surface_terms(depth, K, RgbdSensorParams.edge_jump_rel)[0]


def discontinuity_mask(depth: np.ndarray, jump_rel: float) -> np.ndarray:
    """(H, W) bool: valid pixels on either side of a depth jump (see `surface_terms`)."""
    return surface_terms(depth, K=_UNIT_K, jump_rel=jump_rel)[1]


# A bounded distance writes each edge pixel's window (`_edge_distance_within`) while that is at
# most this many writes; past it one full OpenCV pass is cheaper (measured on 640x480 frames,
# max_px 3, 29 offsets: 0.4-0.8 ms at the 1% edges of a rendered frame, even with OpenCV's
# 1.4-1.8 ms at 5%, 5 ms against 2 ms at 20%).
_WINDOW_WRITES = 400_000


def _chamfer(edges: np.ndarray) -> np.ndarray:
    return cv2.distanceTransform((~edges).view(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_5)


@lru_cache(maxsize=8)
def _chamfer_window(max_px: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(dy, dx, distance) of every pixel offset whose chamfer distance is at most `max_px`.

    The distances are read off OpenCV's own transform of a single edge pixel, so that a minimum
    over them reproduces its values exactly (a chamfer distance is a shortest path of mask steps,
    and the 5x5 mask's steps never make it shorter than the Chebyshev distance)."""
    n = int(np.floor(max_px))
    c = 2 * n + 2
    single = np.zeros((2 * c + 1, 2 * c + 1), dtype=bool)
    single[c, c] = True
    window = _chamfer(single)[c - n : c + n + 1, c - n : c + n + 1]
    dy, dx = np.nonzero(window <= max_px)
    return dy - n, dx - n, window[dy, dx]


@njit(cache=True)
def _edge_distance_within(edges, dy, dx, values):  # pragma: no cover - compiled
    """min over offsets k of values[k] where edges[v + dy[k], u + dx[k]], inf where none: each
    edge pixel writes its window into the pixels around it, so the cost follows the edges (about
    1% of a frame's pixels), not the image."""
    h, w = edges.shape
    out = np.full((h, w), np.inf, dtype=np.float32)
    for y in range(h):
        for x in range(w):
            if edges[y, x]:
                for k in range(dy.size):
                    v = y - dy[k]
                    u = x - dx[k]
                    if 0 <= v < h and 0 <= u < w and values[k] < out[v, u]:
                        out[v, u] = values[k]
    return out


def edge_distance(edges: np.ndarray, max_px: float = np.inf) -> np.ndarray:
    """(H, W) float32 pixel distance to the nearest True pixel of `edges` (0 on it); inf where no
    True pixel lies within `max_px`.

    The distance is OpenCV's 5x5 chamfer approximation of the Euclidean one (steps 1, 1.4 and
    2.1969 px). A finite `max_px` is what the sensor model needs (its ramps end there): with few
    edges it is computed in a window of that radius around each edge pixel instead of over the
    whole image.
    """
    edges = np.asarray(edges, dtype=bool)
    count = np.count_nonzero(edges)
    if count == 0:
        return np.full(edges.shape, np.inf, dtype=np.float32)
    if np.isfinite(max_px):
        dy, dx, values = _chamfer_window(float(max_px))
        if count * dy.size <= _WINDOW_WRITES:
            return _edge_distance_within(np.ascontiguousarray(edges), dy, dx, values)
    dist = _chamfer(edges)
    if np.isfinite(max_px):
        dist[dist > max_px] = np.inf
    return dist


@njit(cache=True, error_model="numpy")
def _range_exponent(depth, max_range, a, b, z0, sigma_ref):  # pragma: no cover - compiled
    """-(sigma_z(z, 0) / sigma_ref)^2 per pixel in float32 (z = 0 where depth is missing), the
    exponent of the range factor."""
    out = np.empty(depth.shape, dtype=np.float32)
    for v in range(depth.shape[0]):
        for u in range(depth.shape[1]):
            d = depth[v, u]
            z = d if (d > 0) & (d <= max_range) else np.float32(0.0)
            sigma = a + b * ((z - z0) * (z - z0))
            r = sigma / sigma_ref
            out[v, u] = -(r * r)
    return out


@njit(cache=True, error_model="numpy")
def _apply_incidence_and_edges(
    conf, depth, incidence, dist, max_range, ramp_px, edge_conf, edge_rest
):  # pragma: no cover - compiled
    """conf *= incidence factor x edge ramp, in float32 and in place; 0 where depth is missing,
    clipped to [0, 1]."""
    zero = np.float32(0.0)
    one = np.float32(1.0)
    for v in range(conf.shape[0]):
        for u in range(conf.shape[1]):
            d = depth[v, u]
            c = conf[v, u] * incidence[v, u]
            c *= edge_conf + edge_rest * min(max(dist[v, u] / ramp_px, zero), one)
            valid = (d > 0) & (d <= max_range)
            conf[v, u] = min(max(c, zero), one) if valid else zero


@njit(cache=True, error_model="numpy")
def _add_axial_noise(depth, theta, noise, a, b, z0, c, max_theta):  # pragma: no cover - compiled
    """depth += sigma_z(depth, theta) x noise in place (float32; NaN stays NaN)."""
    for n in range(depth.size):
        d = depth[n]
        z = d if np.isfinite(d) else np.float32(1.0)
        sigma = np.float32(_axial_sigma_at(z, theta[n], a, b, z0, c, max_theta))
        depth[n] += sigma * noise[n]


def rgbd_confidence(
    depth: np.ndarray, K: np.ndarray, params: RgbdSensorParams | None = None
) -> np.ndarray:
    """Per-pixel confidence of a depth image under the sensor model.

    depth: (H, W) float metres along optical z; NaN, inf, <= 0 or beyond `max_range` = missing.
    K: (3, 3) intrinsics.
    Returns conf (H, W) float32 in [0, 1], 0 where depth is missing.
    """
    params = params or RgbdSensorParams()
    depth, K = check_depth_and_intrinsics(depth, K)
    cos, edges = surface_terms(
        depth,
        K,
        params.edge_jump_rel,
        params.max_range,
        params.normal_smoothing_px,
        params.normal_step_px,
    )
    f32 = np.float32
    conf = _range_exponent(
        depth,
        params.max_range,
        f32(params.sigma_a),
        f32(params.sigma_b),
        f32(params.sigma_z0),
        f32(params.sigma_ref),
    )
    np.exp(conf, out=conf)
    if params.incidence_power != 1.0:
        cos = cos ** f32(params.incidence_power)
    if params.edge_confidence < 1.0:
        dist = edge_distance(edges, params.edge_radius_px + 1)
    else:  # no edge factor: as if every pixel were far from any edge
        dist = np.full(depth.shape, np.inf, dtype=np.float32)
    _apply_incidence_and_edges(
        conf,
        depth,
        cos,
        dist,
        params.max_range,
        f32(params.edge_radius_px + 1),
        f32(params.edge_confidence),
        f32(1.0 - params.edge_confidence),
    )
    return conf


def add_depth_noise(
    depth: np.ndarray,
    K: np.ndarray,
    rng: np.random.Generator,
    params: RgbdSensorParams | None = None,
) -> np.ndarray:
    """A noisy copy of a perfect depth image, as a Kinect-class sensor would return it.

    Applies, in order: lateral jitter of depth edges (pixels within `edge_radius_px` of a
    discontinuity take the depth of a neighbour displaced by N(0, sigma_L(theta)) pixels per axis),
    axial Gaussian noise N(0, sigma_z(z, theta)), flying-pixel dropout on discontinuities
    (probability `edge_dropout`), dropout at grazing incidence (probability ramping from 0 at
    `grazing_start_deg` to 1 at `grazing_full_deg`), and the range cut at `max_range`.

    depth: (H, W) float metres, NaN = no return. K: (3, 3). rng: numpy Generator (seeded by caller).
    Returns (H, W) float32 metres, NaN = no return.
    """
    params = params or RgbdSensorParams()
    depth, K = check_depth_and_intrinsics(depth, K)
    h, w = depth.shape
    valid = valid_depth_mask(depth)
    clean = np.where(valid, depth, np.float32(np.nan))
    cos, edges = surface_terms(
        clean, K, params.edge_jump_rel, np.inf, params.normal_smoothing_px, params.normal_step_px
    )
    theta = np.arccos(cos)
    dist = edge_distance(edges, params.edge_radius_px)

    # Every draw covers the whole image, whatever the depth holds: the noise of a pixel depends
    # on the generator's state and the pixel only, so two renderings that differ in a few edge
    # pixels (a pose through a quaternion and back) get the same noise everywhere else.
    axial = rng.standard_normal(h * w, dtype=np.float32)
    lateral = rng.standard_normal((2, h * w), dtype=np.float32)
    edge_draw = rng.random(h * w, dtype=np.float32)
    grazing_draw = rng.random(h * w, dtype=np.float32)

    out = clean.copy()
    band = np.flatnonzero(dist.ravel() <= params.edge_radius_px)
    if band.size:
        t = np.minimum(theta.ravel()[band], _MAX_THETA)
        sigma_l = params.lateral_l0_px + params.lateral_l1_px * t / (np.pi / 2 - t)
        shift = np.rint(lateral[:, band] * sigma_l).astype(np.int64)
        rows = np.clip(band // w + shift[0], 0, h - 1)
        cols = np.clip(band % w + shift[1], 0, w - 1)
        out.ravel()[band] = clean[rows, cols]
        theta.ravel()[band] = theta[rows, cols]

    _add_axial_noise(
        out.reshape(-1),
        theta.reshape(-1),
        axial,
        params.sigma_a,
        params.sigma_b,
        params.sigma_z0,
        params.sigma_angle,
        _MAX_THETA,
    )

    drop = np.zeros(h * w, dtype=bool)
    on_edge = np.flatnonzero(edges.ravel())
    if on_edge.size and params.edge_dropout > 0:
        drop[on_edge[edge_draw[on_edge] < params.edge_dropout]] = True
    start, full = np.deg2rad(params.grazing_start_deg), np.deg2rad(params.grazing_full_deg)
    risky = np.flatnonzero(theta.ravel() > start)
    if risky.size:
        p_drop = np.clip((theta.ravel()[risky] - start) / (full - start), 0.0, 1.0)
        drop[risky[grazing_draw[risky] < p_drop]] = True
    out.ravel()[drop] = np.nan
    with np.errstate(invalid="ignore"):
        out[~(out > 0) | (out > params.max_range)] = np.nan
    return out
