"""Lens distortion: taken out of a camera's images before anything is estimated from them
(`undistortion`, perception), and put into the simulated camera's (`distortion`, sim_bridge).

The graph projects every image with the CameraInfo's `k` as a pinhole camera (perception, the
planner and the reconstruction alike). A driver that publishes raw images with their distortion
(`d` non-zero: plumb_bob, rational_polynomial; a fisheye's equidistant model) has them remapped
here into the pinhole camera `k` itself, as image_proc's rectify does with `R` = I and `P` = `k`:
every node downstream keeps reading `k` from the same CameraInfo, and sees the images it
describes. Colour is interpolated bilinearly; depth takes its nearest pixel, so that no output
depth mixes two surfaces at an edge. Pixels whose source lies outside the raw image have no
estimate (NaN depth, black colour), and whatever a backend makes of them (a depth camera's
pixel without a return may be declared one beyond its range, to be carved free) is taken back:
nothing was measured there.

Only the distortion is taken out: a stereo pair's rectifying rotation (`R`) is not applied, so a
pair must come rectified (stereo_image_proc) as before.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property, lru_cache
from typing import Any

import cv2
import numpy as np

# distortion models OpenCV undistorts, and how many coefficients of `d` each uses
MODELS = {"plumb_bob": 5, "rational_polynomial": 8, "equidistant": 4}
# a coefficient smaller than this is taken as zero (drivers publish 1e-12 for none)
ZERO = 1e-9


@dataclass(frozen=True)
class Remap:
    """A remap of one camera's images between its raw (distorted) pixels and the pinhole camera
    `K` of the same size: each output pixel reads the input at (map_x, map_y)."""

    model: str
    d: tuple[float, ...]
    map_x: np.ndarray  # (H, W) float32: the input image's column of each output pixel
    map_y: np.ndarray

    @cached_property
    def outside(self) -> np.ndarray:
        """(H, W) bool: the output pixels whose ray lands outside the input image (no estimate
        there, whatever a backend makes of a pixel without depth)."""
        return np.isnan(self.depth(np.ones(self.map_x.shape, np.float32)))

    @property
    def size(self) -> tuple[int, int]:
        return self.map_x.shape[1], self.map_x.shape[0]

    def fits(self, image: np.ndarray | None) -> bool:
        """Whether `image` (H x W, or H x W x C) is of this camera's size: one of another size
        is left as it comes, for the node's size check to refuse by name."""
        return image is not None and image.shape[1::-1] == self.size

    def color(self, image: np.ndarray) -> np.ndarray:
        """A colour or grey image, bilinear; black where the input image has no pixel."""
        return cv2.remap(
            image, self.map_x, self.map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
            borderValue=0,
        )  # fmt: skip

    def depth(self, depth: np.ndarray) -> np.ndarray:
        """A float depth image, from the nearest input pixel; NaN (no estimate) where the input
        image has no pixel."""
        return cv2.remap(
            depth.astype(np.float32, copy=False), self.map_x, self.map_y, cv2.INTER_NEAREST,
            borderMode=cv2.BORDER_CONSTANT, borderValue=float("nan"),
        )  # fmt: skip


def _opencv_K(K: np.ndarray) -> np.ndarray:
    """`K` as OpenCV reads it: OpenCV puts pixel centres at integer coordinates, the graph at
    (u + 0.5, v + 0.5) of k."""
    K_cv = np.asarray(K, np.float64).copy()
    K_cv[:2, 2] -= 0.5
    return K_cv


def undistortion(
    K: np.ndarray, width: int, height: int, model: str, d: Any
) -> tuple[Remap | None, str | None]:
    """(the remap for a camera with distortion `model` and coefficients `d`, or None when there
    is none to take out; a note when its images cannot be undistorted). A pinhole model with all
    of `d` zero needs nothing; a model OpenCV has no undistortion for is used as a pinhole
    camera, and the note says so."""
    model = str(model)
    coeffs = [float(v) for v in d]
    if not any(abs(v) > ZERO for v in coeffs):
        if model in ("", *MODELS):
            return None, None
    if model == "":  # coefficients without a model: ROS reads them as plumb_bob
        model = "plumb_bob"
    if model not in MODELS:
        return None, (
            f"camera_info: distortion_model {model!r} with d {[round(v, 4) for v in coeffs]}: "
            f"not one the graph can undistort ({', '.join(MODELS)}); its images are used as a "
            "pinhole camera's: give it rectified images (image_proc) whose intrinsics are k, or "
            "the surfaces land off their place"
        )
    n = MODELS[model]
    if len(coeffs) < n and model == "equidistant":
        return None, (
            f"camera_info: distortion_model 'equidistant' with {len(coeffs)} coefficients in d: "
            "4 expected (k1-k4); its images are used as a pinhole camera's"
        )
    D = np.zeros(n, np.float64)  # the model's own coefficients; missing ones are zero
    D[: min(len(coeffs), n)] = coeffs[:n]
    K_cv = _opencv_K(K)
    size = (int(width), int(height))
    if model == "equidistant":
        map_x, map_y = cv2.fisheye.initUndistortRectifyMap(
            K_cv, D, np.eye(3), K_cv, size, cv2.CV_32FC1
        )
    else:
        map_x, map_y = cv2.initUndistortRectifyMap(K_cv, D, np.eye(3), K_cv, size, cv2.CV_32FC1)
    return Remap(model, tuple(coeffs), map_x, map_y), None


def camera_undistortion(
    K: np.ndarray, width: int, height: int, model: str, d: Any
) -> tuple[Remap | None, str | None]:
    """`undistortion`, made once per camera (the last few kept) and the same `Remap` object
    after: a driver sends its camera info with every frame."""
    K_bytes = np.asarray(K, np.float64).tobytes()
    return _undistortion_of(K_bytes, int(width), int(height), str(model), tuple(map(float, d)))


@lru_cache(maxsize=8)
def _undistortion_of(
    K_bytes: bytes, width: int, height: int, model: str, d: tuple[float, ...]
) -> tuple[Remap | None, str | None]:
    K = np.frombuffer(K_bytes, np.float64).reshape(3, 3)
    return undistortion(K, width, height, model, d)


def distortion(K: np.ndarray, width: int, height: int, d: Any) -> Remap | None:
    """The remap of a pinhole camera `K`'s images into those of a lens with plumb_bob
    coefficients `d` (k1, k2, p1, p2, k3): each raw pixel reads the pinhole image where its ray
    lands (OpenCV's `undistortPoints`, the inverse of `undistortion`'s map); None without
    distortion. What a simulated camera with that lens sends."""
    coeffs = [float(v) for v in d]
    if len(coeffs) != MODELS["plumb_bob"]:
        raise ValueError(f"d: got {len(coeffs)} coefficients, expected 5 (k1, k2, p1, p2, k3)")
    if not any(abs(v) > ZERO for v in coeffs):
        return None
    K_cv = _opencv_K(K)
    v, u = np.mgrid[0:height, 0:width]
    raw = np.stack([u, v], -1).reshape(-1, 1, 2).astype(np.float64)
    pinhole = cv2.undistortPoints(raw, K_cv, np.array(coeffs), P=K_cv).reshape(height, width, 2)
    return Remap(
        "plumb_bob", tuple(coeffs), pinhole[..., 0].astype(np.float32),
        pinhole[..., 1].astype(np.float32),
    )  # fmt: skip
