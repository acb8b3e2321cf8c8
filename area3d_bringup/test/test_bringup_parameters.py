"""Every parameter the graph's nodes declare says what it does, in which unit, within which range."""

import dataclasses
import importlib

import pytest

from area3d_bringup.graph import NODES
from area3d_msgs_py.param_fields import description_of
from area3d_planner.server import PlannerConfig
from area3d_semantics.weights import SemanticParams

# Numbers whose unit is the number itself (weights, factors, seeds).
UNITLESS = {
    "gamma", "eta", "semantic_weight", "unobserved_uncertainty", "max_confidence", "seed",
    "noise_seed", "sensor.incidence_power", "sensor.edge_confidence", "sensor.edge_dropout",
    "retry_gain", "hard_max_confidence", "repeat_gain",
    "stereo.p1_per_px", "stereo.p2_per_px", "stereo.downscale", "lambda",
}  # fmt: skip
UNITLESS |= {
    name for name, *_ in SemanticParams.flat_parameters() if name[:2] in ("al", "be", "s_")
}


def _params():
    for node in NODES:
        for param in importlib.import_module(node.module).PARAMS:
            yield pytest.param(param, id=f"{node.name}.{param.name}")


@pytest.mark.parametrize("param", _params())
def test_a_declared_parameter_is_described_with_its_unit_and_its_own_range(param):
    text = param.description
    assert len(text) > 12 and "Config." not in text and "Params." not in text, text
    is_number = isinstance(param.default, int | float) and not isinstance(param.default, bool)
    if is_number:
        assert param.range is not None, param.name
        lo, hi = param.range
        assert lo <= param.default <= hi, (param.name, param.default, param.range)
        assert (lo, hi) != (0, 1e6), f"{param.name}: the old shared placeholder range"
        if param.name not in UNITLESS:
            assert "," in text, f"{param.name}: a number says its unit after a comma: {text!r}"


def test_the_planners_parameters_are_its_configuration_fields_with_their_descriptions():
    planner = importlib.import_module("area3d_planner.node")
    declared = {p.name: p for p in planner.PARAMS}
    for field in dataclasses.fields(PlannerConfig):
        assert declared[field.name].description == description_of(field)
        assert declared[field.name].range == field.metadata["range"]
