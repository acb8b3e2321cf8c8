"""Views on a sphere around a point, each looking at it (T_world_cam of the optical frame)."""

from __future__ import annotations

import numpy as np

from area3d_msgs_py.camera_pose import look_at


def orbit_views(
    centre: np.ndarray,
    radius: float,
    azimuths_deg: np.ndarray,
    elevations_deg: np.ndarray,
) -> np.ndarray:
    """(N, 4, 4) views on a sphere of `radius` (m) around `centre`, all looking at it.

    azimuths_deg, elevations_deg: (N,) degrees; azimuth from world +x towards +y, elevation above
    the horizontal plane through `centre`.
    """
    centre = np.asarray(centre, dtype=np.float64)
    az = np.deg2rad(np.asarray(azimuths_deg, dtype=np.float64))
    el = np.deg2rad(np.asarray(elevations_deg, dtype=np.float64))
    eyes = centre + radius * np.stack(
        [np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], 1
    )
    return np.stack([look_at(e, centre) for e in eyes])
