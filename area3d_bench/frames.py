"""Views of a bundled scene rendered once for the benchmarks, so that rendering does not compete
with what is measured."""

from __future__ import annotations

from typing import Any


def render_views(
    scene_name: str, width: int = 640, height: int = 480, held_out: bool = False
) -> tuple[Any, list]:
    """The scene and its initial views (with `held_out`: then its held-out views) rendered at
    width x height: [(rgb (H, W, 3) uint8, depth (H, W) float32 metres, K (3, 3), T (4, 4))]."""
    from sim_bridge.render import RgbdRenderer
    from sim_bridge.scenes import load_scene

    scene = load_scene(scene_name)
    poses = [*scene.initial_views, *(scene.eval_views if held_out else [])]
    renderer = RgbdRenderer(scene, width=width, height=height)
    try:
        frames = []
        for T in poses:
            rgb, depth = renderer.render(T)
            frames.append((rgb, depth, renderer.K, T))
    finally:
        renderer.close()
    return scene, frames


def object_frames(scene_name: str = "single_object") -> tuple[Any, list]:
    """The scene and its initial views at 640x480: [(depth, confidence, K, T)], with the RGB-D
    sensor model's confidence."""
    from area3d_perception.sensor_model import rgbd_confidence

    scene, frames = render_views(scene_name)
    return scene, [(d, rgbd_confidence(d, K), K, T) for _, d, K, T in frames]
