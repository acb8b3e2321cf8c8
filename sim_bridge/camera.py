"""The simulated camera: validate a goal pose, render it, add the depth sensor's noise. No transport.

A real depth camera does not return the scene's exact depth: the camera adds the noise of a
Kinect-class structured-light sensor (axial noise growing with range and incidence, lateral jitter
and flying pixels at depth edges, dropouts at grazing angles; `sim_bridge.noise`, on the sensor
description perception's `rgbd` confidence is derived from, `area3d_msgs_py.depth_sensor`) before
anything downstream sees it, and its images carry the read noise of an 8-bit sensor (each pixel and channel, each image of a
stereo pair on its own).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from area3d_msgs_py.camera import PAPER_HFOV_DEG, PAPER_MAX_RANGE, intrinsics
from area3d_msgs_py.depth_sensor import RgbdSensorParams
from sim_bridge.noise import add_depth_noise, draw_depth_noise
from sim_bridge.render import RgbdRenderer
from sim_bridge.scene import Scene
from sim_bridge.validity import CLEARANCE, check_pose

# optical frame in camera_link (x forward, y left, z up): REP 103 rpy (-pi/2, 0, -pi/2).
# 6 cm: a compact robot stereo head (our choice; 5-12 cm is common). With fx = 320 px, depth
# 0.3 m is 64 px of disparity and 5 m is 3.8 px.
STEREO_BASELINE = 0.06
R_LINK_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


@dataclass
class Capture:
    """One handled goal. rgb (H, W, 3) uint8, depth (H, W) float32 metres; None when not ok.
    rgb_right (H, W, 3) uint8: the right image of the rectified stereo pair (None without stereo).
    refusal: why the pose was refused, in a word (`validity.PoseCheck.kind`; "" when ok)."""

    ok: bool
    reason: str
    T_world_cam: np.ndarray
    rgb: np.ndarray | None = None
    depth: np.ndarray | None = None
    rgb_right: np.ndarray | None = None
    refusal: str = ""


def right_from_left(T_world_cam: np.ndarray, baseline: float) -> np.ndarray:
    """(4, 4) pose of the right camera of a rectified pair: the left optical frame moved
    `baseline` metres along its own x axis (to the right in the image)."""
    T_left_right = np.eye(4)
    T_left_right[0, 3] = baseline
    return np.asarray(T_world_cam, dtype=np.float64) @ T_left_right


def link_from_optical(T_world_cam: np.ndarray) -> np.ndarray:
    """(4, 4) T_world_link of `camera_link` (x forward, z up) given the optical-frame pose."""
    T_link_opt = np.eye(4)
    T_link_opt[:3, :3] = R_LINK_OPTICAL
    return T_world_cam @ np.linalg.inv(T_link_opt)


class SimCamera:
    """Validates goal poses against the scene and renders the valid ones.

    The renderer is created on the first capture, so its OpenGL context belongs to the thread that
    captures (the node's spin thread). stereo_baseline > 0 (metres) renders a second, right image
    from the left pose shifted along the optical x axis: a rectified pair with the same K; 0 = mono.
    Only the left pose is checked for clearance (the right camera is part of the same body).
    depth_noise: add the depth sensor's noise (`sensor`, default a Kinect-class camera) to every
    depth image, drawn from a generator seeded with `seed` (repeatable episodes); False returns
    the renderer's exact depth (ground truth for benchmarks). image_noise: standard deviation of
    the Gaussian read noise added to every colour image, grey levels (0 = the exact rendering).
    noise_skip: captures whose noise is drawn and dropped after construction and each `reseed`,
    so that a camera started for a resumed episode goes on with the noise of the episode's next
    capture, as the camera of the episode never stopped would have.
    """

    def __init__(
        self,
        scene: Scene,
        width: int = 640,
        height: int = 480,
        hfov_deg: float = PAPER_HFOV_DEG,
        max_range: float = PAPER_MAX_RANGE,
        clearance: float = CLEARANCE,
        depth_noise: bool = False,
        seed: int = 0,
        stereo_baseline: float = 0.0,
        sensor: RgbdSensorParams | None = None,
        image_noise: float = 0.0,
        noise_skip: int = 0,
    ) -> None:
        if not (np.isfinite(stereo_baseline) and stereo_baseline >= 0):
            raise ValueError(
                f"stereo_baseline: got {stereo_baseline!r}, expected metres >= 0 (0 = no stereo)"
            )
        if not (np.isfinite(image_noise) and image_noise >= 0):
            raise ValueError(f"image_noise: got {image_noise!r}, expected grey levels >= 0")
        self.image_noise = float(image_noise)
        self.stereo_baseline = float(stereo_baseline)
        self.scene = scene
        self.width, self.height, self.hfov_deg, self.max_range = width, height, hfov_deg, max_range
        self.clearance = clearance
        self.depth_noise = bool(depth_noise)
        self.sensor = sensor or RgbdSensorParams(max_range=max_range)
        self.seed = int(seed)
        if not noise_skip >= 0:
            raise ValueError(f"noise_skip: got {noise_skip!r}, expected captures >= 0")
        self.noise_skip = int(noise_skip)
        self.reseed()
        self._renderer: RgbdRenderer | None = None

    def reseed(self) -> None:
        """Start the noise over from `seed`: the captures that follow repeat those after
        construction (a new episode on the same camera)."""
        # one stream for the depth noise, one for the images: neither shifts the other
        depth_seed, image_seed = np.random.SeedSequence(self.seed).spawn(2)
        self._depth_rng = np.random.default_rng(depth_seed)
        self._image_rng = np.random.default_rng(image_seed)
        # the noise of `noise_skip` captures, drawn as `capture` draws it (its draws depend on
        # the image size alone) and dropped
        images = 2 if self.stereo_baseline > 0 else 1
        for _ in range(self.noise_skip):
            if self.depth_noise:
                draw_depth_noise(self._depth_rng, self.height * self.width)
            if self.image_noise > 0:
                for _ in range(images):
                    self._image_rng.standard_normal((self.height, self.width, 3), np.float32)

    @property
    def renderer(self) -> RgbdRenderer:
        if self._renderer is None:
            self._renderer = RgbdRenderer(
                self.scene, self.width, self.height, self.hfov_deg, self.max_range
            )
        return self._renderer

    @property
    def K(self) -> np.ndarray:
        """The renderer's intrinsics, without making the renderer: its GL context is current in
        the thread that makes it, and the node renders in its executor's."""
        return intrinsics(self.width, self.height, self.hfov_deg)

    def capture(self, T_world_cam: np.ndarray) -> Capture:
        """Render at a (4, 4) optical-frame pose, or say why the pose is refused."""
        check = check_pose(self.scene, T_world_cam, self.clearance)
        T = np.asarray(T_world_cam, dtype=np.float64)
        if not check.ok:
            return Capture(False, check.reason, T, refusal=check.kind)
        rgb, depth = self.renderer.render(T)
        if self.depth_noise:
            depth = add_depth_noise(depth, self.K, self._depth_rng, self.sensor)
        rgb_right = None
        if self.stereo_baseline > 0:
            rgb_right, _ = self.renderer.render(right_from_left(T, self.stereo_baseline))
        if self.image_noise > 0:
            rgb = self._read_noise(rgb)
            rgb_right = None if rgb_right is None else self._read_noise(rgb_right)
        return Capture(True, "ok", T, rgb, depth, rgb_right)

    def _read_noise(self, rgb: np.ndarray) -> np.ndarray:
        noise = self._image_rng.standard_normal(rgb.shape, dtype=np.float32)
        noise *= np.float32(self.image_noise)
        return np.clip(np.rint(rgb + noise), 0, 255).astype(np.uint8)

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
