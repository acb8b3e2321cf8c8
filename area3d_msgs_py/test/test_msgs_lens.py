"""Lens distortion taken out (`area3d_msgs_py.lens`): each output pixel of the pinhole
camera k reads the raw image where the lens put its ray, by the models' own formulas with the
graph's pixel centres (u + 0.5, v + 0.5); what cannot be undistorted is said."""

import numpy as np
import pytest

from area3d_msgs_py.lens import undistortion

H, W = 60, 80
K = np.array([[70.0, 0, 41.0], [0, 68.0, 29.5], [0, 0, 1]])


def rays():
    """The normalised image coordinates of every output pixel's centre."""
    v, u = np.mgrid[0:H, 0:W]
    return (u + 0.5 - K[0, 2]) / K[0, 0], (v + 0.5 - K[1, 2]) / K[1, 1]


def to_index(xd, yd):
    """A distorted normalised point as the raw image's (column, row) array index."""
    return K[0, 0] * xd + K[0, 2] - 0.5, K[1, 1] * yd + K[1, 2] - 0.5


@pytest.mark.parametrize(
    ("model", "d"),
    [
        ("plumb_bob", [-0.28, 0.09, 0.0012, -0.0008, -0.01]),
        ("rational_polynomial", [0.5, -0.1, 0.001, 0.002, 0.01, 0.8, -0.05, 0.02]),
    ],
)
def test_each_pixel_reads_the_raw_image_where_the_brown_conrady_lens_put_its_ray(model, d):
    remap, note = undistortion(K, W, H, model, d)
    assert note is None and remap.model == model and remap.size == (W, H)
    x, y = rays()
    k1, k2, p1, p2, k3, *rest = d
    k4, k5, k6 = rest or (0.0, 0.0, 0.0)
    r2 = x * x + y * y
    radial = (1 + k1 * r2 + k2 * r2**2 + k3 * r2**3) / (1 + k4 * r2 + k5 * r2**2 + k6 * r2**3)
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    col, row = to_index(xd, yd)
    np.testing.assert_allclose(remap.map_x, col, atol=1e-3)
    np.testing.assert_allclose(remap.map_y, row, atol=1e-3)


def test_each_pixel_reads_the_raw_image_where_the_fisheye_put_its_ray():
    d = [0.05, -0.01, 0.002, -0.0005]
    remap, note = undistortion(K, W, H, "equidistant", d)
    assert note is None
    x, y = rays()
    r = np.hypot(x, y)
    theta = np.arctan(r)
    theta_d = theta * (1 + sum(k * theta ** (2 * i + 2) for i, k in enumerate(d)))
    scale = np.where(r > 0, theta_d / np.where(r > 0, r, 1), 1.0)
    col, row = to_index(x * scale, y * scale)
    np.testing.assert_allclose(remap.map_x, col, atol=1e-3)
    np.testing.assert_allclose(remap.map_y, row, atol=1e-3)


def test_images_are_remapped_bilinear_for_colour_and_nearest_for_depth_with_nothing_outside():
    # pincushion: the rays of the output's corners land outside the raw image
    remap, _ = undistortion(K, W, H, "plumb_bob", [0.35, 0.12, 0, 0, 0])
    grey = np.full((H, W), 200, np.uint8)
    out = remap.color(grey)
    assert out[H // 2, W // 2] == 200 and out[0, 0] == 0
    colour = remap.color(np.dstack([grey, grey // 2, grey // 4]))
    assert colour.shape == (H, W, 3) and tuple(colour[H // 2, W // 2]) == (200, 100, 50)
    depth = np.where(np.arange(W) < W // 2, 1.0, 3.0).astype(np.float32)[None].repeat(H, 0)
    undistorted = remap.depth(depth)
    assert np.isnan(undistorted[0, 0])
    finite = undistorted[np.isfinite(undistorted)]
    assert set(np.unique(finite)) == {1.0, 3.0}  # no depth between the two surfaces


def test_no_distortion_needs_no_remap_and_what_cannot_be_undistorted_is_said():
    assert undistortion(K, W, H, "plumb_bob", [0.0] * 5) == (None, None)
    assert undistortion(K, W, H, "", []) == (None, None)
    assert undistortion(K, W, H, "equidistant", [1e-12] * 4) == (None, None)
    # coefficients without a model are plumb_bob's, as ROS reads them
    remap, note = undistortion(K, W, H, "", [0.1, 0, 0, 0, 0])
    assert note is None and remap.model == "plumb_bob"
    remap, note = undistortion(K, W, H, "kannala_brandt_8", [0.1])
    assert remap is None and "'kannala_brandt_8'" in note and "plumb_bob" in note
    remap, note = undistortion(K, W, H, "equidistant", [0.1, 0.2])
    assert remap is None and "4 expected" in note


def test_a_pinhole_image_sent_through_a_lens_and_undistorted_again_comes_back():
    """`distortion` (the simulated camera's lens) and `undistortion` (perception's) are inverse
    maps: a smooth pinhole image, distorted and undistorted again, is itself where the raw image
    covers it, and was not in between."""
    from area3d_msgs_py.lens import distortion

    d = [-0.25, 0.08, 0.001, -0.001, 0.0]
    v, u = np.mgrid[0:H, 0:W]
    image = (128 + 60 * np.sin(u / 5.0) * np.cos(v / 7.0)).astype(np.uint8)
    lens = distortion(K, W, H, d)
    raw = lens.color(image)
    back = undistortion(K, W, H, "plumb_bob", d)[0].color(raw)
    inner = (slice(6, H - 6), slice(6, W - 6))
    error = np.abs(back.astype(float) - image)[inner]
    assert np.median(error) <= 1.0 and error.max() <= 8.0
    assert np.mean(np.abs(raw.astype(float) - image)[inner]) > 4 * np.mean(error)
    # the maps themselves are inverse: where a pinhole pixel reads the raw image, the raw image
    # reads that pinhole pixel
    remap = undistortion(K, W, H, "plumb_bob", d)[0]
    np.testing.assert_allclose(remap.color(lens.map_x)[inner], u[inner], atol=0.02)
    np.testing.assert_allclose(remap.color(lens.map_y)[inner], v[inner], atol=0.02)
    assert distortion(K, W, H, [0.0] * 5) is None
    with pytest.raises(ValueError, match="expected 5"):
        distortion(K, W, H, [0.1, 0.0])


def test_a_camera_sending_the_same_camera_info_gets_the_same_remap_made_once():
    from area3d_msgs_py.lens import camera_undistortion

    d = [-0.2, 0.05, 0.0, 0.0, 0.0]
    first, note = camera_undistortion(K, W, H, "plumb_bob", d)
    again, _ = camera_undistortion(K.copy(), W, H, "plumb_bob", list(d))
    assert note is None and again is first  # a driver sends its camera info every frame
    other, _ = camera_undistortion(K, W, H, "plumb_bob", [-0.1, 0.0, 0.0, 0.0, 0.0])
    assert other is not first and not np.array_equal(other.map_x, first.map_x)
    assert camera_undistortion(K, W, H, "plumb_bob", [0.0] * 5) == (None, None)
