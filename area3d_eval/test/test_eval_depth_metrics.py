"""Depth error and sparsification (AUSE) against known orderings."""

import numpy as np
import pytest

from area3d_eval.depth_metrics import ause, depth_errors, depth_right, sparsification_curve
from area3d_msgs_py.errors import InputError


def test_errors_count_only_pixels_valid_in_both_and_report_density():
    truth = np.array([[1.0, 2.0], [np.nan, 4.0]])
    estimate = np.array([[1.1, np.nan], [3.0, 4.0]])
    out = depth_errors(estimate, truth, confidence=np.array([[0.5, 1.0], [1.0, 0.9]]))
    np.testing.assert_allclose(out.abs_rel, [0.1, 0.0])
    np.testing.assert_allclose(out.confidence, [0.5, 0.9])
    assert out.density == pytest.approx(2 / 3)
    assert out.median_abs_rel == pytest.approx(0.05) and out.share_off == 0.5
    with pytest.raises(InputError, match="estimate"):
        depth_errors(estimate[:1], truth)


def test_a_confidence_ordering_pixels_like_their_errors_has_zero_ause():
    errors = np.random.default_rng(0).random(1000)
    assert ause(errors, -errors) == pytest.approx(0.0)
    assert ause(errors, 1.0 / (errors + 0.1)) == pytest.approx(0.0)  # any decreasing map
    curve = sparsification_curve(errors, -errors)
    assert curve[0] == pytest.approx(errors.mean()) and np.all(np.diff(curve) <= 1e-12)


def test_random_and_inverted_confidence_rank_worse_than_a_good_one():
    rng = np.random.default_rng(1)
    errors = rng.random(5000)
    noisy_good = -errors + rng.normal(0, 0.1, errors.size)
    assert ause(errors, noisy_good) < ause(errors, rng.random(errors.size)) < ause(errors, errors)


def test_a_depth_is_right_within_a_centimetre_and_a_percent_of_the_truth():
    truth = np.array([3.0, 3.0, 3.0, 1.0, np.nan], np.float32)
    estimate = np.array([3.0398, 2.9602, 3.0402, np.nan, 1.0], np.float32)
    assert depth_right(estimate, truth).tolist() == [True, True, False, False, False]
