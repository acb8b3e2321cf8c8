"""The renderer's depth is metric z along the optical axis, pixel-exact against MuJoCo ray casts."""

import mujoco
import numpy as np
import pytest

from area3d_msgs_py.camera import intrinsics
from area3d_msgs_py.camera_pose import look_at
from sim_bridge.render import RgbdRenderer
from sim_bridge.scenes import load_scene


def ray_depth(scene, T, K, pixels_uv, max_range):
    """z depth of the first hit through each pixel centre, by mj_ray on the scene model (NaN = none)."""
    model, data = scene.model()
    geomid = np.zeros(1, dtype=np.int32)
    out = []
    for u, v in pixels_uv:
        d_cam = np.array([(u + 0.5 - K[0, 2]) / K[0, 0], (v + 0.5 - K[1, 2]) / K[1, 1], 1.0])
        d_world = T[:3, :3] @ d_cam
        n = np.linalg.norm(d_world)
        dist = mujoco.mj_ray(model, data, T[:3, 3], d_world / n, None, 1, -1, geomid)
        z = dist / n if dist >= 0 else np.nan
        out.append(z if z <= max_range else np.nan)
    return np.array(out)


@pytest.mark.parametrize("name", ["clutter7_a", "living_room"])
def test_depth_matches_ray_casts_through_the_same_pixels(name):
    scene = load_scene(name)
    with RgbdRenderer(scene) as renderer:
        rng = np.random.default_rng(1)
        for T in (scene.initial_views[0], scene.eval_views[5]):
            _, depth = renderer.render(T)
            uv = np.stack([rng.integers(0, 640, 200), rng.integers(0, 480, 200)], 1)
            expected = ray_depth(scene, T, renderer.K, uv, renderer.max_range)
            got = depth[uv[:, 1], uv[:, 0]]
            assert np.array_equal(np.isnan(got), np.isnan(expected))
            assert np.nanmax(np.abs(got - expected)) < 1e-3
            assert np.isfinite(expected).sum() > 80


def test_intrinsics_are_square_pixels_centred_for_a_90_degree_fov():
    K = intrinsics(640, 480, 90.0)
    assert K[0, 0] == pytest.approx(320.0) and K[1, 1] == pytest.approx(320.0)
    assert (K[0, 2], K[1, 2]) == (320.0, 240.0)


def test_a_surface_in_front_of_the_camera_has_positive_depth_at_the_right_pixel():
    scene = load_scene("single_object")
    # Look straight down at the table top from 0.4 m above, off to the side of the object.
    eye = np.array([0.3, -0.2, 0.75 + 0.4])
    T = look_at(eye, eye - [0, 0, 1.0])
    with RgbdRenderer(scene) as renderer:
        rgb, depth = renderer.render(T)
    assert rgb.shape == (480, 640, 3) and rgb.dtype == np.uint8
    assert depth.shape == (480, 640) and depth.dtype == np.float32
    # The centre pixels see the table top 0.4 m below along +z of the optical frame.
    assert depth[238:242, 318:322] == pytest.approx(0.4, abs=1e-4)


def test_optical_frame_axes_map_to_the_image_right_and_down():
    scene = load_scene("single_object")
    top = 0.75
    # Camera above the table's +x edge looking down, image x (right) along world -y.
    eye = np.array([0.45, 0.0, top + 0.3])
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = [0, -1, 0], [-1, 0, 0], [0, 0, -1], eye
    with RgbdRenderer(scene) as renderer:
        _, depth = renderer.render(T)
    # Image "down" is world -x: the lower half sees the table (0.3 m), the upper half
    # looks past the table edge at the floor (0.3 + 0.75 m).
    assert np.nanmedian(depth[300:, 300:340]) == pytest.approx(0.3, abs=1e-3)
    assert np.nanmedian(depth[:180, 300:340]) == pytest.approx(0.3 + top, abs=1e-3)


def test_surfaces_beyond_max_range_are_nan():
    scene = load_scene("living_room")
    T = scene.initial_views[0]
    with RgbdRenderer(scene, max_range=5.0) as far, RgbdRenderer(scene, max_range=1.5) as near:
        _, d_far = far.render(T)
        _, d_near = near.render(T)
    beyond = d_far > 1.5 + 1e-4
    assert beyond.any()
    assert np.all(np.isnan(d_near[beyond]))
    kept = d_far < 1.5 - 1e-4
    assert np.allclose(d_near[kept], d_far[kept], atol=1e-5)


def test_bad_renderer_arguments_are_rejected_with_the_field_name():
    scene = load_scene("single_object")
    with pytest.raises(ValueError, match="hfov_deg"):
        RgbdRenderer(scene, hfov_deg=200.0)
    with pytest.raises(ValueError, match="width"):
        RgbdRenderer(scene, width=0)


@pytest.mark.parametrize("name", ["clutter7_a", "living_room"])
def test_scenes_are_lit_by_their_own_lights_not_a_camera_headlight(name):
    scene = load_scene(name)
    with RgbdRenderer(scene, width=160, height=120) as renderer:
        assert renderer.scene_lit and renderer.model.nlight > 0
        assert np.all(renderer.model.vis.headlight.diffuse == 0)
        assert np.all(renderer.model.vis.headlight.specular == 0)
        assert np.all(renderer.model.vis.headlight.ambient > 0)  # direction-free, kept
        rgb, depth = renderer.render(scene.eval_views[3])
    seen = np.isfinite(depth)
    assert rgb[seen].mean() > 40  # not black
    assert (rgb[seen].max(axis=1) < 10).mean() < 0.05
    with RgbdRenderer(scene, width=160, height=120, camera_headlight=True) as renderer:
        assert not renderer.scene_lit and np.all(renderer.model.vis.headlight.diffuse > 0)
        lit, _ = renderer.render(scene.eval_views[3])
    assert lit[seen].mean() > rgb[seen].mean() + 5  # the headlight did add light before


def test_a_model_without_lights_keeps_its_headlight(tmp_path):
    path = tmp_path / "dark.xml"
    path.write_text(
        '<mujoco><worldbody><geom type="box" size="0.1 0.1 0.1" rgba="0.8 0.8 0.8 1"/>'
        "</worldbody></mujoco>"
    )
    scene = load_scene(path)
    with RgbdRenderer(scene, width=80, height=60) as renderer:
        assert not renderer.scene_lit and np.all(renderer.model.vis.headlight.diffuse > 0)
        rgb, depth = renderer.render(look_at(np.array([0.4, -0.4, 0.3]), np.zeros(3)))
    assert rgb[np.isfinite(depth)].mean() > 60
