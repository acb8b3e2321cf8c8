"""Every parameter the graph's nodes declare says what it does, in which unit, within which range."""

import dataclasses
import importlib
import re
from pathlib import Path

import pytest

from area3d_bringup.graph import NODES
from area3d_msgs_py.param_fields import description_of
from area3d_planner.config import PlannerConfig
from area3d_semantics.weights import SemanticParams

# Numbers whose unit is the number itself (weights, factors, seeds).
UNITLESS = {
    "gamma", "eta", "semantic_weight", "unobserved_uncertainty", "max_confidence", "seed",
    "noise_seed", "sensor.incidence_power", "sensor.edge_confidence", "sensor.edge_dropout",
    "retry_gain", "hard_max_confidence", "repeat_gain", "unobserved_far_weight",
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


def _documented_names(readme: Path) -> tuple[set[str], tuple[str, ...]]:
    """The names a README gives in backticks outside code blocks, with `a_min/max`, `a, b` and
    `alpha_x / _y` expanded, and the prefixes it covers with a star (`sensor.*`, `pose_*`)."""
    text = re.sub(r"```.*?```", "", readme.read_text(), flags=re.S)
    names: set[str] = set()
    prefixes: list[str] = []
    for line in text.splitlines():
        for quoted in re.findall(r"`([^`]+)`", line):
            parts = [part.strip() for part in re.split(r"\s*[,/]\s*", quoted) if part.strip()]
            for part in parts:
                if part.startswith("_") or part in ("max", "min"):  # alpha_a / _b, roi_min/max
                    stem = parts[0].rsplit("_", 1)[0]
                    part = f"{stem}{part}" if part.startswith("_") else f"{stem}_{part}"
                if re.fullmatch(r"\w+[._]\*", part):  # not a topic's `*/camera_info`
                    prefixes.append(part[:-1])
                names.add(part)
    return names, tuple(prefixes)


DOCUMENTED = [(node.package, node.module) for node in NODES]
DOCUMENTED += [("area3d_bringup", "area3d_bringup.foxglove_bridge")]


@pytest.mark.parametrize(("package", "module"), DOCUMENTED)
def test_every_declared_parameter_is_named_in_its_packages_readme(package, module):
    readme = Path(__file__).resolve().parents[2] / package / "README.md"
    names, prefixes = _documented_names(readme)
    missing = [
        p.name
        for p in importlib.import_module(module).PARAMS
        if p.name not in names
        and p.name.rsplit(".", 1)[-1] not in names  # a table of `sensor.` parameters
        and not p.name.startswith(prefixes)
    ]
    assert not missing, f"{package}/README.md does not name {missing}"
