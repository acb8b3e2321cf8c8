"""What one depth frame tells a voxel grid, from the grid's layout alone (never its evidence):
the voxels its pixels hit, with the frame's confidence in each, the voxels its rays cross as
free, and the region voxels it looked at without a return (`FrameObserver.observe`), with the
direction each was seen from (`direction_bits`: one of `DIRECTION_BINS`). `fusion.FusedGrid`
adds an observation to its evidence.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np
from numba import njit

from area3d_msgs_py.backproject import pixel_to_world
from area3d_msgs_py.carving import carve_depth_frame
from area3d_msgs_py.errors import InputError
from area3d_msgs_py.grid import GridSpec

# A voxel whose pixel has no return is hidden when the nearest returns on both sides of that pixel,
# along its row or its column and within this many pixels, put a surface more than a voxel in front
# of it (`_hidden`): the camera's dropouts on a surface seen at a grazing angle are single pixels
# and short runs. On the default episode (single_object, seed 0) 1,200 unknown voxels under the
# table top counted as looked at without a return and were reported hard; within 3 px 118 stayed,
# within 6 px none.
OCCLUDER_WINDOW_PX = 6


def _direction_bins(count: int) -> np.ndarray:
    """(count, 3) unit vectors spread evenly over the sphere (Fibonacci lattice)."""
    i = np.arange(count) + 0.5
    z = 1.0 - 2.0 * i / count
    r = np.sqrt(1.0 - z * z)
    phi = i * np.pi * (3.0 - np.sqrt(5.0))
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


# Directions a voxel is observed from, in bins about 45 degrees wide (one bit each of a uint32):
# two views count as distinct directions when they fall into different bins.
DIRECTION_BINS = _direction_bins(20)


def check_pose(T: np.ndarray, field: str) -> np.ndarray:
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise InputError(field, T if T.size <= 16 else T.shape, "a finite (4, 4) T_world_cam")
    R = T[:3, :3]
    if not np.allclose(R.T @ R, np.eye(3), atol=1e-5) or np.linalg.det(R) < 0:
        raise InputError(field, R.tolist(), "a proper rotation in the upper-left 3x3 block")
    return T


def check_K(K: np.ndarray) -> np.ndarray:
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise InputError(
            "K", K.tolist() if K.size == 9 else K.shape, "3x3 intrinsics with fx, fy > 0"
        )
    return K


def _declared_no_return(depth: np.ndarray) -> bool | np.ndarray:
    """What `carve_depth_frame` may carve along pixels without a return: those that say there is
    none within range (+Inf, REP 117), never those without an estimate (NaN)."""
    declared = np.isposinf(depth)
    return declared if declared.any() else False


def _carving_depth(depth: np.ndarray, conf: np.ndarray, min_confidence: float = 0.0) -> np.ndarray:
    """The depth a frame carves free space along: a pixel with a depth at confidence 0 (a
    guess its backend gives no weight, e.g. a stereo match the left-right check refused), or
    below `min_confidence`, marks the voxel it lands in, at its confidence, but is no evidence of
    the space in front of it: it carves nothing (NaN here). +Inf (no return within range) keeps
    carving."""
    with np.errstate(invalid="ignore"):
        # one comparison: above 0, conf < min_confidence holds wherever conf <= 0 does
        below = conf < min_confidence if min_confidence > 0 else conf <= 0
        guess = below & np.isfinite(depth)
    if not guess.any():
        return depth
    out = depth.copy()
    out[guess] = np.nan
    return out


def direction_bits(centres: np.ndarray, camera: np.ndarray) -> np.ndarray:
    """(K,) uint32: one bit per voxel, the `DIRECTION_BINS` bin of the direction from each voxel
    centre (K, 3) to the camera centre (3,) (or to its own point of (K, 3))."""
    d = np.asarray(camera, np.float64) - np.asarray(centres, np.float64)
    bins = np.argmax(d @ DIRECTION_BINS.T, axis=1)
    return np.left_shift(np.uint32(1), bins.astype(np.uint32))


@dataclass(frozen=True)
class DepthObservation:
    """One frame's evidence: hit voxel ids (ascending) with the frame's mean confidence and
    log(1 - capped confidence) in each, and the bit of the direction they were seen from; the ids
    of voxels its rays crossed as free; and the region voxels it looked at without a return
    (`missed`: in view, within range, their pixel has no depth) with their direction bits."""

    hit: np.ndarray  # (M,) int64
    confidence: np.ndarray  # (M,) float32
    log_residual: np.ndarray  # (M,) float32
    free: np.ndarray  # (F,) int64
    hit_bits: np.ndarray | None = None  # (M,) uint32
    hit_range: np.ndarray | None = None  # (M,) float32 metres: optical depth of each hit voxel
    missed: np.ndarray | None = None  # (K,) int64
    missed_bits: np.ndarray | None = None  # (K,) uint32


class FrameObserver:
    """Observes frames for a grid of layout `spec` with region voxels `roi_ids` (centres
    `roi_centres`), capping one observation's confidence at `max_confidence`. One frame at a
    time: its per-voxel tallies (`_FrameScratch`) are allocated once and cleared after each."""

    def __init__(
        self,
        spec: GridSpec,
        roi_ids: np.ndarray,
        roi_centres: np.ndarray,
        max_confidence: float,
        carve_min_confidence: float = 0.0,
    ) -> None:
        self.spec, self.roi_ids, self.roi_centres = spec, roi_ids, roi_centres
        self.max_confidence = float(max_confidence)
        self.carve_min_confidence = float(carve_min_confidence)
        self._scratch: _FrameScratch | None = None
        self._lock = threading.Lock()

    def observe(
        self,
        depth: np.ndarray,
        conf: np.ndarray,
        K: np.ndarray,
        T_world_cam: np.ndarray,
        max_range: float,
        stride: int,
    ) -> DepthObservation:
        """`FusedGrid.observe_depth`, which says what the arguments are."""
        depth = np.asarray(depth)
        conf = np.asarray(conf)
        if depth.ndim != 2:
            raise InputError("depth", depth.shape, "an (H, W) float32 image")
        if conf.shape != depth.shape:
            raise InputError("confidence", conf.shape, f"the depth image shape {depth.shape}")
        K = check_K(K)
        T = check_pose(T_world_cam, "T_world_cam")
        if not (max_range > 0 and np.isfinite(max_range)):
            raise InputError("max_range", max_range, "a finite value > 0 metres")
        if int(stride) < 1:
            raise InputError("stride", stride, "an integer >= 1")
        stride = int(stride)
        depth = np.ascontiguousarray(depth, dtype=np.float32)
        conf = np.ascontiguousarray(conf)
        with self._lock:
            if self._scratch is None:
                self._scratch = _FrameScratch(self.spec)
            scratch = self._scratch
            try:
                # Surface hits: every pixel with a return and a confidence, back-projected
                # (X = T D K^-1 x) into its voxel; each voxel's sample is the mean confidence
                # of its pixels. One pass, tallied in the scratch, not arrays of every pixel.
                touched = _tally_surface_hits(
                    depth,
                    conf,
                    float(K[0, 0]),
                    float(K[1, 1]),
                    float(K[0, 2]),
                    float(K[1, 2]),
                    T,
                    self.spec.lower,
                    float(self.spec.voxel_size),
                    np.asarray(self.spec.shape, np.int64),
                    scratch.pixels,
                    scratch.conf_sum,
                    scratch.touched,
                )
                hit = np.sort(scratch.touched[:touched])
                frame_conf = scratch.conf_sum[hit] / scratch.pixels[hit]
                # Free space: the perception package's carving (the one DDA for camera rays),
                # counted once per voxel per frame here; pixels with no return carve out to
                # max_range, guesses at confidence 0 (or below carve_min_confidence) carve
                # nothing. A voxel hit in this frame is not free in it.
                carve_depth_frame(
                    self.spec,
                    _carving_depth(depth, conf, self.carve_min_confidence),
                    K,
                    T,
                    scratch.crossed,
                    stride,
                    max_range,
                    carve_no_return=_declared_no_return(depth),
                    count=False,  # crossed or not: the rays run in parallel
                )
                crossed = np.flatnonzero(scratch.crossed)
                free = crossed[scratch.pixels[crossed] == 0]
                # Region voxels in view whose pixel has no depth: looked at, not resolved
                # (neither hit nor carved), e.g. a glossy or blank surface without a return.
                missed_at = _unresolved_in_view(
                    depth,
                    float(K[0, 0]),
                    float(K[1, 1]),
                    float(K[0, 2]),
                    float(K[1, 2]),
                    np.ascontiguousarray(np.linalg.inv(T)),
                    self.roi_centres,
                    float(max_range),
                    float(self.spec.voxel_size),
                    scratch.pixels,
                    scratch.crossed.reshape(-1),
                    self.roi_ids,
                )
                missed = self.roi_ids[missed_at]
            except BaseException:
                scratch.reset()  # a frame that fails part way leaves nothing behind
                raise
            scratch.clear(hit, crossed)
        capped = np.minimum(frame_conf, self.max_confidence)
        camera = T[:3, 3]
        hit_centres = self.spec.centers_of(hit)
        return DepthObservation(
            hit=hit,
            confidence=frame_conf.astype(np.float32),
            log_residual=np.log1p(-capped).astype(np.float32),
            free=free,
            hit_bits=direction_bits(hit_centres, camera),
            hit_range=((hit_centres - camera) @ T[:3, 2]).astype(np.float32),
            missed=missed,
            missed_bits=direction_bits(self.roi_centres[missed_at], camera),
        )


class _FrameScratch:
    """Per-voxel tallies of one frame, allocated once per grid and cleared after each frame.

    A frame's fusion used to allocate arrays of every pixel (points, indices, masks: megabytes
    each) and of every voxel (two bincounts) per frame: 20-30 ms of a 10 Hz stream went to
    allocating, filling and freeing them, and the heap they cycled through fragmented."""

    def __init__(self, spec: GridSpec) -> None:
        n = spec.num_voxels
        self.pixels = np.zeros(n, np.int32)  # the frame's pixels that landed in each voxel
        self.conf_sum = np.zeros(n, np.float64)  # ... and the sum of their confidences
        self.touched = np.empty(n, np.int64)  # the voxels with pixels, in first-touch order
        self.crossed = np.zeros(spec.shape, np.uint8)  # voxels the frame's rays crossed

    def clear(self, hit: np.ndarray, crossed: np.ndarray) -> None:
        """Zero what a frame wrote: its hit voxels and the voxels its rays crossed."""
        self.pixels[hit] = 0
        self.conf_sum[hit] = 0.0
        self.crossed.reshape(-1)[crossed] = 0

    def reset(self) -> None:
        self.pixels.fill(0)
        self.conf_sum.fill(0.0)
        self.crossed.fill(0)


@njit(cache=True, nogil=True, inline="always")
def _hidden(depth, iu, iv, limit):  # pragma: no cover - compiled
    """Whether the pixel (iu, iv), which has no return, lies between returns of a surface nearer
    than `limit`: along its row or its column, the nearest finite depths on both sides within
    OCCLUDER_WINDOW_PX, interpolated linearly to the pixel, give a depth below `limit`."""
    for axis in range(2):
        before, before_step = _nearest_return(depth, iu, iv, axis, -1)
        after, after_step = _nearest_return(depth, iu, iv, axis, 1)
        if before_step > 0 and after_step > 0:
            between = (before * after_step + after * before_step) / (before_step + after_step)
            if between < limit:
                return True
    return False


@njit(cache=True, nogil=True, inline="always")
def _nearest_return(depth, iu, iv, axis, sign):  # pragma: no cover - compiled
    """(depth, steps) of the nearest finite depth from (iu, iv) along its row (axis 0) or column
    (axis 1) in direction `sign`, within OCCLUDER_WINDOW_PX; steps 0 where there is none."""
    h, w = depth.shape
    for step in range(1, OCCLUDER_WINDOW_PX + 1):
        u = iu + sign * step if axis == 0 else iu
        v = iv + sign * step if axis == 1 else iv
        if u < 0 or u >= w or v < 0 or v >= h:
            break
        if np.isfinite(depth[v, u]):
            return np.float64(depth[v, u]), step
    return 0.0, 0


@njit(cache=True, nogil=True)
def _unresolved_in_view(
    depth, fx, fy, cx, cy, T_cam_world, centres, max_range, voxel_size, pixels, crossed, ids
):  # pragma: no cover - compiled
    """Positions (into `centres` (K, 3), flat voxel `ids` (K,)) of the voxels in front of the
    camera, within max_range, inside the image, whose centre's pixel has no finite depth and
    which the frame neither hit (`pixels` of the voxel 0) nor carved (`crossed` 0), and which no
    surface hides (`_hidden`): a dropout among returns from a surface in front of the voxel (a
    table top seen at a grazing angle) is not a look at what lies behind that surface."""
    h, w = depth.shape
    out = np.empty(centres.shape[0], np.int64)
    count = 0
    for k in range(centres.shape[0]):
        x, y, z = centres[k, 0], centres[k, 1], centres[k, 2]
        zc = T_cam_world[2, 0] * x + T_cam_world[2, 1] * y + T_cam_world[2, 2] * z
        zc += T_cam_world[2, 3]
        if not (zc > 0 and zc <= max_range):
            continue
        xc = T_cam_world[0, 0] * x + T_cam_world[0, 1] * y + T_cam_world[0, 2] * z
        yc = T_cam_world[1, 0] * x + T_cam_world[1, 1] * y + T_cam_world[1, 2] * z
        u = np.floor(fx * (xc + T_cam_world[0, 3]) / zc + cx)
        v = np.floor(fy * (yc + T_cam_world[1, 3]) / zc + cy)
        if not (0 <= u < w and 0 <= v < h):
            continue
        iu, iv = int(u), int(v)
        if np.isfinite(depth[iv, iu]):
            continue
        voxel = ids[k]
        if pixels[voxel] != 0 or crossed[voxel] != 0:
            continue
        if _hidden(depth, iu, iv, zc - voxel_size):
            continue
        out[count] = k
        count += 1
    return out[:count]


@njit(cache=True, nogil=True)
def _tally_surface_hits(
    depth, conf, fx, fy, cx, cy, T, lower, voxel_size, shape, pixels, conf_sum, touched
):  # pragma: no cover - compiled
    """Back-project each pixel with a finite depth > 0 and a finite confidence (clipped to
    [0, 1]) into its voxel (`pixel_to_world`, then the voxel rule of `GridSpec.flat_index`), and
    tally pixels and confidence per voxel inside the grid; returns how many voxels it touched
    (their ids in touched[:count]). Reads only its inputs and the scratch, so it releases the
    GIL."""
    h, w = depth.shape
    point = np.empty(3, np.float64)
    count = 0
    for v in range(h):
        for u in range(w):
            d = np.float64(depth[v, u])
            if not (np.isfinite(d) and d > 0):
                continue
            c = np.float64(conf[v, u])
            if not np.isfinite(c):
                continue
            pixel_to_world(u, v, d, fx, fy, cx, cy, T, point)
            index = 0
            inside = True
            for a in range(3):
                x = np.floor((point[a] - lower[a]) / voxel_size)
                if not (np.isfinite(x) and 0 <= x < shape[a]):
                    inside = False
                    break
                index = index * shape[a] + int(x)
            if not inside:
                continue
            if pixels[index] == 0:
                touched[count] = index
                count += 1
            pixels[index] += 1
            conf_sum[index] += min(max(c, 0.0), 1.0)
    return count
