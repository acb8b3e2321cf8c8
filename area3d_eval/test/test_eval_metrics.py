"""Surface and image metrics on cases whose answer is known analytically."""

import math

import cv2
import numpy as np
import pytest
import trimesh

from area3d_eval.metrics import (
    ReferenceSurface,
    psnr,
    sample_surface,
    ssim,
    ssim_map,
    surface_metrics,
)
from area3d_eval.render import render_mesh
from area3d_msgs_py.errors import InputError

TAU = 0.01


def plane(size: float = 0.2, z: float = 0.0) -> trimesh.Trimesh:
    h = size / 2
    v = np.array([[-h, -h, z], [h, -h, z], [h, h, z], [-h, h, z]], float)
    return trimesh.Trimesh(v, [[0, 1, 2], [0, 2, 3]], process=False)


def test_mesh_compared_with_itself_is_complete_and_accurate():
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.1)
    m = surface_metrics(sphere, sphere, TAU, num_points=20_000)
    assert m["completion"] == 1.0 and m["precision"] == 1.0 and m["fscore"] == 1.0
    # two independent samples of one surface are ~point spacing apart (0.13 m^2 / 20k -> ~2.5 mm)
    assert m["accuracy"] < 0.002 and m["completeness"] < 0.002
    assert m["chamfer"] == pytest.approx(0.5 * (m["accuracy"] + m["completeness"]))


def test_surface_shifted_along_its_normal_is_that_far_away():
    d = 0.03
    m = surface_metrics(plane(z=d), plane(z=0.0), TAU, num_points=20_000)
    assert m["accuracy"] == pytest.approx(d, abs=1e-3)
    assert m["completeness"] == pytest.approx(d, abs=1e-3)
    assert m["chamfer"] == pytest.approx(d, abs=1e-3)
    assert m["completion"] == 0.0 and m["fscore"] == 0.0  # d > tau everywhere


def test_shift_below_tau_keeps_full_completion():
    # 20k points on 0.04 m^2: ~1.4 mm spacing, so the nearest point is within 4 mm + spacing < tau
    m = surface_metrics(plane(z=0.004), plane(), TAU, num_points=20_000)
    assert m["completion"] == 1.0 and m["fscore"] == 1.0


def test_half_the_surface_missing_halves_completion_not_precision():
    gt = trimesh.creation.icosphere(subdivisions=5, radius=0.1)
    upper = gt.submesh([np.flatnonzero(gt.triangles_center[:, 2] > 0)], append=True)
    m = surface_metrics(upper, gt, TAU, num_points=30_000)
    # points of the lower half within tau of the equator still count: a band of ~tau / (pi r / 2)
    assert m["completion"] == pytest.approx(0.5 + 0.5 * TAU / (math.pi * 0.1 / 2), abs=0.03)
    assert m["precision"] == 1.0


def test_empty_reconstruction_scores_zero_and_infinite_distance():
    m = surface_metrics(trimesh.Trimesh(), plane(), TAU, num_points=1000)
    assert m["completion"] == 0.0 and m["fscore"] == 0.0 and m["precision"] == 0.0
    assert m["completeness"] == math.inf and m["chamfer"] == math.inf
    assert math.isnan(m["accuracy"])


def test_surface_sampling_is_uniform_by_area():
    # two triangles, one with 3x the area of the other: 3/4 of the points land on it
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [10, 0, 0], [13, 0, 0], [10, 1, 0]], float)
    pts = sample_surface(v, np.array([[0, 1, 2], [3, 4, 5]]), 40_000, seed=3)
    assert np.mean(pts[:, 0] >= 10) == pytest.approx(0.75, abs=0.01)
    on_first = pts[pts[:, 0] < 10]
    assert np.all(on_first[:, 0] + on_first[:, 1] <= 1 + 1e-9)  # inside the triangle


def test_bad_tau_is_rejected_with_its_name():
    with pytest.raises(InputError, match="tau"):
        surface_metrics(plane(), plane(), 0.0, num_points=100)


def test_psnr_of_identical_images_is_infinite():
    img = np.random.default_rng(0).integers(0, 256, (20, 30, 3), dtype=np.uint8)
    assert psnr(img, img) == math.inf


def test_psnr_of_a_known_error_follows_the_definition():
    a = np.full((16, 16, 3), 100, np.uint8)
    b = a.copy()
    b[::2] += 10  # half the rows off by 10, the rest exact: MSE = 50
    assert psnr(a, b) == pytest.approx(10 * math.log10(255**2 / 50.0))
    mask = np.zeros((16, 16), bool)
    mask[::2] = True  # only the rows that are off: MSE = 100
    assert psnr(a, b, mask) == pytest.approx(10 * math.log10(255**2 / 100.0))


def test_psnr_rejects_images_of_different_shapes():
    with pytest.raises(InputError, match="b"):
        psnr(np.zeros((4, 4, 3)), np.zeros((4, 5, 3)))


def _image_pairs():
    """(reference, distorted) pairs: noise at three levels, a shift, a blur, a gain, grey and
    colour, and an image compared with itself."""
    rng = np.random.default_rng(1)
    ramp = (np.add.outer(np.arange(48), np.arange(64)) * 3 % 256).astype(np.uint8)
    texture = rng.integers(0, 256, (48, 64, 3), dtype=np.uint8)
    smooth = cv2.GaussianBlur(texture, (7, 7), 2.0)
    pairs = []
    for sigma in (2, 10, 40):
        noisy = np.clip(smooth + rng.normal(0, sigma, smooth.shape), 0, 255).astype(np.uint8)
        pairs.append(pytest.param(smooth, noisy, id=f"noise{sigma}"))
    pairs += [
        pytest.param(smooth, np.roll(smooth, 2, axis=1), id="shift"),
        pytest.param(texture, cv2.GaussianBlur(texture, (5, 5), 1.0), id="blur"),
        pytest.param(ramp, np.clip(ramp * 0.8 + 20, 0, 255).astype(np.uint8), id="gain-grey"),
        pytest.param(texture, texture, id="identical"),
    ]
    return pairs


def reference_ssim_map(a: np.ndarray, b: np.ndarray, data_range: float = 255.0) -> np.ndarray:
    """SSIM of Wang et al. 2004 per pixel as the paper writes it, in float64: 11 x 11 Gaussian
    window of sigma 1.5 (OpenCV's), mirrored at the border, population (co)variances, K1 0.01,
    K2 0.03; averaged over channels."""
    fa, fb = np.atleast_3d(a).astype(np.float64), np.atleast_3d(b).astype(np.float64)

    def blur(x):
        return np.stack(
            [
                cv2.GaussianBlur(x[..., c], (11, 11), 1.5, borderType=cv2.BORDER_REFLECT)
                for c in range(x.shape[-1])
            ],
            axis=-1,
        )

    mu_a, mu_b = blur(fa), blur(fb)
    var_a, var_b = blur(fa * fa) - mu_a**2, blur(fb * fb) - mu_b**2
    cov = blur(fa * fb) - mu_a * mu_b
    c1, c2 = (0.01 * data_range) ** 2, (0.03 * data_range) ** 2
    s = ((2 * mu_a * mu_b + c1) * (2 * cov + c2)) / (
        (mu_a**2 + mu_b**2 + c1) * (var_a + var_b + c2)
    )
    return s.mean(axis=-1)


@pytest.mark.parametrize(("a", "b"), _image_pairs())
def test_psnr_and_ssim_follow_their_definitions(a, b):
    """PSNR is 10 log10(255^2 / MSE) over all pixels or a mask's; SSIM is the Wang et al. 2004
    map written out above, its mean taken over the pixels at least a window radius from the
    border, or over a mask's."""
    mask = np.zeros(a.shape[:2], bool)
    mask[10:30, 5:40] = True  # a region's pixels: the mean of the same map over them
    error = (a.astype(np.float64) - b) ** 2
    for m, mse in ((None, error.mean()), (mask, error[mask].mean())):
        expected = math.inf if mse == 0 else 10 * math.log10(255**2 / mse)
        assert psnr(a, b, m) == pytest.approx(expected, rel=1e-9)
    full = reference_ssim_map(a, b)
    r = 5  # the window radius
    np.testing.assert_allclose(ssim_map(a, b), full, atol=1e-9)
    assert ssim(a, b) == pytest.approx(full[r:-r, r:-r].mean(), abs=1e-9)
    assert ssim(a, b, mask) == pytest.approx(full[mask].mean(), abs=1e-9)


def test_image_metrics_refuse_what_they_cannot_measure():
    with pytest.raises(InputError, match="^b: "):
        ssim(np.zeros((16, 16, 3), np.uint8), np.zeros((16, 17, 3), np.uint8))
    with pytest.raises(InputError, match="^a: .*11 x 11"):
        ssim(np.zeros((8, 16), np.uint8), np.zeros((8, 16), np.uint8))
    with pytest.raises(InputError, match="^mask: "):
        psnr(np.zeros((16, 16)), np.ones((16, 16)), np.ones((4, 4), bool))
    assert math.isnan(psnr(np.zeros((16, 16)), np.ones((16, 16)), np.zeros((16, 16), bool)))
    assert math.isnan(ssim(np.zeros((16, 16)), np.ones((16, 16)), np.zeros((16, 16), bool)))


def test_ssim_decreases_as_noise_grows():
    rng = np.random.default_rng(2)
    img = (
        (np.add.outer(np.arange(64), np.arange(64)) * 2 % 256)
        .astype(np.uint8)[..., None]
        .repeat(3, 2)
    )
    scores = []
    for sigma in (2, 10, 40):
        noisy = np.clip(img + rng.normal(0, sigma, img.shape), 0, 255).astype(np.uint8)
        scores.append(ssim(img, noisy))
    assert 1.0 > scores[0] > scores[1] > scores[2]


def test_ssim_of_flat_images_is_the_luminance_term():
    # no variance: contrast and structure terms are 1, SSIM = (2 mu_a mu_b + c1) / (mu_a^2 + mu_b^2 + c1)
    a, b = np.full((32, 32), 100, np.uint8), np.full((32, 32), 140, np.uint8)
    c1 = (0.01 * 255) ** 2
    assert ssim(a, b) == pytest.approx((2 * 100 * 140 + c1) / (100**2 + 140**2 + c1))


def test_completion_does_not_fall_when_the_reconstruction_grows_elsewhere():
    # The same surface plus a large patch far away: a fixed-size sample of the reconstruction
    # would spread thinner over the plane and lose GT points; the exact distance does not.
    gt = plane()
    far = trimesh.creation.box(extents=[3.0, 3.0, 0.01])
    far.apply_translation([0.0, 0.0, 2.0])
    alone = surface_metrics(gt, gt, TAU, num_points=2000)
    grown = surface_metrics(trimesh.util.concatenate([gt, far]), gt, TAU, num_points=2000)
    assert alone["completion"] == 1.0 and grown["completion"] == 1.0
    assert grown["completeness"] < 1e-6


def test_surface_sample_does_not_depend_on_the_order_of_the_triangles():
    mesh = trimesh.creation.icosphere(subdivisions=2, radius=0.1)
    rng = np.random.default_rng(0)
    faces = mesh.faces[rng.permutation(len(mesh.faces))]
    faces = np.roll(faces, 1, axis=1)  # same triangles, same orientation, other first corner
    perm = rng.permutation(len(mesh.vertices))  # and the vertices listed in another order
    inverse = np.argsort(perm)
    a = sample_surface(mesh.vertices, mesh.faces, 500, seed=3)
    b = sample_surface(mesh.vertices[perm], inverse[faces], 500, seed=3)
    assert np.allclose(a, b)


def _listed_otherwise(vertices: np.ndarray, faces: np.ndarray, seed: int = 1):
    """The same mesh with its vertices and triangles in another order and each triangle starting
    at another corner (as Open3D's multi-threaded extraction lists a surface from run to run)."""
    rng = np.random.default_rng(seed)
    perm = rng.permutation(len(vertices))
    inverse = np.argsort(perm)
    faces = np.roll(faces[rng.permutation(len(faces))], 1, axis=1)
    return vertices[perm], inverse[faces], perm


def test_metrics_do_not_depend_on_the_order_the_reconstruction_lists_its_triangles_in():
    gt = trimesh.creation.icosphere(subdivisions=4, radius=0.1)
    recon = trimesh.creation.icosphere(subdivisions=3, radius=0.1)
    recon.vertices += np.random.default_rng(0).normal(0.0, 0.002, recon.vertices.shape)
    vertices, faces, _ = _listed_otherwise(recon.vertices, recon.faces)
    other = trimesh.Trimesh(vertices, faces, process=False)
    reference = ReferenceSurface(gt, 50_000)
    # bit for bit: the same frames must give the same table wherever and however often evaluated
    assert reference.compare(recon, TAU) == reference.compare(other, TAU)


def test_a_render_does_not_depend_on_the_order_the_mesh_lists_its_triangles_in():
    mesh = trimesh.creation.icosphere(subdivisions=3, radius=0.1)
    colours = np.random.default_rng(2).integers(0, 255, (len(mesh.vertices), 3), dtype=np.uint8)
    mesh.visual.vertex_colors = np.c_[colours, np.full(len(colours), 255, np.uint8)]
    vertices, faces, perm = _listed_otherwise(mesh.vertices, mesh.faces)
    other = trimesh.Trimesh(vertices, faces, process=False)
    other.visual.vertex_colors = mesh.visual.vertex_colors[perm]
    K = np.array([[80.0, 0, 40], [0, 80.0, 30], [0, 0, 1]])
    T = np.eye(4)
    T[2, 3] = -0.4  # looking along +z at the sphere
    rgb_a, depth_a = render_mesh(mesh, K, T, 80, 60)
    rgb_b, depth_b = render_mesh(other, K, T, 80, 60)
    assert np.isfinite(depth_a).mean() > 0.2 and rgb_a[np.isfinite(depth_a)].max() > 0
    np.testing.assert_array_equal(depth_a, depth_b)
    np.testing.assert_array_equal(rgb_a, rgb_b)
