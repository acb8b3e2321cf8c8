"""Region masks, weight maps and the semantic uncertainty follow the paper's definitions."""

import numpy as np
import pytest

from area3d_msgs_py.errors import InputError
from area3d_semantics.masks import cell_bounds, region_mask
from area3d_semantics.region import COLUMNS, ROWS, Region
from area3d_semantics.weights import (
    SemanticParams,
    semantic_uncertainty,
    sigma_from_confidence,
    weight_map,
    weight_maps,
)

H, W = 480, 640


def region(
    column="center-left", row="middle", type_="OCCLUSION", priority="HIGH", size="medium", image=0
):
    return Region(image, column, row, type_, priority, size, "")


@pytest.mark.parametrize("column", COLUMNS)
@pytest.mark.parametrize("row", ROWS)
def test_mask_peaks_inside_its_cell_and_is_low_far_away(column, row):
    mask = region_mask(region(column, row), H, W)
    x0, x1, y0, y1 = cell_bounds(column, row)
    inside = mask[int(y0 * H) : int(y1 * H), int(x0 * W) : int(x1 * W)]
    assert inside.min() == pytest.approx(1.0)
    assert mask.max() == pytest.approx(1.0) and mask.min() >= 0.0
    # Two cells away the taper has died out.
    far_col = (COLUMNS.index(column) + 2) % 4
    cx = int((far_col + 0.5) * W / 4)
    assert mask[int((y0 + y1) / 2 * H), cx] < 1e-3


def test_mask_dilation_is_mild_and_the_taper_is_smooth():
    mask = region_mask(region("center-left", "middle"), H, W, dilation=0.1, taper_sigma=0.15)
    row = mask[H // 2]
    cell_w = W / 4
    # Full weight reaches 10% of a cell beyond the edge, no further.
    assert row[int(cell_w * 2 + 0.1 * cell_w) - 2] == pytest.approx(1.0)
    assert row[int(cell_w * 2 + 0.1 * cell_w) + 3] < 1.0
    # The neighbouring cell's centre gets only a few percent.
    assert row[int(2.5 * cell_w)] < 0.05
    # Smooth: no jump between neighbouring pixels larger than the Gaussian's steepest slope.
    sigma_px = 0.15 * cell_w
    assert np.abs(np.diff(row)).max() <= 1.0 / (sigma_px * np.sqrt(np.e)) + 1e-3
    assert np.all(
        np.diff(row[: int(1.5 * cell_w)]) >= -1e-7
    )  # rises monotonically towards the cell


def test_without_dilation_the_mask_stops_at_the_cell_edge():
    mask = region_mask(region("left", "top"), H, W, dilation=0.0, taper_sigma=0.0)
    assert mask[:160, :160].min() == 1.0
    assert mask[:, 161:].max() == 0.0 and mask[161:, :].max() == 0.0


def test_the_default_tables_are_the_papers_and_the_prompts_ranking():
    params = SemanticParams()
    # paper, supplement Table 6
    assert params.beta == {"HIGH": 3.0, "MEDIUM": 1.5, "LOW": 0.5}
    assert params.s == {"small": 0.8, "medium": 1.0, "large": 1.2}
    assert params.lam == 1.0
    # not published: the prompt's order, most important first, never rising
    alpha = [params.alpha[t] for t in ("OCCLUSION", "GEOMETRIC", "LIGHTING", "BOUNDARY", "TEXTURE")]
    assert alpha == [1.0, 1.0, 0.6, 0.6, 0.3]


def test_high_priority_outweighs_low_by_the_beta_ratio_before_normalisation():
    params = SemanticParams.from_flat({"beta_high": 4.0, "beta_low": 0.25})
    high = region("left", "top", priority="HIGH")
    low = region("right", "bottom", priority="LOW")
    raw = weight_map([high, low], H, W, params, normalise=False)
    assert raw[80, 80] / raw[400, 560] == pytest.approx(4.0 / 0.25, rel=1e-3)


def test_weights_are_the_product_of_the_type_priority_and_size_weights():
    params = SemanticParams.from_flat(
        {"alpha_occlusion": 2.0, "alpha_texture": 0.5, "s_large": 1.5, "s_small": 0.25}
    )
    occ = region("left", "top", type_="OCCLUSION", size="large")
    tex = region("right", "bottom", type_="TEXTURE", size="small")
    raw = weight_map([occ, tex], H, W, params, normalise=False)
    # peak of a mask is 1: the raw map there is alpha * beta * s (beta HIGH = 3 for both)
    assert raw[80, 80] == pytest.approx(2.0 * 3.0 * 1.5, rel=1e-3)
    assert raw[400, 560] == pytest.approx(0.5 * 3.0 * 0.25, rel=1e-3)


def test_normalised_weight_map_has_max_one_and_overlaps_add():
    a = region("center-left", "middle", type_="OCCLUSION")
    b = region("center-left", "middle", type_="GEOMETRIC")
    c = region("right", "top", type_="TEXTURE", priority="LOW")
    w = weight_map([a, b, c], H, W)
    assert w.dtype == np.float32 and w.shape == (H, W)
    assert w.max() == pytest.approx(1.0) and w.min() >= 0.0
    assert w[240, 240] == pytest.approx(1.0)
    # the two overlapping regions add up: 2 x (1.0 x 3.0); the texture region alone: 0.3 x 0.5
    assert w[80, 560] == pytest.approx(0.3 * 0.5 / (2 * 1.0 * 3.0), rel=1e-3)


def test_no_regions_give_an_all_zero_map():
    assert not weight_map([], H, W).any()
    maps = weight_maps([region(image=1)], 3, 48, 64)
    assert maps.shape == (3, 48, 64)
    assert not maps[0].any() and maps[1].max() == pytest.approx(1.0) and not maps[2].any()


def test_semantic_uncertainty_is_the_normalised_modulated_sigma():
    rng = np.random.default_rng(1)
    sigma = rng.uniform(0.1, 0.9, (H, W)).astype(np.float32)
    weight = weight_map([region("left", "top")], H, W)
    lam = 1.0
    usem = semantic_uncertainty(sigma, weight, lam)
    raw = sigma * (1 + lam * weight)
    np.testing.assert_allclose(usem, raw / raw.max(), rtol=1e-6)
    assert usem.max() == pytest.approx(1.0)


def test_semantic_uncertainty_with_zero_weight_is_sigma_over_its_max():
    sigma = np.linspace(0, 0.5, H * W, dtype=np.float32).reshape(H, W)
    np.testing.assert_allclose(
        semantic_uncertainty(sigma, np.zeros_like(sigma)), sigma / 0.5, rtol=1e-6
    )


def test_semantic_uncertainty_is_zero_safe_and_keeps_nan():
    zero = semantic_uncertainty(np.zeros((4, 4)), np.ones((4, 4)))
    assert not zero.any() and np.isfinite(zero).all()
    sigma = np.full((4, 4), 0.5, np.float32)
    sigma[0, 0] = np.nan
    out = semantic_uncertainty(sigma, np.zeros((4, 4)))
    assert np.isnan(out[0, 0]) and out[1, 1] == pytest.approx(1.0)


def test_sigma_is_one_minus_confidence():
    conf = np.array([[0.0, 0.25], [1.0, 1.5]], np.float32)
    np.testing.assert_allclose(sigma_from_confidence(conf), [[1.0, 0.75], [0.0, 0.0]])


def test_params_from_flat_names_and_bad_values_are_rejected():
    params = SemanticParams.from_flat(
        {"alpha_texture": 0.9, "beta_high": 4.0, "s_large": 2.0, "lambda": 0.5}
    )
    assert params.alpha["TEXTURE"] == 0.9 and params.beta["HIGH"] == 4.0
    assert params.s["large"] == 2.0 and params.lam == 0.5
    assert params.beta["LOW"] == 0.5  # untouched defaults stay the paper's
    with pytest.raises(InputError, match="alpha_sparkle"):
        SemanticParams.from_flat({"alpha_sparkle": 1.0})
    with pytest.raises(InputError, match="lam"):
        SemanticParams(lam=-1.0)
    with pytest.raises(InputError, match="sigma"):
        semantic_uncertainty(np.zeros(5), np.zeros(5))
