"""The offline analyzer finds the expected kinds of regions on synthetic images and answers in the
VLM's own format."""

import cv2
import numpy as np
import pytest

from area3d_semantics.analysis import analyze_views
from area3d_semantics.backends import HeuristicBackend, NoneBackend
from area3d_semantics.heuristic import analyze_image
from area3d_semantics.parser import parse_answer

H, W = 240, 320


def textured(seed: int = 0) -> np.ndarray:
    """Mid-grey image with blotchy texture: no saturation, no flat patch, few strong edges."""
    rng = np.random.default_rng(seed)
    coarse = rng.integers(70, 190, (H // 6, W // 6, 3)).astype(np.uint8)
    return cv2.resize(coarse, (W, H), interpolation=cv2.INTER_LINEAR)


def cells_of(regions, type_):
    return {(c, r) for c, r, t, *_ in regions if t == type_}


def test_saturated_patch_is_lighting_in_its_cell():
    image = textured()
    image[100:150, 250:300] = 255  # right column (240..320), middle row (80..160)
    regions = analyze_image(image)
    assert regions[0][:3] == ("right", "middle", "LIGHTING")
    assert cells_of(regions, "LIGHTING") == {("right", "middle")}


def test_depth_step_is_occlusion_at_the_step_and_boundary_where_it_meets_the_border():
    image = textured(1)
    depth = np.full((H, W), 2.0, np.float32)
    depth[:, 200:] = 1.0  # vertical occluding edge at x = 200: center-right column (160..240)
    regions = analyze_image(image, depth)
    occlusion = cells_of(regions, "OCCLUSION")
    assert ("center-right", "middle") in occlusion
    assert {c for c, _ in occlusion} == {"center-right"}
    assert regions[0][2] == "OCCLUSION" and regions[0][0] == "center-right"
    assert {c for c, _ in cells_of(regions, "BOUNDARY")} <= {"center-right"}


def test_object_against_no_return_is_an_occluding_contour():
    image = textured(2)
    depth = np.full((H, W), np.nan, np.float32)
    depth[60:180, 40:120] = 1.5  # an object in the left column, nothing behind it
    occlusion = cells_of(analyze_image(image, depth), "OCCLUSION")
    assert occlusion and {c for c, _ in occlusion} <= {"left", "center-left"}


def test_flat_grey_image_is_texture_everywhere_it_reports():
    regions = analyze_image(np.full((H, W, 3), 128, np.uint8))
    assert 5 <= len(regions) <= 8
    assert {t for _, _, t, *_ in regions} == {"TEXTURE"}
    assert regions[0][3] == "HIGH" and regions[0][4] == "large"


def test_dense_thin_stripes_are_geometric():
    image = textured(3)
    image[90:150, 20:140, :] = 60
    image[90:150, 20:140:4, :] = 230  # one-pixel bright lines every 4 px: thin structure
    geometric = cells_of(analyze_image(image), "GEOMETRIC")
    assert ("left", "middle") in geometric


def test_heuristic_answer_parses_back_to_the_same_regions():
    image = textured(4)
    image[10:60, 10:80] = 255
    depth = np.full((H, W), 2.0, np.float32)
    depth[:, 200:] = 1.0
    images, depths = [image, np.full((H, W, 3), 128, np.uint8)], [depth, None]
    answer = HeuristicBackend().analyze(images, depths)
    assert answer.startswith("IMAGE 1\n") and "\nIMAGE 2\n" in answer
    parsed = parse_answer(answer, 2)
    assert not parsed.skipped
    direct = [analyze_image(i, d) for i, d in zip(images, depths, strict=True)]
    for k in range(2):
        assert [(r.column, r.row, r.type, r.priority, r.size) for r in parsed.regions_of(k)] == [
            reg[:5] for reg in direct[k]
        ]


def test_none_backend_gives_no_regions_and_no_fallback():
    analysis = analyze_views(NoneBackend(), [textured()], None)
    assert analysis.regions == [] and analysis.fallback_used is None and analysis.backend == "none"


class Garbage:
    name = "garbage"

    def analyze(self, images, depths=None):
        return "as an AI model I would rather talk about the weather"


class Broken:
    name = "broken"

    def analyze(self, images, depths=None):
        raise RuntimeError("CUDA out of memory")


@pytest.mark.parametrize("backend", [Garbage(), Broken()])
def test_failed_backend_falls_back_to_heuristic_or_zeros(backend):
    images = [np.full((H, W, 3), 128, np.uint8)]
    heuristic = analyze_views(backend, images, fallback="heuristic")
    assert heuristic.fallback_used == "heuristic" and heuristic.error
    assert {r.type for r in heuristic.regions} == {"TEXTURE"}
    zeros = analyze_views(backend, images, fallback="zeros")
    assert zeros.fallback_used == "zeros" and zeros.regions == []
    payload = zeros.to_json([123])
    assert payload["fallback_used"] == "zeros" and payload["images"] == [
        {"stamp_ns": 123, "regions": []}
    ]
