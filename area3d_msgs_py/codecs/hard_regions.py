"""area3d_interfaces/HardRegionArray <-> (N,) HARD_REGION_DTYPE rows (`area3d_msgs_py.hard_region`)."""

from __future__ import annotations

from typing import Any

import numpy as np

from area3d_msgs_py import msgs
from area3d_msgs_py.codecs.header import header
from area3d_msgs_py.errors import InputError
from area3d_msgs_py.hard_region import HARD_REGION_DTYPE


def hard_regions_to_msg(regions: np.ndarray, stamp_ns: int, frame_id: str) -> Any:
    """(N,) HARD_REGION_DTYPE -> area3d_interfaces/HardRegionArray (order kept)."""
    regions = np.asarray(regions)
    if regions.dtype != HARD_REGION_DTYPE or regions.ndim != 1:
        raise InputError(
            "regions", f"{regions.dtype} {regions.shape}", "a (N,) array of HARD_REGION_DTYPE"
        )
    numbers = np.concatenate(
        [regions["centroid"], regions["extent"], regions["mean_uncertainty"][:, None]], axis=1
    )
    if not np.isfinite(numbers).all():
        raise InputError("regions", "non-finite values", "finite centroids, extents, uncertainty")
    if (regions["extent"] < 0).any():
        raise InputError("regions.extent", regions["extent"].tolist(), "sizes >= 0 m")
    return msgs.HardRegionArray(
        header=header(stamp_ns, frame_id),
        regions=[
            msgs.HardRegion(
                centroid=msgs.Point(x=float(c[0]), y=float(c[1]), z=float(c[2])),
                extent=msgs.Vector3(x=float(e[0]), y=float(e[1]), z=float(e[2])),
                voxel_count=int(n),
                direction_count=int(d),
                mean_uncertainty=float(u),
            )
            for c, e, n, d, u in zip(
                regions["centroid"],
                regions["extent"],
                regions["voxel_count"],
                regions["direction_count"],
                regions["mean_uncertainty"],
                strict=True,
            )
        ],
    )


def msg_to_hard_regions(msg: Any) -> np.ndarray:
    """area3d_interfaces/HardRegionArray -> (N,) HARD_REGION_DTYPE."""
    regions = np.zeros(len(msg.regions), HARD_REGION_DTYPE)
    for i, region in enumerate(msg.regions):
        c, e = region.centroid, region.extent
        regions[i] = (
            (c.x, c.y, c.z),
            (e.x, e.y, e.z),
            region.voxel_count,
            region.direction_count,
            region.mean_uncertainty,
        )
    return regions
