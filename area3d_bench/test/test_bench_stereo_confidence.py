"""The calibration fit of `area3d bench stereo-confidence`, on generated samples."""

from __future__ import annotations

import numpy as np

from area3d_bench.stereo_confidence import auc, fit_logistic


def test_the_fit_recovers_the_weights_that_generated_the_samples():
    rng = np.random.default_rng(0)
    x = np.column_stack([rng.normal(2.5, 0.7, 60_000), rng.normal(0.3, 0.2, 60_000),
                         rng.uniform(0.0, 1.0, 60_000)])  # fmt: skip
    truth = np.array([2.0, -1.5, 4.0, -6.0])
    p = 1.0 / (1.0 + np.exp(-(x @ truth[:3] + truth[3])))
    right = rng.random(len(p)) < p
    fitted = np.array(fit_logistic(x, right))
    assert fitted.shape == (4,)
    assert np.allclose(fitted, truth, atol=0.15 * np.abs(truth).max())


def test_auc_is_one_for_a_separating_score_a_half_for_a_blind_one():
    right = np.array([True, True, False, False, True])
    assert auc(np.array([0.9, 0.8, 0.1, 0.2, 0.7]), right) == 1.0
    assert auc(np.array([0.1, 0.2, 0.9, 0.8, 0.3]), right) == 0.0
    assert auc(np.full(5, 0.5), right) == 0.5  # ties count half
    assert np.isnan(auc(np.ones(3), np.ones(3, bool)))  # no wrong pixel: undefined
