"""The voxel grid every node agrees on: an axis-aligned box of cubic voxels in `world`."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit


@dataclass(frozen=True)
class GridSpec:
    """Axis-aligned voxel grid in the `world` frame.

    origin: (3,) world coordinates of the min corner of voxel (0, 0, 0), metres.
    voxel_size: edge length of one cubic voxel, metres.
    shape: (nx, ny, nz) voxel counts.
    """

    origin: tuple[float, float, float]
    voxel_size: float
    shape: tuple[int, int, int]

    @classmethod
    def from_bounds(cls, lo: np.ndarray, hi: np.ndarray, voxel_size: float) -> GridSpec:
        """Smallest grid of `voxel_size` voxels that covers the box [lo, hi]."""
        lo = np.asarray(lo, dtype=np.float64)
        hi = np.asarray(hi, dtype=np.float64)
        if not (voxel_size > 0 and np.isfinite(voxel_size)):
            raise ValueError(f"voxel_size: got {voxel_size!r}, expected a finite value > 0 metres")
        if lo.shape != (3,) or hi.shape != (3,) or not np.all(hi > lo):
            raise ValueError(
                f"bounds: got lo={lo.tolist()} hi={hi.tolist()}, expected lo < hi on every axis"
            )
        shape = np.maximum(np.ceil((hi - lo) / voxel_size - 1e-9).astype(int), 1)
        return cls(tuple(float(v) for v in lo), float(voxel_size), tuple(int(v) for v in shape))

    @property
    def num_voxels(self) -> int:
        return int(np.prod(self.shape))

    @property
    def lower(self) -> np.ndarray:
        return np.asarray(self.origin, dtype=np.float64)

    @property
    def upper(self) -> np.ndarray:
        return self.lower + np.asarray(self.shape) * self.voxel_size

    def centers(self) -> np.ndarray:
        """(nx*ny*nz, 3) float64 voxel centres in C order (x slowest, z fastest)."""
        axes = [
            self.origin[i] + (np.arange(self.shape[i]) + 0.5) * self.voxel_size for i in range(3)
        ]
        gx, gy, gz = np.meshgrid(*axes, indexing="ij")
        return np.stack([gx.ravel(), gy.ravel(), gz.ravel()], axis=1)

    def centers_of(self, ids: np.ndarray) -> np.ndarray:
        """(K, 3) float64 centres of the voxels with flat (C order) indices `ids` (K,)."""
        ijk = np.stack(np.unravel_index(np.asarray(ids, np.int64), self.shape), axis=1)
        return np.ascontiguousarray(self.lower + (ijk + 0.5) * self.voxel_size)

    def voxel_index(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Integer voxel coordinates of `points` (N, 3) and a mask of those inside the grid.

        Returns (ijk (N, 3) int64, inside (N,) bool); ijk of outside points is clipped, not valid.
        """
        ijk = np.floor(
            (np.asarray(points, dtype=np.float64) - self.lower) / self.voxel_size
        ).astype(np.int64)
        inside = np.all((ijk >= 0) & (ijk < np.asarray(self.shape)), axis=1)
        return np.clip(ijk, 0, np.asarray(self.shape) - 1), inside

    def flat_index(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Flat (C order) voxel index of `points` (N, 3) and the inside mask (as `voxel_index`:
        outside points get the index of the clipped voxel). One pass per frame's 300k points
        instead of the half dozen (N, 3) temporaries of `voxel_index`."""
        points = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
        return _flat_index(points, self.lower, float(self.voxel_size), np.asarray(self.shape))


@njit(cache=True, nogil=True)
def _flat_index(points, lower, voxel_size, shape):  # pragma: no cover - compiled
    n = points.shape[0]
    flat = np.empty(n, dtype=np.int64)
    inside = np.empty(n, dtype=np.bool_)
    for p in range(n):
        index = 0
        ok = True
        for axis in range(3):
            x = np.floor((points[p, axis] - lower[axis]) / voxel_size)
            if not np.isfinite(x):  # as numpy's cast of NaN: outside, clipped to 0
                i = 0
                ok = False
            else:
                i = int(x)
                if i < 0:
                    i = 0
                    ok = False
                elif i >= shape[axis]:
                    i = shape[axis] - 1
                    ok = False
            index = index * shape[axis] + i
        flat[p] = index
        inside[p] = ok
    return flat, inside
