"""Cached visibility masks of the candidate views (`candidates.py`), and their scores.

Masks are dense: every voxel that can carry utility is tested against a cube-map z-buffer of the
occupied voxels at each candidate position (`zbuffer.py`), then against each view's frustum, and
weighted by the share of a full observation the view's resolution gives it. The masks are built,
or brought up to date after the map changed (`incremental.py`), in `visibility_build.py`.
"""

from __future__ import annotations

import copy
import threading
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from area3d_msgs_py.errors import InputError
from area3d_msgs_py.grid import GridSpec
from area3d_planner.candidates import VisibilityParams
from area3d_planner.fusion import RANGE_BIN
from area3d_planner.masks import (
    score_all_views,
    score_view_list,
    score_views,
    view_weights,
)
from area3d_planner.visibility_build import Geometry, assemble
from area3d_planner.zbuffer import in_frustum

if TYPE_CHECKING:
    from area3d_planner import incremental


@dataclass(frozen=True)
class ViewEvidence:
    """What the fused frames say about a view's worth beyond its geometry, applied to each mask
    entry when views are scored (`masks.entry_weight`): the depth backend's confidence by range
    relative to its best, and a share for voxels already observed from the view's direction.

    directions: (N,) uint32, the `observation.DIRECTION_BINS` each voxel was observed from
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
    `observation.DIRECTION_BINS` row of the direction from the voxel to the camera): geometry only.
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
        geometry = Geometry.of(spec, params, occupancy, seeds, rotations, relevant, occluders)
        return assemble(cls, geometry, None, threads, incremental)

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
        geometry = Geometry.of(
            self.spec, self.params, occupancy, seeds, rotations, relevant, occluders
        )
        return assemble(type(self), geometry, self._take_state(self), threads, True)

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
