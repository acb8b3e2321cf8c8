"""Candidate views: their parameters (`VisibilityParams`, also those of the visibility cache),
positions and orientations.

Candidates are sampled where a camera works: at object level on shells around the region of
interest at the working distance (elevations that look at it, a small fan of orientations per
position); at room level on a lattice of known-free positions inside the room, each with a coarse
yaw x pitch set of orientations. Positions are checked against the fused occupancy map only (what
a robot has): clear of occupied voxels, and in known-free space (object level: or in unknown space
outside the region of interest). Their visibility masks: `visibility.py`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from area3d_msgs_py.camera_pose import look_rotation
from area3d_msgs_py.errors import InputError
from area3d_msgs_py.grid import GridSpec

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
    # ... also over the region (above its top, within its footprint) at object level (off: a view
    # from above sees the region through it; a stereo pair leaves much of it uncarved).
    unknown_above_occludes: bool = False
    # ... but only this deep (metres, whole voxels; 0 = at once): a view sees into unknown space
    # behind the boundary of carved space as far as this and counts what it sees there, where the
    # surface it may add lies (a side of an object in the shadow of the initial views), not only
    # the boundary layer, and not the whole depth of an unknown column.
    unknown_see_through: float = 0.0
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
        if not (np.isfinite(self.unknown_see_through) and self.unknown_see_through >= 0):
            raise InputError(
                "unknown_see_through", self.unknown_see_through, "a finite value >= 0 metres"
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
