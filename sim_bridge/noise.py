"""The simulated depth camera's noise: a noisy copy of a perfect depth image, as a Kinect-class
structured-light camera would return it.

The sensor's coefficients are `area3d_msgs_py.depth_sensor.RgbdSensorParams` (Nguyen, Izadi and
Lovell, 3DIMPVT 2012), the same description perception derives its `rgbd` confidence from; the
incidence angles and depth edges come from the image itself (`area3d_msgs_py.depth_surface`), as
they would for a real sensor.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from area3d_msgs_py.depth_sensor import (
    MAX_THETA,
    RgbdSensorParams,
    axial_sigma_at,
    check_depth_and_intrinsics,
    valid_depth_mask,
)
from area3d_msgs_py.depth_surface import edge_distance, surface_terms


@njit(cache=True, error_model="numpy")
def _add_axial_noise(depth, theta, noise, a, b, z0, c, max_theta):  # pragma: no cover - compiled
    """depth += sigma_z(depth, theta) x noise in place (float32; NaN stays NaN)."""
    for n in range(depth.size):
        d = depth[n]
        z = d if np.isfinite(d) else np.float32(1.0)
        sigma = np.float32(axial_sigma_at(z, theta[n], a, b, z0, c, max_theta))
        depth[n] += sigma * noise[n]


def draw_depth_noise(
    rng: np.random.Generator, n: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The draws of one noisy depth image of `n` pixels: (axial (n,), lateral (2, n), edge (n,),
    grazing (n,)). Every draw covers the whole image, whatever the depth holds: the noise of a
    pixel depends on the generator's state and the pixel only, so two renderings that differ in
    a few edge pixels (a pose through a quaternion and back) get the same noise everywhere else,
    and a camera can skip a capture's noise by drawing it (`SimCamera.reseed`)."""
    axial = rng.standard_normal(n, dtype=np.float32)
    lateral = rng.standard_normal((2, n), dtype=np.float32)
    edge_draw = rng.random(n, dtype=np.float32)
    grazing_draw = rng.random(n, dtype=np.float32)
    return axial, lateral, edge_draw, grazing_draw


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
    `grazing_start_deg` to 1 at `grazing_full_deg`), and the range cut at `max_range` and
    `min_range`. The coefficients are the sensor's at the camera's focal length (`at_focal`).

    depth: (H, W) float metres, NaN = no return. K: (3, 3). rng: numpy Generator (seeded by caller).
    Returns (H, W) float32 metres, NaN = no return, -Inf = nearer than `min_range` (REP 117).
    """
    depth, K = check_depth_and_intrinsics(depth, K)
    params = (params or RgbdSensorParams()).at_focal(K[0, 0])
    h, w = depth.shape
    valid = valid_depth_mask(depth)
    clean = np.where(valid, depth, np.float32(np.nan))
    cos, edges = surface_terms(
        clean, K, params.edge_jump_rel, np.inf, params.normal_smoothing_px, params.normal_step_px
    )
    theta = np.arccos(cos)
    dist = edge_distance(edges, params.edge_radius_px)

    axial, lateral, edge_draw, grazing_draw = draw_depth_noise(rng, h * w)

    out = clean.copy()
    band = np.flatnonzero(dist.ravel() <= params.edge_radius_px)
    if band.size:
        t = np.minimum(theta.ravel()[band], MAX_THETA)
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
        MAX_THETA,
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
        out[out < params.min_range] = -np.inf  # REP 117: nearer than the camera measures
    return out
