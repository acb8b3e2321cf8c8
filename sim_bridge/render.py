"""Offscreen RGB-D rendering of a scene at an optical-frame camera pose (MuJoCo, headless OpenGL)."""

from __future__ import annotations

import os

import mujoco
import numpy as np

from area3d_msgs_py.camera import PAPER_HFOV_DEG, PAPER_MAX_RANGE, intrinsics
from sim_bridge.scene import Scene

ZNEAR = 0.01  # metres, near clipping plane: closer surfaces are not seen
CAMERA_NAME = "area3d_optical"
# MuJoCo cameras look along -z with y up; the optical frame looks along +z with y down.
MJ_FROM_OPTICAL = np.diag([1.0, -1.0, -1.0])


def _gl_context(width: int, height: int):
    """A current offscreen OpenGL context from the backend in MUJOCO_GL, else EGL, then OSMesa."""
    errors = []
    requested = os.environ.get("MUJOCO_GL", "egl").lower()
    for backend in dict.fromkeys([requested, "egl", "osmesa"]):
        try:
            if backend == "egl":
                from mujoco.egl import GLContext
            elif backend == "osmesa":
                from mujoco.osmesa import GLContext
            else:
                from mujoco.glfw import GLContext
            ctx = GLContext(width, height)
            ctx.make_current()
            return ctx
        except Exception as exc:  # noqa: BLE001  (any failure means: try the next backend)
            errors.append(f"{backend}: {exc}")
    raise RuntimeError(
        "MUJOCO_GL: no headless OpenGL backend works ("
        + "; ".join(errors)
        + "). Install EGL (libegl1 + a Mesa or GPU driver) or OSMesa (libosmesa6) and set MUJOCO_GL=egl or osmesa."
    )


class RgbdRenderer:
    """Renders (rgb, depth) of a scene at a T_world_cam optical-frame pose.

    K follows the shared convention: square pixels, principal point at the image centre. Depth is
    metres along the optical z axis, NaN where nothing was hit or beyond `max_range`.

    Lighting: MuJoCo's headlight is mounted on the camera, so its diffuse and specular light make a
    surface's colour change with the viewing direction, which no fused colour map can reproduce at
    a held-out view. When the model has lights of its own and `camera_headlight` is False (the
    default), the headlight's diffuse and specular parts are switched off and the scene is lit by
    its own lights plus the headlight's ambient term (the same from every direction).
    `scene_lit` says whether that happened; a model without lights keeps its full headlight.
    """

    def __init__(
        self,
        scene: Scene,
        width: int = 640,
        height: int = 480,
        hfov_deg: float = PAPER_HFOV_DEG,
        max_range: float = PAPER_MAX_RANGE,
        camera_headlight: bool = False,
    ) -> None:
        if not (isinstance(width, int | np.integer) and width > 0):
            raise ValueError(f"width: got {width!r}, expected a positive integer (pixels)")
        if not (isinstance(height, int | np.integer) and height > 0):
            raise ValueError(f"height: got {height!r}, expected a positive integer (pixels)")
        if not (0.0 < hfov_deg < 180.0):
            raise ValueError(f"hfov_deg: got {hfov_deg!r}, expected degrees in (0, 180)")
        if not (max_range > ZNEAR):
            raise ValueError(f"max_range: got {max_range!r}, expected metres > {ZNEAR}")
        self.scene = scene
        self.width, self.height = int(width), int(height)
        self.max_range = float(max_range)
        self.K = intrinsics(self.width, self.height, hfov_deg)
        fovy = 2 * np.degrees(np.arctan((self.height / 2) / self.K[1, 1]))

        spec = mujoco.MjSpec.from_file(str(scene.mjcf_path))
        spec.visual.global_.offwidth = max(self.width, spec.visual.global_.offwidth)
        spec.visual.global_.offheight = max(self.height, spec.visual.global_.offheight)
        spec.worldbody.add_camera(name=CAMERA_NAME, fovy=fovy)
        self.model = spec.compile()
        self.scene_lit = not camera_headlight and self.model.nlight > 0
        if self.scene_lit:
            self.model.vis.headlight.diffuse[:] = 0.0
            self.model.vis.headlight.specular[:] = 0.0
        extent = self.model.stat.extent
        self.model.vis.map.znear = ZNEAR / extent
        self.model.vis.map.zfar = 2.0 * max(self.max_range, 1.0) / extent
        self.data = mujoco.MjData(self.model)
        mujoco.mj_forward(self.model, self.data)
        self._cam_id = self.model.camera(CAMERA_NAME).id

        self._gl = _gl_context(self.width, self.height)
        self._ctx = mujoco.MjrContext(self.model, mujoco.mjtFontScale.mjFONTSCALE_150.value)
        mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN.value, self._ctx)
        self._ctx.readDepthMap = mujoco.mjtDepthMap.mjDEPTH_ZEROFAR
        self._scene = mujoco.MjvScene(self.model, maxgeom=10000)
        self._option = mujoco.MjvOption()
        self._camera = mujoco.MjvCamera()
        self._camera.type = mujoco.mjtCamera.mjCAMERA_FIXED
        self._camera.fixedcamid = self._cam_id
        self._rect = mujoco.MjrRect(0, 0, self.width, self.height)
        self._rgb = np.empty((self.height, self.width, 3), dtype=np.uint8)
        self._zbuf = np.empty((self.height, self.width), dtype=np.float32)

    def render(self, T_world_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """rgb (H, W, 3) uint8 and depth (H, W) float32 metres (NaN = no return) at the pose.

        T_world_cam: (4, 4) pose of the camera optical frame (z forward, x right, y down) in world.
        """
        if self._ctx is None:
            raise RuntimeError("render called after close()")
        T = np.asarray(T_world_cam, dtype=np.float64)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise ValueError(f"T_world_cam: got shape {T.shape}, expected a finite (4, 4) pose")
        self.data.cam_xpos[self._cam_id] = T[:3, 3]
        self.data.cam_xmat[self._cam_id] = (T[:3, :3] @ MJ_FROM_OPTICAL).ravel()
        self._gl.make_current()
        mujoco.mjv_updateScene(
            self.model,
            self.data,
            self._option,
            None,
            self._camera,
            mujoco.mjtCatBit.mjCAT_ALL.value,
            self._scene,
        )
        mujoco.mjr_render(self._rect, self._scene, self._ctx)
        mujoco.mjr_readPixels(self._rgb, self._zbuf, self._rect, self._ctx)
        rgb = np.ascontiguousarray(self._rgb[::-1])
        return rgb, self._linear_depth(self._zbuf[::-1])

    def _linear_depth(self, zbuf: np.ndarray) -> np.ndarray:
        # Reverse-Z projection (MuJoCo's default): window depth 1 at the near plane, 0 at the far
        # plane; invert it in float64 as mujoco.Renderer does.
        extent = self.model.stat.extent
        near = np.float32(self.model.vis.map.znear * extent)
        far = np.float32(self.model.vis.map.zfar * extent)
        c = np.float64(near) / (np.float64(far) - np.float64(near))
        d = np.float64(far) * np.float64(near) / (np.float64(far) - np.float64(near))
        z = zbuf.astype(np.float64)
        with np.errstate(divide="ignore"):
            depth = d / (z + c)
        depth[(zbuf <= 0.0) | (depth > self.max_range) | (depth >= far * 0.999)] = np.nan
        return depth.astype(np.float32)

    def close(self) -> None:
        """Free the OpenGL resources; the renderer cannot render afterwards."""
        if self._ctx is not None:
            self._gl.make_current()
            self._ctx.free()
            self._ctx = None
            self._gl.free()

    def __enter__(self) -> RgbdRenderer:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __del__(self) -> None:
        try:
            self.close()
        except Exception:  # noqa: BLE001  (interpreter shutdown: GL may already be gone)
            pass
