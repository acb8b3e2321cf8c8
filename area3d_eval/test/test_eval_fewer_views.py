"""The views each policy takes to reach the reference policy's final completion."""

import numpy as np
import pytest

from area3d_eval.fewer_views import cell, markdown_lines, mean_curve, views_to_reach


def curve(*points):
    return [{"num_views": n, "completion": c} for n, c in points]


def test_a_row_reaches_the_reference_at_its_first_checkpoint_at_or_above_the_final_mean():
    uniform = [curve((4, 0.5), (8, 0.80), (12, 0.90)), curve((4, 0.5), (8, 0.82), (12, 0.92))]
    rows = {
        ("scene", "uniform"): uniform,
        # mean 0.905 at 8 (one seed above, one below the target 0.91) and 0.915 at 9
        ("scene", "area3d"): [
            curve((4, 0.5), (8, 0.90), (9, 0.91), (12, 0.95)),
            curve((4, 0.5), (8, 0.91), (9, 0.92), (12, 0.95)),
        ],
        ("scene", "random"): [curve((4, 0.5), (8, 0.70), (12, 0.85))],
        ("other", "area3d"): [curve((4, 0.5), (8, 0.99))],  # no uniform ran there
    }
    found = {(e["scene"], e["label"]): e for e in views_to_reach(rows)}
    assert set(found) == {("scene", "uniform"), ("scene", "area3d"), ("scene", "random")}
    assert all(e["target"] == pytest.approx(0.91) for e in found.values())
    assert (
        found[("scene", "area3d")]["views"] == 9 and found[("scene", "area3d")]["last_views"] == 12
    )
    assert found[("scene", "uniform")]["views"] == 12  # its own final mean, at its last view
    assert found[("scene", "random")]["views"] is None
    assert found[("scene", "random")]["last"] == pytest.approx(0.85)
    assert cell(found[("scene", "area3d")]) == "9 of 12 (75 %)"
    assert cell(found[("scene", "random")]) == "not reached (0.850 < 0.910)"
    table = markdown_lines(list(found.values()))
    assert (
        "| area3d | 9 of 12 (75 %) |" in table
        and "| random | not reached (0.850 < 0.910) |" in table
    )


def test_the_mean_curve_keeps_the_checkpoints_every_run_has_with_a_finite_value():
    runs = [
        curve((4, 0.4), (8, 0.8), (9, 0.85), (12, 0.9)),
        curve((4, 0.6), (8, float("nan")), (12, 1.0)),  # no checkpoint at 9; 8 undefined
    ]
    mean = mean_curve(runs)
    assert list(mean) == [4, 12]
    assert mean[4] == pytest.approx(0.5) and mean[12] == pytest.approx(0.95)
    assert mean_curve([]) == {} and not views_to_reach({("s", "area3d"): runs})


def test_a_reference_that_plateaus_is_reached_before_its_last_view():
    flat = [curve((4, 0.5), (8, 0.9), (12, 0.9))]
    (entry,) = views_to_reach({("s", "uniform"): flat})
    assert entry["views"] == 8 and np.isclose(entry["target"], 0.9)
