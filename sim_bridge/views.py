"""Camera poses that look at a point: T_world_cam of the optical frame (z forward, x right, y down)."""

from __future__ import annotations

import numpy as np

WORLD_UP = np.array([0.0, 0.0, 1.0])  # REP 103: `world` is z-up


def look_at(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """(4, 4) float64 T_world_cam of an optical frame at `eye` (3,) looking at `target` (3,), metres.

    The image x axis stays horizontal (no roll); looking straight up or down is resolved by
    taking world +x as the image "down" direction.
    """
    eye = np.asarray(eye, dtype=np.float64)
    z = np.asarray(target, dtype=np.float64) - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, WORLD_UP)
    if np.linalg.norm(x) < 1e-9:
        x = np.cross(z, [1.0, 0.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = x, y, z, eye
    return T


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
