"""Candidate views and their cached visibility masks.

Candidates are sampled where a camera works: at object level on shells around the region of
interest at the working distance (elevations that look at it, a small fan of orientations per
position); at room level on a lattice of known-free positions inside the room, each with a coarse
yaw x pitch set of orientations. Positions are checked against the fused occupancy map only (what
a robot has): clear of occupied voxels, and in known-free space (object level: or in unknown space
outside the region of interest).

Masks are dense: every voxel that can carry utility is tested against a cube-map z-buffer of the
occupied voxels at each candidate position (`zbuffer.py`), then against each view's frustum, and
weighted by the share of a full observation the view's resolution gives it.
"""

from __future__ import annotations

import copy
import os
import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
from numba import njit

from area3d_msgs_py.camera_pose import look_rotation
from area3d_msgs_py.errors import InputError
from area3d_perception.grid import GridSpec
from area3d_planner import incremental
from area3d_planner.fusion import DIRECTION_BINS, RANGE_BIN
from area3d_planner.masks import (
    score_all_views,
    score_view_list,
    score_views,
    view_weights,
)
from area3d_planner.zbuffer import in_frustum, new_zbuffer, seed_view_masks

CHUNKS_PER_THREAD = 8  # seed chunks per worker thread when building masks (load balance)
LEVELS = ("object", "room")


@dataclass(frozen=True)
class VisibilityParams:
    """Tunables of the candidates and the visibility cache (paper where it fixes them, else ours)."""

    level: str = "object"  # "object": shells around the region; "room": lattice inside it
    # object level: shells at these multiples of the working distance around the region centre
    shell_scales: tuple = (0.7, 0.85, 1.0)
    shell_elevations_deg: tuple = (0.0, 12.0, 25.0, 38.0, 52.0, 66.0, 80.0)
    shell_azimuth_step_deg: float = 15.0  # on the lowest ring; rings above get fewer positions
    fan_deg: float = 20.0  # orientations per shell position: at the centre, and +-fan in yaw/pitch
    # room level: a lattice of positions, each with yaw_bins x pitch_bins orientations
    seed_spacing: float = 0.5  # metres
    yaw_bins: int = 12  # 30 degree yaw steps: a coarse yaw/pitch grid (paper, "Visibility Gate")
    pitch_bins: int = 4  # pitch from pitch_min_deg to pitch_max_deg
    pitch_min_deg: float = -60.0  # looking down onto a table or the floor
    pitch_max_deg: float = 15.0  # looking at a wall, slightly up
    hfov_deg: float = 90.0  # paper, supplement: FOV 90 degrees
    width: int = 640  # image size: frustum aspect and pixel footprint of a voxel
    height: int = 480
    max_range: float = 5.0  # paper, supplement: max depth 5 m
    near: float = 0.05  # metres, nothing nearer than this is in view
    face_res: int = 256  # cube-map z-buffer pixels per face edge (0.35 degrees at the face centre)
    # A voxel counts as fully observed by a view where it covers at least this many pixels (4 x 4);
    # fewer pixels count in proportion: the resolution term of the utility.
    pixels_per_voxel: float = 16.0
    # Unknown space hides what lies behind it, like the surface it may hold: a view counts the
    # first non-free layer it sees (expected new surface), not the depth of an unknown column.
    unknown_occludes: bool = True
    # Weigh each voxel by the cosine between its free-space side and the direction to the camera
    # (the surface it may hold is seen foreshortened at a grazing angle).
    incidence: bool = False
    # Weigh each voxel by the confidence the depth backend reached at the view's range so far,
    # relative to its best range (FusedGrid.range_profile): a stereo camera's depth is less
    # precise far away, a depth camera's hardly changes within a few metres.
    range_profile: bool = True
    # A voxel seen again from a direction it was already observed from (a DIRECTION_BINS bin,
    # about 45 degrees) counts this much of a new observation: the same line of sight repeats the
    # same errors (a stereo match, a depth edge, a grazing angle) and the same occlusions.
    repeat_gain: float = 0.25

    def validate(self) -> None:
        if self.level not in LEVELS:
            raise InputError("level", self.level, f"one of {', '.join(LEVELS)}")
        for name in ("yaw_bins", "pitch_bins", "width", "height", "face_res"):
            value = getattr(self, name)
            if int(value) < 1:
                raise InputError(name, value, "an integer >= 1")
        if not (0 < self.hfov_deg < 180):
            raise InputError("hfov_deg", self.hfov_deg, "a value in (0, 180) degrees")
        if not (self.max_range > 0 and np.isfinite(self.max_range)):
            raise InputError("max_range", self.max_range, "a finite value > 0 metres")
        if not (0 <= self.near < self.max_range):
            raise InputError("near", self.near, f"a value in [0, max_range={self.max_range}) m")
        if not (0.0 <= self.repeat_gain <= 1.0):
            raise InputError("repeat_gain", self.repeat_gain, "a value in [0, 1]")
        if not (self.pixels_per_voxel > 0 and np.isfinite(self.pixels_per_voxel)):
            raise InputError("pixels_per_voxel", self.pixels_per_voxel, "a finite value > 0")
        if not (self.seed_spacing > 0 and np.isfinite(self.seed_spacing)):
            raise InputError("seed_spacing", self.seed_spacing, "a finite value > 0 metres")
        if not (self.shell_azimuth_step_deg > 0):
            raise InputError("shell_azimuth_step_deg", self.shell_azimuth_step_deg, "> 0 degrees")
        if len(self.shell_scales) == 0 or min(self.shell_scales) <= 0:
            raise InputError("shell_scales", list(self.shell_scales), "values > 0")
        if len(self.shell_elevations_deg) == 0 or not all(
            -90 < e < 90 for e in self.shell_elevations_deg
        ):
            raise InputError(
                "shell_elevations_deg", list(self.shell_elevations_deg), "values in (-90, 90)"
            )
        if not (-90 < self.pitch_min_deg <= self.pitch_max_deg < 90):
            raise InputError(
                "pitch_min_deg/pitch_max_deg",
                (self.pitch_min_deg, self.pitch_max_deg),
                "-90 < pitch_min_deg <= pitch_max_deg < 90",
            )

    @property
    def tan_x(self) -> float:
        return float(np.tan(np.deg2rad(self.hfov_deg) / 2))

    @property
    def tan_y(self) -> float:
        return self.tan_x * self.height / self.width

    @property
    def focal(self) -> float:
        """Focal length in pixels of the candidate views' camera."""
        return 0.5 * self.width / self.tan_x


def range_bin_dtype(max_range: float) -> type:
    """The integer type of the masks' range bins (`fusion.RANGE_BIN` metres each) up to
    max_range: uint8 up to 25.5 m, else uint16."""
    return np.uint8 if max_range / RANGE_BIN < np.iinfo(np.uint8).max else np.uint16


def _direction(yaw: np.ndarray, pitch: np.ndarray) -> np.ndarray:
    return np.stack(
        [np.cos(pitch) * np.cos(yaw), np.cos(pitch) * np.sin(yaw), np.sin(pitch)], axis=-1
    )


def orientation_bins(params: VisibilityParams) -> tuple[np.ndarray, np.ndarray]:
    """Yaw x pitch bins: (forward (B, 3) unit directions, rotations (B, 3, 3) R_world_cam).

    B = yaw_bins * pitch_bins, bin index = yaw_index * pitch_bins + pitch_index.
    """
    yaws = np.deg2rad(np.arange(params.yaw_bins) * 360.0 / params.yaw_bins)
    if params.pitch_bins == 1:
        pitches = np.deg2rad([0.5 * (params.pitch_min_deg + params.pitch_max_deg)])
    else:
        pitches = np.deg2rad(
            np.linspace(params.pitch_min_deg, params.pitch_max_deg, params.pitch_bins)
        )
    yy, pp = np.meshgrid(yaws, pitches, indexing="ij")
    forward = _direction(yy.ravel(), pp.ravel())
    return forward, look_rotation(forward)


def shell_positions(centre: np.ndarray, radius: float, params: VisibilityParams) -> np.ndarray:
    """(P, 3) positions on the shells around `centre` at shell_scales * radius, one ring per
    elevation, azimuths spaced so that neighbours on a ring are about as far apart as on the
    lowest ring."""
    centre = np.asarray(centre, np.float64)
    points = []
    base = np.deg2rad(params.shell_azimuth_step_deg)
    for scale in params.shell_scales:
        for i, el in enumerate(np.deg2rad(params.shell_elevations_deg)):
            count = max(3, int(round(2 * np.pi * np.cos(el) / base)))
            az = (np.arange(count) + 0.5 * (i % 2)) * 2 * np.pi / count
            d = _direction(az, np.full(count, el))
            points.append(centre + scale * radius * d)
    return np.concatenate(points)


def shell_rotations(positions: np.ndarray, target: np.ndarray, fan_deg: float) -> np.ndarray:
    """(P, 5, 3, 3): per position, looking at `target`, then turned by +-fan_deg in yaw and pitch."""
    to_t = np.asarray(target, np.float64)[None] - positions
    yaw = np.arctan2(to_t[:, 1], to_t[:, 0])
    pitch = np.arctan2(to_t[:, 2], np.linalg.norm(to_t[:, :2], axis=1))
    f = np.deg2rad(fan_deg)
    offsets = [(0.0, 0.0), (f, 0.0), (-f, 0.0), (0.0, f), (0.0, -f)]
    out = np.empty((positions.shape[0], len(offsets), 3, 3))
    for b, (dy, dp) in enumerate(offsets):
        p = np.clip(pitch + dp, -np.deg2rad(89.0), np.deg2rad(89.0))
        out[:, b] = look_rotation(_direction(yaw + dy, p))
    return out


def lattice_positions(lo: np.ndarray, hi: np.ndarray, spacing: float) -> np.ndarray:
    """(P, 3) centres of a `spacing` lattice inside the box [lo, hi], centred in it."""
    lo = np.asarray(lo, dtype=np.float64)
    hi = np.asarray(hi, dtype=np.float64)
    counts = np.maximum(np.floor((hi - lo) / spacing + 1e-9).astype(int), 1)
    offset = lo + 0.5 * ((hi - lo) - (counts - 1) * spacing)
    axes = [offset[a] + np.arange(counts[a]) * spacing for a in range(3)]
    return np.stack([g.ravel() for g in np.meshgrid(*axes, indexing="ij")], axis=1)


def valid_seeds(
    points: np.ndarray,
    spec: GridSpec,
    occupancy: np.ndarray,
    workspace_lo: np.ndarray,
    workspace_hi: np.ndarray,
    clearance: float,
    unknown_ok_outside: tuple[np.ndarray, np.ndarray] | None = None,
) -> np.ndarray:
    """(P,) bool: camera centres `points` (P, 3) a robot may plan for from its map alone.

    Inside the workspace box; no occupied voxel centre closer than clearance + voxel_size / 2;
    in a known-free voxel, or outside the grid, or (with `unknown_ok_outside` = (lo, hi)) in an
    unknown voxel outside that box. The camera itself refuses a pose the map got wrong.
    """
    lo = np.asarray(workspace_lo, dtype=np.float64)
    hi = np.asarray(workspace_hi, dtype=np.float64)
    if (
        lo.shape != (3,)
        or hi.shape != (3,)
        or not np.all(hi > lo)
        or not np.all(np.isfinite(hi - lo))
    ):
        raise InputError(
            "workspace", [lo.tolist(), hi.tolist()], "workspace_min < workspace_max on every axis"
        )
    points = np.asarray(points, np.float64).reshape(-1, 3)
    ok = np.all(np.isfinite(points), axis=1) & np.all((points >= lo) & (points <= hi), axis=1)
    if ok.any():
        ok &= _clear_of_occupied(
            points,
            ok,
            np.ascontiguousarray(occupancy).reshape(-1),
            np.asarray(spec.shape, np.int64),
            np.asarray(spec.lower, np.float64),
            float(spec.voxel_size),
            float(clearance + 0.5 * spec.voxel_size + 1e-12),
        )
    vox, inside = spec.flat_index(points)
    state = np.where(inside, occupancy[vox], 0)
    allowed = state == 0
    if unknown_ok_outside is not None:
        box_lo, box_hi = unknown_ok_outside
        outside_box = ~np.all((points >= box_lo) & (points <= box_hi), axis=1)
        allowed |= (state == -1) & outside_box
    return ok & allowed


@njit(cache=True, nogil=True)
def _clear_of_occupied(
    points, check, occupancy, shape, lower, voxel_size, bound
):  # pragma: no cover - compiled
    """(P,) bool: no occupied voxel (occupancy == 1) has its centre closer than `bound` to the
    point, for the points where `check` is True (True elsewhere). Only the voxels of the box
    around each point that can be that close are looked at: a few hundred at most for a camera's
    clearance, where a search tree over every occupied voxel of a room took tens of
    milliseconds to build."""
    ny, nz = shape[1], shape[2]
    reach = bound / voxel_size
    bound2 = bound * bound
    out = np.ones(points.shape[0], dtype=np.bool_)
    lo = np.empty(3, np.int64)
    hi = np.empty(3, np.int64)
    for p in range(points.shape[0]):
        if not check[p]:
            continue
        for a in range(3):
            # centre_a = lower + (i + 0.5) voxel_size lies within `bound` of x only for i in
            # ((x - lower) / voxel_size - 0.5 -+ reach): one voxel more on each side
            u = (points[p, a] - lower[a]) / voxel_size - 0.5
            u = min(max(u, -reach - 2.0), shape[a] + reach + 1.0)  # far outside: no voxel
            lo[a] = max(int(np.floor(u - reach)) - 1, 0)
            hi[a] = min(int(np.floor(u + reach)) + 1, shape[a] - 1)
        clear = True
        for i in range(lo[0], hi[0] + 1):
            dx = points[p, 0] - (lower[0] + (i + 0.5) * voxel_size)
            for j in range(lo[1], hi[1] + 1):
                dy = points[p, 1] - (lower[1] + (j + 0.5) * voxel_size)
                row = (i * ny + j) * nz
                for k in range(lo[2], hi[2] + 1):
                    if occupancy[row + k] != 1:
                        continue
                    dz = points[p, 2] - (lower[2] + (k + 0.5) * voxel_size)
                    if dx * dx + dy * dy + dz * dz < bound2:
                        clear = False
                        break
                if not clear:
                    break
            if not clear:
                break
        out[p] = clear
    return out


def free_side_normals(spec: GridSpec, occupancy: np.ndarray, ids: np.ndarray) -> np.ndarray:
    """(K, 3) unit normals of voxels `ids`: the mean direction to their known-free face neighbours
    (where a surface they hold faces), zero for voxels with none."""
    free = np.asarray(occupancy).reshape(spec.shape) == 0
    ijk = np.stack(np.unravel_index(np.asarray(ids, np.int64), spec.shape), axis=1)
    shape = np.asarray(spec.shape)
    n = np.zeros((ijk.shape[0], 3))
    for axis in range(3):
        for step in (-1, 1):
            nb = ijk.copy()
            nb[:, axis] += step
            ok = (nb[:, axis] >= 0) & (nb[:, axis] < shape[axis])
            hit = np.zeros(ijk.shape[0], bool)
            hit[ok] = free[tuple(nb[ok].T)]
            n[hit, axis] += step
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    return np.divide(n, norm, out=np.zeros_like(n), where=norm > 0)


@dataclass(frozen=True)
class ViewEvidence:
    """What the fused frames say about a view's worth beyond its geometry, applied to each mask
    entry when views are scored (`masks.entry_weight`): the depth backend's confidence by range
    relative to its best, and a share for voxels already observed from the view's direction.

    directions: (N,) uint32, the `fusion.DIRECTION_BINS` each voxel was observed from
    (`FusedGrid.directions`; empty: none yet); profile: (R,) float64 per `fusion.RANGE_BIN` of
    optical depth (`FusedGrid.range_profile`; ones: no preference); repeat_gain: what a voxel seen
    again from a direction it was observed from counts (`VisibilityParams.repeat_gain`).
    """

    directions: np.ndarray
    profile: np.ndarray
    repeat_gain: float

    @classmethod
    def none(cls) -> ViewEvidence:
        """No evidence: every range as good as the best, every direction new."""
        return cls(np.zeros(0, np.uint32), np.ones(1), 1.0)

    @classmethod
    def of_grid(
        cls, evidence: tuple[np.ndarray, tuple[np.ndarray, float]], params: VisibilityParams
    ) -> ViewEvidence:
        """From `FusedGrid.view_evidence()` ((directions, (profile, bin width))) and the
        parameters that say which of it counts (`range_profile`, `repeat_gain`)."""
        directions, (profile, width) = evidence
        if not np.isclose(width, RANGE_BIN):
            raise InputError("range profile bin", width, f"{RANGE_BIN} m (fusion.RANGE_BIN)")
        return cls(
            np.ascontiguousarray(directions, np.uint32),
            np.ascontiguousarray(profile if params.range_profile else np.ones(1), np.float64),
            float(params.repeat_gain),
        )

    def kernel_args(self) -> tuple:
        return (self.directions, self.profile, float(self.repeat_gain))


class VisibilityCache:
    """Cached visibility masks of every candidate view (seed s, orientation b), view index s * B + b.

    seeds: (S, 3) camera centres; rotations: (S, B, 3, 3) R_world_cam of their views.
    CSR layout: the mask of view v is voxel_ids[indptr[v]:indptr[v+1]] (int32 flat voxel index)
    with weights (float64, the share of a full observation the view's resolution gives the voxel),
    range_bins (the `fusion.RANGE_BIN` of its optical depth) and direction_bins (uint8, the
    `fusion.DIRECTION_BINS` row of the direction from the voxel to the camera): geometry only.
    The evidence of the fused frames (`ViewEvidence`, see `bind`) weighs each entry when views are
    scored: scoring a view against a field U (N,) is sum_k w_k U[id_k], w_k the entry's weight
    times repeat_gain where the voxel was observed from its direction bin already, times the
    range profile at its bin, rounded to float32 (`masks.entry_weight`: the weights a build with
    the evidence baked in stored, bit for bit; hence float64 geometric weights).
    record_ids (int32) / record_centres ((K, 3) metres): the voxels the masks may hold (for the
    frustum decay).
    """

    def __init__(
        self,
        spec: GridSpec,
        seeds: np.ndarray,
        rotations: np.ndarray,
        indptr: np.ndarray,
        voxel_ids: np.ndarray,
        weights: np.ndarray,
        record_ids: np.ndarray,
        params: VisibilityParams,
        range_bins: np.ndarray | None = None,
        direction_bins: np.ndarray | None = None,
        evidence: ViewEvidence | None = None,
    ) -> None:
        self.spec = spec
        self.seeds = seeds
        self.rotations = rotations
        self.forward = rotations[..., 2] if rotations.size else np.zeros((0, 0, 3))
        self.indptr = indptr
        self.voxel_ids = voxel_ids
        self.weights = weights
        self.range_bins = np.zeros(voxel_ids.size, np.uint8) if range_bins is None else range_bins
        self.direction_bins = (
            np.zeros(voxel_ids.size, np.uint8) if direction_bins is None else direction_bins
        )
        self.record_ids = record_ids
        self.record_centres = spec.centers_of(record_ids)
        self.params = params
        self.evidence = evidence or ViewEvidence.none()
        self._state: incremental.State | None = None  # what `update` starts from
        # how it was made: positions built in full / updated, what changed (`incremental`)
        self.report: dict = {}
        self._state_lock = threading.Lock()

    @property
    def num_seeds(self) -> int:
        return int(self.seeds.shape[0])

    @property
    def num_bins(self) -> int:
        return int(self.rotations.shape[1]) if self.rotations.ndim == 4 else 0

    @property
    def num_views(self) -> int:
        return self.num_seeds * self.num_bins

    @property
    def masks(self) -> tuple:
        """(indptr, voxel_ids, weights, range_bins, direction_bins): the kernels' mask set."""
        return (self.indptr, self.voxel_ids, self.weights, self.range_bins, self.direction_bins)

    def bind(self, evidence: ViewEvidence | None) -> VisibilityCache:
        """The same masks scored under `evidence` (a shallow copy: the arrays are shared)."""
        bound = copy.copy(self)
        bound.evidence = evidence or ViewEvidence.none()
        bound._state = None  # updates start from the cache itself, not its bound copies
        bound._state_lock = threading.Lock()
        return bound

    @classmethod
    def build(
        cls,
        spec: GridSpec,
        occupancy: np.ndarray,
        seeds: np.ndarray,
        rotations: np.ndarray,
        params: VisibilityParams | None = None,
        relevant: np.ndarray | None = None,
        threads: int | None = None,
        occluders: np.ndarray | None = None,
        incremental: bool = False,
    ) -> VisibilityCache:
        """Dense masks of every (seed, orientation) view: every relevant voxel visible from the
        seed (cube-map z-buffer of the occupied voxels) and inside the view's frustum.

        occupancy: (N,) int8 (-1 unknown, 0 free, 1 occupied). seeds: (S, 3); rotations:
        (S, B, 3, 3) or (B, 3, 3) shared by every seed. relevant: (N,) bool, the voxels recorded
        (default: every voxel that is not known free). occluders: (N,) bool, the voxels splatted
        into the z-buffer (default: the occupied ones). threads: worker threads (default: CPU
        count); the result does not depend on it. The masks depend on this geometry alone; the
        evidence of the frames weighs them when views are scored (`bind`). incremental: keep
        each position's z-buffer (cropped to what its splats wrote: 4 bytes a pixel) for `update`.
        """
        params = params or VisibilityParams()
        params.validate()
        geometry = _Geometry.of(spec, params, occupancy, seeds, rotations, relevant, occluders)
        return _assemble(cls, geometry, None, threads, incremental)

    def update(
        self,
        occupancy: np.ndarray,
        seeds: np.ndarray,
        rotations: np.ndarray,
        relevant: np.ndarray | None = None,
        threads: int | None = None,
        occluders: np.ndarray | None = None,
    ) -> VisibilityCache:
        """The cache of a changed map (arguments as `build`'s, with this cache's grid and
        parameters), equal to a full build's entry by entry, made incrementally
        (`incremental.py`): a position that stays a candidate keeps its masks where the change
        does not show from it and is re-examined only where it does; new positions are built in
        full. The z-buffers move to the new cache: this one's next update is a full build, and
        so is the update of a cache built without `incremental`."""
        geometry = _Geometry.of(
            self.spec, self.params, occupancy, seeds, rotations, relevant, occluders
        )
        return _assemble(type(self), geometry, self._take_state(self), threads, True)

    @staticmethod
    def _take_state(cache: VisibilityCache) -> tuple | None:
        """(the cache, its incremental state) once; None after (or without one)."""
        with cache._state_lock:
            state, cache._state = cache._state, None
        return None if state is None else (cache, state)

    def score(self, field: np.ndarray) -> np.ndarray:
        """(num_views,) float64 mask-weighted utility of every view under field U (N,) and the
        bound evidence."""
        return score_all_views(
            self.masks, self.evidence.kernel_args(), np.asarray(field, np.float64)
        )

    def score_seed(self, field: np.ndarray, seed: int) -> np.ndarray:
        """(num_bins,) float64 utilities of one seed's views (same sums as `score`)."""
        b = self.num_bins
        field = np.asarray(field, np.float64)
        return score_views(self.masks, self.evidence.kernel_args(), field, seed * b, seed * b + b)

    def score_views(self, field: np.ndarray, views: np.ndarray) -> np.ndarray:
        """(len(views),) float64 utilities of the given views (the same sums as `score`)."""
        return score_view_list(
            self.masks,
            self.evidence.kernel_args(),
            np.asarray(field, np.float64),
            np.asarray(views, np.int64),
        )

    def mask(self, view: int) -> tuple[np.ndarray, np.ndarray]:
        """(voxel ids int32, weights float32) of one view, each weight under the bound evidence
        (`masks.entry_weight`)."""
        lo, hi = self.indptr[view], self.indptr[view + 1]
        return self.voxel_ids[lo:hi], view_weights(
            self.masks, self.evidence.kernel_args(), int(view)
        )

    def view_pose(self, view: int) -> np.ndarray:
        """(4, 4) T_world_cam of a view (optical frame)."""
        s, b = divmod(int(view), self.num_bins)
        T = np.eye(4)
        T[:3, :3] = self.rotations[s, b]
        T[:3, 3] = self.seeds[s]
        return T

    def frustum(self, T_world_cam: np.ndarray) -> np.ndarray:
        """int32 ids of the recorded voxels inside the frustum of a pose, occluded or not (the
        paper's frustum decay acts on all of them)."""
        p = self.params
        inside = in_frustum(
            self.record_centres,
            np.ascontiguousarray(T_world_cam, np.float64),
            p.near,
            p.max_range,
            p.tan_x,
            p.tan_y,
        )
        return self.record_ids[inside]


@dataclass
class _Geometry:
    """What a build reads of the map, checked and prepared."""

    spec: GridSpec
    params: VisibilityParams
    occupancy: np.ndarray  # (N,) int8
    seeds: np.ndarray  # (S, 3)
    rotations: np.ndarray  # (S, B, 3, 3)
    record_ids: np.ndarray  # (K,) int32 ascending
    centres: np.ndarray  # (K, 3)
    normals: np.ndarray  # (K, 3)
    occluders: np.ndarray  # (N,) bool

    @classmethod
    def of(
        cls,
        spec: GridSpec,
        params: VisibilityParams,
        occupancy: np.ndarray,
        seeds: np.ndarray,
        rotations: np.ndarray,
        relevant: np.ndarray | None,
        occluders: np.ndarray | None,
    ) -> _Geometry:
        occupancy = np.ascontiguousarray(occupancy, dtype=np.int8)
        if occupancy.shape != (spec.num_voxels,):
            raise InputError(
                "occupancy", occupancy.shape, f"({spec.num_voxels},) int8 flat occupancy"
            )
        seeds = np.ascontiguousarray(np.asarray(seeds, dtype=np.float64).reshape(-1, 3))
        rotations = np.asarray(rotations, np.float64)
        if rotations.ndim == 3:
            rotations = np.broadcast_to(rotations, (seeds.shape[0], *rotations.shape))
        rotations = np.ascontiguousarray(rotations)
        if rotations.shape[:1] != seeds.shape[:1] or rotations.shape[2:] != (3, 3):
            raise InputError(
                "rotations", rotations.shape, f"({seeds.shape[0]}, B, 3, 3) view rotations"
            )
        if relevant is None:
            relevant = occupancy != 0
        record_ids = np.flatnonzero(relevant).astype(np.int32)
        if params.incidence:
            normals = free_side_normals(spec, occupancy, record_ids)
        else:
            normals = np.zeros((record_ids.size, 3))
        if occluders is None:
            occluders = occupancy == 1
        return cls(
            spec,
            params,
            occupancy,
            seeds,
            rotations,
            record_ids,
            spec.centers_of(record_ids),
            normals,
            np.asarray(occluders, bool),
        )

    @property
    def tol(self) -> float:
        return 0.7 * self.spec.voxel_size  # the surface layer counts, one behind it does not

    @property
    def bin_template(self) -> np.ndarray:
        return np.zeros(0, range_bin_dtype(self.params.max_range))


def _match(g: _Geometry, previous: tuple | None) -> np.ndarray:
    """(S,) int64: the position of each candidate of `g` in the previous cache (same centre and
    view rotations, bit for bit), -1 for a new one (or without a compatible previous cache)."""
    match = np.full(g.seeds.shape[0], -1, np.int64)
    if previous is None:
        return match
    old = previous[0]
    if old.params != g.params or old.spec != g.spec or old.num_bins != g.rotations.shape[1]:
        return match
    where = {
        seed.tobytes() + rot.tobytes(): i
        for i, (seed, rot) in enumerate(zip(old.seeds, old.rotations, strict=True))
    }
    for s, (seed, rot) in enumerate(zip(g.seeds, g.rotations, strict=True)):
        match[s] = where.get(seed.tobytes() + rot.tobytes(), -1)
    return match


def _chunks(positions: np.ndarray, count: int) -> list[np.ndarray]:
    return [c for c in np.array_split(positions, max(1, min(count, positions.size))) if c.size]


def _assemble(
    cls: type, g: _Geometry, previous: tuple | None, threads: int | None, keep: bool
) -> VisibilityCache:
    """Masks of every candidate view of `g`: built in full, or updated from `previous` (a cache
    and its `incremental.State`) for the positions it holds too; with `keep`, the new cache
    keeps its z-buffers for the next update."""
    params, spec = g.params, g.spec
    n_seeds, n_views = g.seeds.shape[0], g.rotations.shape[1]
    match = _match(g, previous)
    fresh, kept = np.flatnonzero(match < 0), np.flatnonzero(match >= 0)
    change = incremental.Change(g, *previous, match) if kept.size else None
    threads = max(1, min(threads or os.cpu_count() or 1, max(1, n_seeds)))
    per_share = (threads * CHUNKS_PER_THREAD if threads > 1 else 1) / max(1, n_seeds)
    tasks = [("full", c) for c in _chunks(fresh, round(per_share * fresh.size))]
    if change is not None and not change.nothing:
        tasks += [("update", c) for c in _chunks(kept, round(per_share * kept.size))]
    occ_centres = spec.centers_of(np.flatnonzero(g.occluders)) if fresh.size else None
    scratch = threading.local()

    def run(task: tuple) -> tuple:
        kind, idx = task
        if kind == "update":
            if not hasattr(scratch, "update"):
                scratch.update = incremental.new_scratch(params.face_res, spec.num_voxels)
            return kind, idx, change.run(idx, scratch.update)
        if not hasattr(scratch, "zbuf"):
            scratch.zbuf, scratch.dirty = new_zbuffer(params.face_res)
        return (
            kind,
            idx,
            seed_view_masks(
                np.ascontiguousarray(g.seeds[idx]),
                np.ascontiguousarray(g.rotations[idx]),
                occ_centres,
                g.centres,
                g.record_ids,
                g.normals,
                spec.voxel_size,
                params.max_range,
                params.near,
                params.tan_x,
                params.tan_y,
                params.focal,
                params.pixels_per_voxel,
                g.tol,
                scratch.zbuf,
                scratch.dirty,
                RANGE_BIN,
                DIRECTION_BINS,
                g.bin_template,
                keep,
            ),
        )

    if threads == 1 or len(tasks) <= 1:
        results = [run(t) for t in tasks]
    else:
        with ThreadPoolExecutor(max_workers=threads) as pool:
            results = list(pool.map(run, tasks))
    # each position's masks, and its buffer
    pieces: list = [None] * n_seeds
    buffers = incremental.Buffers.empty(n_seeds, params.face_res)
    if change is not None:
        change.finish()
        buffers.take(kept, change.buffers, match[kept])
    if keep:  # the new positions' buffers go into the pool: room for all of them at once
        buffers.reserve(sum(out[5][0].size for kind, _, out in results if kind == "full"))
    for kind, idx, out in results:
        if kind == "update":
            for s, piece in zip(idx, out, strict=True):
                pieces[s] = piece
            continue
        nnz, ids, w, rb, db, (data, rects, offsets) = out
        if keep:
            buffers.add(idx, data, rects, offsets, g.rotations[idx], params)
        counts = nnz.reshape(idx.size, n_views)
        ends = np.cumsum(counts.sum(axis=1))
        for q, s in enumerate(idx):
            a, e = ends[q] - counts[q].sum(), ends[q]
            pieces[s] = (counts[q], ids[a:e], w[a:e], rb[a:e], db[a:e])
    for s in kept:
        if pieces[s] is None:  # nothing it sees changed: its masks as they were
            pieces[s] = change.old_piece(match[s])
    columns = [
        np.concatenate([p[i] for p in pieces]) if pieces else np.zeros(0, dtype)
        for i, dtype in enumerate((np.int64, np.int32, np.float64, g.bin_template.dtype, np.uint8))
    ]
    indptr = np.zeros(columns[0].size + 1, np.int64)
    np.cumsum(columns[0], out=indptr[1:])
    cache = cls(
        spec,
        g.seeds,
        g.rotations,
        indptr,
        columns[1],
        columns[2],
        g.record_ids,
        params,
        columns[3],
        columns[4],
    )
    if keep:
        cache._state = incremental.State(buffers.compacted(), g.occluders, g.normals)
    cache.report = {"positions": n_seeds, "built": int(fresh.size), "updated": int(kept.size)}
    if change is not None:
        cache.report |= change.counts | dict(
            zip(incremental.STAT_NAMES, change.stats.tolist(), strict=True)
        )
    return cache
