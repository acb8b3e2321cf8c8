"""A Kinect-class depth camera, described once: its noise parameters and their validation, the
axial noise curve, and the checks every depth image of the sensor model passes.

The simulated camera draws its noise from this description (`sim_bridge.noise`), perception derives
its `rgbd` confidence from it (`area3d_perception.sensor_model`): one sensor, one set of
coefficients. Axial and lateral noise follow Nguyen, Izadi and Lovell, "Modeling Kinect Sensor
Noise for Improved 3D Reconstruction and Tracking" (3DIMPVT 2012):

    sigma_z(z, theta) = a + b (z - z0)^2 + c / sqrt(z) * theta^2 / (pi/2 - theta)^2   [metres]
    sigma_L(theta)    = l0 + l1 * theta / (pi/2 - theta)                              [pixels]

with a = 0.0012, b = 0.0019, z0 = 0.4 m, c = 0.0001, l0 = 0.8 px, l1 = 0.035 px; theta is the angle
between the surface normal and the viewing ray (`area3d_msgs_py.depth_surface`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numba import njit

from area3d_msgs_py.camera import PAPER_MAX_RANGE
from area3d_msgs_py.errors import InputError
from area3d_msgs_py.param_fields import described


@dataclass(frozen=True)
class RgbdSensorParams:
    """Noise and confidence model of a depth camera; defaults are a Kinect-class sensor."""

    # Axial noise sigma_z = a + b (z - z0)^2 (Nguyen et al. 2012, fit for 10-60 deg incidence).
    sigma_a: float = described(
        0.0012, "axial noise sigma_z = a + b (z - z0)^2: a (Nguyen et al. 2012)", "metres",
        (0.0, 1.0),
    )  # fmt: skip
    sigma_b: float = described(
        0.0019, "axial noise: b (Nguyen et al. 2012)", "per metre", (0.0, 1.0)
    )
    sigma_z0: float = described(0.4, "axial noise: z0 (Nguyen et al. 2012)", "metres", (0.0, 100.0))
    # Angular growth of axial noise, c / sqrt(z) * theta^2 / (pi/2 - theta)^2 (Nguyen et al. 2012).
    sigma_angle: float = described(
        0.0001,
        "growth of axial noise with incidence theta, c / sqrt(z) theta^2 / (pi/2 - theta)^2: c "
        "(Nguyen et al. 2012)",
        "metres^1.5",
        (0.0, 1.0),
    )
    # Lateral noise in pixels, l0 + l1 * theta / (pi/2 - theta) (Nguyen et al. 2012).
    lateral_l0_px: float = described(
        0.8, "lateral noise l0 + l1 theta / (pi/2 - theta): l0 (Nguyen et al. 2012)", "pixels",
        (0.0, 100.0),
    )  # fmt: skip
    lateral_l1_px: float = described(
        0.035, "lateral noise: l1 (Nguyen et al. 2012)", "pixels", (0.0, 100.0)
    )
    # Axial sigma at which range confidence falls to 1/e; 2.5 cm is reached near 3.9 m on the curve
    # above, where Kinect-class depth stops being useful for centimetre reconstruction (our choice).
    sigma_ref: float = described(
        0.025, "axial sigma at which the range confidence falls to 1/e", "metres", (1e-6, 10.0)
    )
    # Normals: edge-preserving box mean of this radius, then tangents over this many pixels; at
    # 1 m a Kinect pixel is ~3 mm wide and the axial noise ~2 mm, so 1-pixel tangents would be
    # dominated by noise (our choice; KinectFusion smooths depth before normals for the same reason).
    normal_smoothing_px: int = described(
        1, "radius of the edge-preserving mean before normals", "pixels", (0, 32)
    )
    normal_step_px: int = described(2, "normals: tangents over this many pixels", "pixels", (1, 32))
    # Exponent p of the incidence factor max(cos theta, 0)^p (Lambertian return: p = 1).
    incidence_power: float = described(
        1.0, "exponent p of the incidence confidence max(cos theta, 0)^p (Lambertian: 1)", "",
        (0.0, 10.0),
    )  # fmt: skip
    # A neighbour differing by more than this fraction of the nearer depth is a discontinuity.
    edge_jump_rel: float = described(
        0.05,
        "a neighbour this much farther, as a fraction of the nearer depth, makes a discontinuity",
        "fraction",
        (1e-6, 10.0),
    )
    # Pixels within this many pixels of a discontinuity get reduced confidence (mixed pixels).
    edge_radius_px: int = described(
        2, "pixels this close to a discontinuity get reduced confidence", "pixels", (0, 64)
    )
    # Confidence factor on the discontinuity itself; ramps linearly to 1 outside the radius.
    edge_confidence: float = described(
        0.2, "confidence factor on a discontinuity, ramping to 1 at edge_radius_px", "", (0.0, 1.0)
    )
    # Noise only: probability that a pixel on a discontinuity becomes a dropout (flying pixel).
    edge_dropout: float = described(
        0.5, "noise: probability that a pixel on a discontinuity drops out", "", (0.0, 1.0)
    )
    # Noise only: dropout probability ramps from 0 at this incidence angle ...
    grazing_start_deg: float = described(
        70.0, "noise: dropouts start at this incidence angle", "degrees", (0.0, 90.0)
    )
    # ... to 1 at this one (structured light loses the pattern at grazing angles).
    grazing_full_deg: float = described(
        85.0, "noise: every pixel drops out from this incidence angle", "degrees", (0.0, 90.0)
    )
    # Returns beyond this range are NaN (the paper's camera: max range 5 m).
    max_range: float = described(
        PAPER_MAX_RANGE, "returns beyond this range are no return (the paper's camera: 5)",
        "metres", (0.01, 1000.0),
    )  # fmt: skip
    # A structured-light or active-stereo camera measures nothing nearer than its minimum range
    # (the projector's pattern and the matcher's disparity range end there): REP 117's -Inf.
    min_range: float = described(
        0.0,
        "nothing nearer than this is measured: such pixels are -Inf (REP 117: too near), no "
        "estimate (0: an ideal camera's)",
        "metres",
        (0.0, 100.0),
    )
    # Depth from disparity: sigma_z = z^2 sigma_d / (f b), so the axial coefficients hold at the
    # focal length they were fitted at (Nguyen et al.: a Kinect, 580 px) and scale by f_ref / f;
    # lateral noise is in pixels of that camera and scales by f / f_ref (`at_focal`). 0 applies
    # them as given at any focal length: the default camera's, with which every result in docs/
    # was measured; the camera presets (`area3d run --camera`) set it.
    reference_focal_px: float = described(
        0.0,
        "focal length the noise coefficients were fitted at: a camera of focal f gets the axial "
        "noise times this / f and the lateral noise in pixels times f / this (0: as given at "
        "any focal length)",
        "pixels",
        (0.0, 1e5),
    )

    def __post_init__(self) -> None:
        positive = {
            "sigma_ref": self.sigma_ref,
            "max_range": self.max_range,
            "edge_jump_rel": self.edge_jump_rel,
        }
        for name, value in positive.items():
            if not (np.isfinite(value) and value > 0):
                raise InputError(name, value, "a finite value > 0")
        nonneg = {
            "sigma_a": self.sigma_a,
            "sigma_b": self.sigma_b,
            "sigma_angle": self.sigma_angle,
            "lateral_l0_px": self.lateral_l0_px,
            "lateral_l1_px": self.lateral_l1_px,
            "incidence_power": self.incidence_power,
        }
        for name, value in nonneg.items():
            if not (np.isfinite(value) and value >= 0):
                raise InputError(name, value, "a finite value >= 0")
        for name, value in (
            ("edge_confidence", self.edge_confidence),
            ("edge_dropout", self.edge_dropout),
        ):
            if not (0.0 <= value <= 1.0):
                raise InputError(name, value, "a value in [0, 1]")
        for name, value, low in (
            ("edge_radius_px", self.edge_radius_px, 0),
            ("normal_smoothing_px", self.normal_smoothing_px, 0),
            ("normal_step_px", self.normal_step_px, 1),
        ):
            if int(value) != value or value < low:
                raise InputError(name, value, f"an integer >= {low}")
        if not (0.0 <= self.min_range < self.max_range):
            raise InputError("min_range", self.min_range, f"[0, max_range={self.max_range}) metres")
        if not (0.0 <= self.grazing_start_deg < self.grazing_full_deg <= 90.0):
            raise InputError(
                "grazing_start_deg/grazing_full_deg",
                (self.grazing_start_deg, self.grazing_full_deg),
                "0 <= start < full <= 90 degrees",
            )

    def at_focal(self, fx: float) -> RgbdSensorParams:
        """The sensor's coefficients for a camera of focal length `fx` pixels: the axial noise
        times reference_focal_px / fx, the lateral noise (pixels) times fx / reference_focal_px
        (itself with reference_focal_px 0)."""
        if self.reference_focal_px == 0 or fx == self.reference_focal_px:
            return self
        if not (np.isfinite(fx) and fx > 0):
            raise InputError("fx", fx, "a focal length > 0 pixels")
        s = self.reference_focal_px / float(fx)
        return replace(
            self,
            sigma_a=self.sigma_a * s,
            sigma_b=self.sigma_b * s,
            sigma_angle=self.sigma_angle * s,
            lateral_l0_px=self.lateral_l0_px / s,
            lateral_l1_px=self.lateral_l1_px / s,
            reference_focal_px=float(fx),
        )


# theta^2 / (pi/2 - theta)^2 diverges at 90 deg; such pixels are dropped as grazing anyway.
MAX_THETA = np.deg2rad(89.0)


def check_depth_and_intrinsics(depth: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Validate a depth image and intrinsics at the boundary; returns (depth float32, K float64)."""
    depth = np.asarray(depth)
    if depth.ndim != 2 or depth.size == 0 or not np.issubdtype(depth.dtype, np.floating):
        raise InputError(
            "depth",
            f"array {depth.dtype} {depth.shape}",
            "a non-empty (H, W) float array in metres",
        )
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise InputError(
            "K", K.tolist() if K.size <= 9 else K.shape, "finite 3x3 intrinsics with fx, fy > 0"
        )
    return depth.astype(np.float32, copy=False), K


def valid_depth_mask(depth: np.ndarray, max_range: float = np.inf) -> np.ndarray:
    """(H, W) bool: finite, > 0 and within `max_range` metres."""
    with np.errstate(invalid="ignore"):
        return np.isfinite(depth) & (depth > 0) & (depth <= max_range)


@njit(cache=True, inline="always")
def axial_sigma_at(z, theta, a, b, z0, c, max_theta):  # pragma: no cover - compiled
    t = min(abs(theta), max_theta)
    r = t / (np.pi / 2 - t)
    return a + b * (z - z0) ** 2 + c / np.sqrt(max(z, 1e-6)) * r * r


@njit(cache=True, error_model="numpy")
def _axial_sigma(z, theta, a, b, z0, c, max_theta):  # pragma: no cover - compiled
    out = np.empty(z.shape, dtype=np.float32)
    for n in range(z.size):
        out[n] = axial_sigma_at(z[n], theta[n], a, b, z0, c, max_theta)
    return out


def axial_sigma(z: np.ndarray, theta: np.ndarray | float, params: RgbdSensorParams) -> np.ndarray:
    """Axial noise standard deviation sigma_z(z, theta) in metres (Nguyen et al. 2012).

    z: depth in metres, theta: incidence angle in radians (an array of z's shape, or a scalar).
    Returns float32 of z's shape.
    """
    z = np.asarray(z, dtype=np.float32)
    if np.isscalar(theta) and theta == 0.0:
        return (params.sigma_a + params.sigma_b * (z - np.float32(params.sigma_z0)) ** 2).astype(
            np.float32
        )
    theta = np.broadcast_to(np.asarray(theta, dtype=np.float32), z.shape)
    sigma = _axial_sigma(
        np.ascontiguousarray(z).reshape(-1),
        np.ascontiguousarray(theta).reshape(-1),
        params.sigma_a,
        params.sigma_b,
        params.sigma_z0,
        params.sigma_angle,
        MAX_THETA,
    )
    return sigma.reshape(z.shape)
