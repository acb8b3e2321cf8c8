"""The `rgbd` backend: per-pixel confidence of a structured-light / ToF camera's depth.

The camera is `area3d_msgs_py.depth_sensor.RgbdSensorParams` (axial noise of Nguyen, Izadi and
Lovell, 3DIMPVT 2012: sigma_z(z, theta) = a + b (z - z0)^2 + c / sqrt(z) * theta^2 /
(pi/2 - theta)^2), the description the simulated camera draws its noise from
(`sim_bridge.noise`). Confidence is the product of three factors in [0, 1]:

    range:      exp(-(sigma_z(z, 0) / sigma_ref)^2)
    incidence:  max(cos theta, 0)^p
    edges:      ramps from `edge_confidence` on a depth discontinuity to 1 at `edge_radius_px` + 1 px

and 0 where depth is missing; theta and the discontinuities come from `area3d_msgs_py.depth_surface`.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from area3d_msgs_py.depth_sensor import RgbdSensorParams, check_depth_and_intrinsics
from area3d_msgs_py.depth_surface import edge_distance, surface_terms


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


def rgbd_confidence(
    depth: np.ndarray, K: np.ndarray, params: RgbdSensorParams | None = None
) -> np.ndarray:
    """Per-pixel confidence of a depth image under the sensor model.

    depth: (H, W) float metres along optical z; NaN, inf, <= 0 or beyond `max_range` = missing.
    K: (3, 3) intrinsics.
    Returns conf (H, W) float32 in [0, 1], 0 where depth is missing.
    """
    depth, K = check_depth_and_intrinsics(depth, K)
    params = (params or RgbdSensorParams()).at_focal(K[0, 0])
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
